"""The thesis's Student-t decoder, batched over label hypotheses.

Each class is a Gaussian with unknown mean and covariance under the non-informative
(Jeffreys) prior. Integrating them out gives, for a class with ``n`` signals in ``d``
dimensions, a multivariate Student-t predictive with ``nu = n - d`` degrees of freedom,
location the class mean and scale ``S (n + 1) / (n nu)``, where ``S`` is the class scatter
matrix (shrunk towards the identity scaled to its mean variance, as in the thesis's
"shrink 0.5"). Class probabilities are the normalised predictive densities (equal priors).
A class with ``n <= d`` signals has an improper predictive: it takes no part (probability
0); while fewer than two classes take part the decoder gives no information (uniform).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaln

from decoding.estimator import StatisticsClassifier
from decoding.lda import DEFAULT_SHRINKAGE
from decoding.statistics import (
    BatchedDecoders,
    ClassStatistics,
    log_softmax,
    shrink_towards_identity,
)


@dataclass(frozen=True)
class StudentTDecoders(BatchedDecoders):
    """A batch of per-class Student-t predictive decoders.

    Attributes
    ----------
    means : ndarray, shape (*B, n_classes, n_features)
    precisions : ndarray, shape (*B, n_classes, n_features, n_features)
        Inverse scale matrices.
    log_norm : ndarray, shape (*B, n_classes)
        Log normalising constant of each class density.
    dof : ndarray, shape (*B, n_classes)
        Degrees of freedom ``n - d``.
    present : ndarray, shape (*B, n_classes), bool
        Classes that take part (more signals than features); the others get probability
        0. A decoder with fewer than two present classes is uninformative (uniform).
    """

    means: np.ndarray
    precisions: np.ndarray
    log_norm: np.ndarray
    dof: np.ndarray
    present: np.ndarray

    def _known_log_proba(self, X: np.ndarray) -> np.ndarray:
        centred = X[..., None, :, :] - self.means[..., :, None, :]
        # (x - mu)^T P (x - mu) per class and signal, as a batched matrix product (BLAS)
        # rather than a three-operand einsum, which numpy runs as a plain loop.
        mahalanobis = np.sum((centred @ self.precisions) * centred, axis=-1)
        n_features = X.shape[-1]
        dof = self.dof[..., None]
        log_density = self.log_norm[..., None] - 0.5 * (dof + n_features) * np.log1p(
            mahalanobis / dof
        )
        return log_softmax(np.swapaxes(log_density, -1, -2))


def fit_student_t(
    statistics: ClassStatistics, shrinkage: float = DEFAULT_SHRINKAGE
) -> StudentTDecoders:
    """Student-t predictive decoders from class statistics (batched over leading axes)."""
    means, covariances = statistics.class_moments()
    n_features = means.shape[-1]
    counts = statistics.counts
    present = counts > n_features
    dof = np.maximum(counts - n_features, 1.0)
    scatter = shrink_towards_identity(covariances * counts[..., None, None], shrinkage)
    scale = scatter * ((counts + 1.0) / (np.maximum(counts, 1.0) * dof))[..., None, None]
    scale = np.where(present[..., None, None], scale, np.eye(n_features))
    _, log_det = np.linalg.slogdet(scale)
    log_norm = (
        gammaln(0.5 * (dof + n_features))
        - gammaln(0.5 * dof)
        - 0.5 * n_features * np.log(np.pi * dof)
        - 0.5 * log_det
    )
    return StudentTDecoders(
        means=means,
        precisions=np.linalg.inv(scale),
        log_norm=np.where(present, log_norm, -np.inf),
        dof=dof,
        present=present,
    )


class StudentTClassifier(StatisticsClassifier):
    """Bayesian Gaussian classifier with a Student-t predictive per class (equal priors).

    Parameters
    ----------
    shrinkage : float, default 0.5
        Weight of the scaled-identity target in each class scatter matrix, in [0, 1].

    Attributes
    ----------
    classes_ : ndarray, shape (n_classes,)
    decoders_ : StudentTDecoders
        The fitted class predictives (no batch axes).
    """

    _fit_statistics = staticmethod(fit_student_t)

    def __init__(self, shrinkage: float = DEFAULT_SHRINKAGE) -> None:
        super().__init__(shrinkage)

    def _min_count(self, n_features: int) -> float:
        return n_features + 1
