"""The scikit-learn face of the batched decoders: fit on (X, y), predict probabilities."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.utils.validation import check_is_fitted, validate_data

from decoding.statistics import BatchedDecoders, ClassStatistics, one_hot


class StatisticsClassifier(ClassifierMixin, BaseEstimator):
    """A classifier fitted from class statistics (subclasses set ``_fit_statistics`` and
    ``_min_count``).

    Parameters
    ----------
    shrinkage : float
        Covariance shrinkage towards the scaled identity, in [0, 1].

    Attributes
    ----------
    classes_ : ndarray, shape (n_classes,)
    decoders_ : BatchedDecoders
        The fitted decoder (no batch axes).
    """

    _fit_statistics: Callable[[ClassStatistics, float], BatchedDecoders]

    def __init__(self, shrinkage: float) -> None:
        self.shrinkage = shrinkage

    def _min_count(self, n_features: int) -> float:
        """Signals every class needs (a class with fewer would take no part)."""
        raise NotImplementedError

    def fit(self, X: np.ndarray, y: np.ndarray) -> StatisticsClassifier:
        """Fit on signals ``X`` (n_signals, n_features) with labels ``y`` (n_signals,)."""
        if not 0.0 <= float(self.shrinkage) <= 1.0:
            raise ValueError(f"shrinkage must be in [0, 1]; got {self.shrinkage!r}")
        X, y = validate_data(self, X, y)
        self.classes_, encoded = np.unique(y, return_inverse=True)
        name = type(self).__name__
        if len(self.classes_) < 2:
            raise ValueError(f"{name} needs at least 2 classes in y")
        statistics = ClassStatistics.from_signals(X, one_hot(encoded, len(self.classes_)))
        minimum = self._min_count(X.shape[1])
        if np.any(statistics.counts < minimum):
            raise ValueError(
                f"{name}: every class needs at least {minimum:g} signals; got class counts "
                f"{statistics.counts.astype(int).tolist()}"
            )
        self.decoders_ = type(self)._fit_statistics(statistics, float(self.shrinkage))
        return self

    def predict_log_proba(self, X: np.ndarray) -> np.ndarray:
        """Log class probabilities, shape (n_signals, n_classes)."""
        check_is_fitted(self)
        return self.decoders_.log_proba(validate_data(self, X, reset=False))

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        """Class probabilities, shape (n_signals, n_classes)."""
        return np.exp(self.predict_log_proba(X))

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Most probable class of each signal, shape (n_signals,)."""
        return self.classes_[np.argmax(self.predict_log_proba(X), axis=1)]
