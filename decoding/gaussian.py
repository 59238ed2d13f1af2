"""A plain Gaussian decoder (quadratic discriminant analysis), batched over label hypotheses.

Each class is one Gaussian with the class's weighted mean and (biased) weighted
covariance, shrunk towards the identity scaled to its mean variance,
``Sigma_k = (1 - lambda) C_k + lambda tr(C_k) / d I`` (the thesis's "shrink 0.5"); class
probabilities are the normalised densities with equal priors:
``log p(k | x) = log_softmax(-(x - mu_k)^T Sigma_k^-1 (x - mu_k) / 2 - ln det Sigma_k / 2)``.
A class with less than ``MIN_CLASS_COUNT`` weight, or whose shrunk covariance is singular
(no shrinkage and fewer signals than features), takes no part (probability 0); while fewer
than two classes take part the decoder gives no information (uniform).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from decoding.estimator import StatisticsClassifier
from decoding.lda import DEFAULT_SHRINKAGE, MIN_CLASS_COUNT
from decoding.statistics import (
    BatchedDecoders,
    ClassStatistics,
    at_least,
    log_softmax,
    shrink_towards_identity,
)

#: Smallest eigenvalue of a shrunk class covariance, relative to its largest, below which
#: it counts as singular (the class then takes no part).
_SINGULAR = 1e-10


@dataclass(frozen=True)
class GaussianDecoders(BatchedDecoders):
    """A batch of per-class Gaussian decoders.

    Attributes
    ----------
    means : ndarray, shape (*B, n_classes, n_features)
    precisions : ndarray, shape (*B, n_classes, n_features, n_features)
        Inverse shrunk class covariances (the identity for absent classes).
    log_norm : ndarray, shape (*B, n_classes)
        ``-ln det Sigma_k / 2`` (the ``2 pi`` term is common to every class); -inf for
        absent classes.
    present : ndarray, shape (*B, n_classes), bool
        Classes that take part.
    """

    means: np.ndarray
    precisions: np.ndarray
    log_norm: np.ndarray
    present: np.ndarray

    def _known_log_proba(self, X: np.ndarray) -> np.ndarray:
        centred = X[..., None, :, :] - self.means[..., :, None, :]  # (*B, K, n, d)
        mahalanobis = np.sum((centred @ self.precisions) * centred, axis=-1)
        log_density = self.log_norm[..., None] - 0.5 * mahalanobis
        return log_softmax(np.swapaxes(log_density, -1, -2))


def fit_gaussian(
    statistics: ClassStatistics, shrinkage: float = DEFAULT_SHRINKAGE
) -> GaussianDecoders:
    """Gaussian class decoders from class statistics (batched over leading axes)."""
    means, covariances = statistics.class_moments()
    n_features = means.shape[-1]
    covariances = shrink_towards_identity(covariances, shrinkage)
    eigenvalues, vectors = np.linalg.eigh(covariances)
    regular = eigenvalues[..., 0] > _SINGULAR * np.maximum(eigenvalues[..., -1], 0.0)
    present = at_least(statistics.counts, MIN_CLASS_COUNT) & regular
    eigenvalues = np.where(present[..., None], eigenvalues, 1.0)
    vectors = np.where(present[..., None, None], vectors, np.eye(n_features))
    precisions = (vectors / eigenvalues[..., None, :]) @ np.swapaxes(vectors, -1, -2)
    return GaussianDecoders(
        means=means,
        precisions=precisions,
        log_norm=np.where(present, -0.5 * np.log(eigenvalues).sum(axis=-1), -np.inf),
        present=present,
    )


class GaussianClassifier(StatisticsClassifier):
    """Gaussian classifier (QDA) with shrunk class covariances and equal class priors.

    Parameters
    ----------
    shrinkage : float, default 0.5
        Weight of the scaled-identity target in each class covariance, in [0, 1].

    Attributes
    ----------
    classes_ : ndarray, shape (n_classes,)
    decoders_ : GaussianDecoders
        The fitted class Gaussians (no batch axes).
    """

    _fit_statistics = staticmethod(fit_gaussian)

    def __init__(self, shrinkage: float = DEFAULT_SHRINKAGE) -> None:
        super().__init__(shrinkage)

    def _min_count(self, n_features: int) -> float:
        return MIN_CLASS_COUNT
