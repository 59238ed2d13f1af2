"""Shrinkage linear discriminant analysis, batched over label hypotheses.

The model is scikit-learn's ``LinearDiscriminantAnalysis(solver="lsqr",
shrinkage=shrinkage, priors=<equal>)``: a covariance shared by the classes, the equally
weighted mean of the class covariances, shrunk towards the identity scaled to their
mean variance; linear scores ``x Sigma^-1 mu_k - mu_k Sigma^-1 mu_k / 2 + log(1 / K)``
and a softmax.
:func:`fit_lda` computes it from :class:`~decoding.statistics.ClassStatistics` with any
leading batch shape, so the decoders of all tasks and all cross-validation folds are one
batched linear solve.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from scipy.special import log_softmax
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.utils.validation import check_is_fitted, validate_data

from decoding.statistics import ClassStatistics, one_hot, shrink_towards_identity

DEFAULT_SHRINKAGE = 0.5
#: A class needs this much (weighted) data before a decoder that uses it is informative.
MIN_CLASS_COUNT = 2.0


@dataclass(frozen=True)
class LinearDecoders:
    """A batch of linear decoders ``log p(k | x) = log_softmax(x W + b)``.

    Attributes
    ----------
    coef : ndarray, shape (*B, n_features, n_classes)
    intercept : ndarray, shape (*B, n_classes)
    informative : ndarray, shape (*B,), bool
        False where some class had too little data: that decoder predicts uniformly.
    """

    coef: np.ndarray
    intercept: np.ndarray
    informative: np.ndarray

    def log_proba(self, X: np.ndarray) -> np.ndarray:
        """Log class probabilities of signals ``X`` (n, d) under every decoder: (*B, n, K)."""
        scores = np.einsum("nd,...dk->...nk", X, self.coef) + self.intercept[..., None, :]
        log_p = log_softmax(scores, axis=-1)
        uniform = -np.log(self.coef.shape[-1])
        return np.where(self.informative[..., None, None], log_p, uniform)

    def select(self, index: object) -> LinearDecoders:
        """The decoders at ``index`` of the batch axes (numpy indexing)."""
        return LinearDecoders(*(getattr(self, f.name)[index] for f in fields(self)))


def fit_lda(statistics: ClassStatistics, shrinkage: float = DEFAULT_SHRINKAGE) -> LinearDecoders:
    """Shrinkage-LDA decoders from class statistics (batched over leading axes)."""
    means, covariances = statistics.class_moments()
    n_classes = means.shape[-2]
    shared = shrink_towards_identity(covariances.mean(axis=-3), shrinkage)
    informative = np.all(statistics.counts >= MIN_CLASS_COUNT, axis=-1)
    # Uninformative decoders get a harmless identity system instead of a singular one.
    eye = np.eye(shared.shape[-1])
    shared = np.where(informative[..., None, None], shared, eye)
    coef = np.linalg.solve(shared, np.swapaxes(means, -1, -2))
    intercept = -0.5 * np.einsum("...kd,...dk->...k", means, coef) - np.log(n_classes)
    return LinearDecoders(coef=coef, intercept=intercept, informative=informative)


class ShrinkageLDA(ClassifierMixin, BaseEstimator):
    """Shrinkage LDA with equal class priors, as used by every task hypothesis.

    Equivalent to ``LinearDiscriminantAnalysis(solver="lsqr", shrinkage=shrinkage,
    priors=<equal>)``, computed from class statistics (see :func:`fit_lda`).

    Parameters
    ----------
    shrinkage : float, default 0.5
        Weight of the diagonal target in the shared covariance, in [0, 1].

    Attributes
    ----------
    classes_ : ndarray, shape (n_classes,)
    coef_ : ndarray, shape (n_features, n_classes)
    intercept_ : ndarray, shape (n_classes,)

    Examples
    --------
    >>> import numpy as np
    >>> X = np.r_[np.random.default_rng(0).normal(size=(20, 3)), np.ones((20, 3))]
    >>> ShrinkageLDA().fit(X, [0] * 20 + [1] * 20).predict(np.ones((1, 3)))
    array([1])
    """

    def __init__(self, shrinkage: float = DEFAULT_SHRINKAGE) -> None:
        self.shrinkage = shrinkage

    def fit(self, X: np.ndarray, y: np.ndarray) -> ShrinkageLDA:
        """Fit on signals ``X`` (n_signals, n_features) with labels ``y`` (n_signals,)."""
        if not 0.0 <= float(self.shrinkage) <= 1.0:
            raise ValueError(f"shrinkage must be in [0, 1]; got {self.shrinkage!r}")
        X, y = validate_data(self, X, y)
        self.classes_, encoded = np.unique(y, return_inverse=True)
        if len(self.classes_) < 2:
            raise ValueError("ShrinkageLDA needs at least 2 classes in y")
        statistics = ClassStatistics.from_signals(X, one_hot(encoded, len(self.classes_)))
        decoders = fit_lda(statistics, float(self.shrinkage))
        if not decoders.informative:
            raise ValueError(f"every class needs at least {MIN_CLASS_COUNT:g} signals")
        self.coef_, self.intercept_ = decoders.coef, decoders.intercept
        return self

    def predict_log_proba(self, X: np.ndarray) -> np.ndarray:
        """Log class probabilities, shape (n_signals, n_classes)."""
        check_is_fitted(self)
        X = validate_data(self, X, reset=False)
        return log_softmax(X @ self.coef_ + self.intercept_, axis=-1)

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        """Class probabilities, shape (n_signals, n_classes)."""
        return np.exp(self.predict_log_proba(X))

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Most probable class of each signal, shape (n_signals,)."""
        return self.classes_[np.argmax(self.predict_log_proba(X), axis=1)]
