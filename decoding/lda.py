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

from dataclasses import dataclass

import numpy as np

from decoding.estimator import StatisticsClassifier
from decoding.statistics import (
    BatchedDecoders,
    Statistics,
    log_softmax,
    shrink_towards_identity,
    solve_spd,
)

DEFAULT_SHRINKAGE = 0.5
#: A class needs this much (weighted) data before a decoder that uses it is informative.
MIN_CLASS_COUNT = 2.0


@dataclass(frozen=True)
class LinearDecoders(BatchedDecoders):
    """A batch of linear decoders ``log p(k | x) = log_softmax(x W + b)``.

    Attributes
    ----------
    coef : ndarray, shape (*B, n_features, n_classes)
    intercept : ndarray, shape (*B, n_classes)
    present : ndarray, shape (*B, n_classes), bool
        Classes with enough data to take part; the others get probability 0. A decoder
        with fewer than two present classes is uninformative and predicts uniformly.
    """

    coef: np.ndarray
    intercept: np.ndarray
    present: np.ndarray

    def _known_log_proba(self, X: np.ndarray) -> np.ndarray:
        return log_softmax(X @ self.coef + self.intercept[..., None, :])


def fit_lda(statistics: Statistics, shrinkage: float = DEFAULT_SHRINKAGE) -> LinearDecoders:
    """Shrinkage-LDA decoders from class statistics (batched over leading axes).

    Only the classes with at least ``MIN_CLASS_COUNT`` signals take part (equal priors
    among them); the others get probability 0, as a scikit-learn model fitted on the
    classes it has seen. A decoder with fewer than two such classes is uninformative.
    """
    counts = statistics.counts
    present = counts >= MIN_CLASS_COUNT
    n_present = present.sum(axis=-1)
    informative = n_present >= 2
    safe_counts = np.where(present, counts, 1.0)
    means = np.where(present[..., None], statistics.sums / safe_counts[..., None], 0.0)
    # The equally weighted mean of the present classes' covariances, without forming each:
    # sum_k (scatter_k / n_k - mu_k mu_k^T) / K.
    class_weights = np.where(present, 1.0 / np.maximum(n_present, 1)[..., None], 0.0)
    n_features = means.shape[-1]
    shared = statistics.weighted_scatter(class_weights / safe_counts)
    shared -= np.swapaxes(means * class_weights[..., None], -1, -2) @ means
    shared = shrink_towards_identity(shared, shrinkage)
    # Uninformative decoders get a harmless identity system instead of a singular one.
    shared[~informative] = np.eye(n_features)
    coef = solve_spd(shared, np.swapaxes(means, -1, -2))
    with np.errstate(divide="ignore"):
        log_priors = np.log(class_weights)
    intercept = -0.5 * np.einsum("...kd,...dk->...k", means, coef) + log_priors
    return LinearDecoders(coef=coef, intercept=intercept, present=present)


class ShrinkageLDA(StatisticsClassifier):
    """Shrinkage LDA with equal class priors, as used by every task hypothesis.

    Equivalent to ``LinearDiscriminantAnalysis(solver="lsqr", shrinkage=shrinkage,
    priors=<equal>)``, computed from class statistics (see :func:`fit_lda`).

    Parameters
    ----------
    shrinkage : float, default 0.5
        Weight of the scaled-identity target in the shared covariance, in [0, 1].

    Attributes
    ----------
    classes_ : ndarray, shape (n_classes,)
    decoders_ : LinearDecoders
        ``coef`` (n_features, n_classes) and ``intercept`` (n_classes,).

    Examples
    --------
    >>> import numpy as np
    >>> X = np.r_[np.random.default_rng(0).normal(size=(20, 3)), np.ones((20, 3))]
    >>> ShrinkageLDA().fit(X, [0] * 20 + [1] * 20).predict(np.ones((1, 3)))
    array([1])
    """

    _fit_statistics = staticmethod(fit_lda)

    def __init__(self, shrinkage: float = DEFAULT_SHRINKAGE) -> None:
        super().__init__(shrinkage)

    def _min_count(self, n_features: int) -> float:
        return MIN_CLASS_COUNT
