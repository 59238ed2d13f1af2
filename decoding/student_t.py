"""The thesis's Student-t decoder, batched over label hypotheses.

Each class is a Gaussian with unknown mean and covariance under the non-informative
(Jeffreys) prior. Integrating them out gives, for a class with ``n`` signals in ``d``
dimensions, a multivariate Student-t predictive with ``nu = n - d`` degrees of freedom,
location the class mean and scale ``S (n + 1) / (n nu)``, where ``S`` is the class scatter
matrix (shrunk towards the identity scaled to its mean variance, as in the thesis's
"shrink 0.5"). Class probabilities are the normalised predictive densities (equal priors).
A class with ``n <= d`` signals has an improper predictive: it takes no part (probability
0); while fewer than two classes take part the decoder gives no information (uniform).

**The thesis code's count** (``counts="total"``): the thesis's
``GaussianUninformativePrior_classifier`` (lfui) puts the *total* number of signals ``N``
of the training set in place of ``n`` for every class (``nu = N - d``, scale
``S (N + 1) / (N nu)`` with ``S = Sigma (N - 1)``, ``Sigma`` the class's weighted, shrunk
covariance), although each class's mean and covariance come from its own (soft-labelled)
signals. Every class then takes part as soon as the training set has more signals than
dimensions, however few of them it holds, provided it has a covariance of its own: with
hard labels (the thesis trains on soft ones, where every class weighs every signal) a
class needs a weight of at least 2 (`MIN_CLASS_WEIGHT`) and signals that are not
all the same (`MIN_RELATIVE_SPREAD`); without shrinkage, more signals than
dimensions. ``N`` is the sum of the class weights, the number of signals when every
signal is labelled. The default,
``counts="class"``, is the exact predictive of each class's own data.
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
    at_least,
    log_softmax,
    more_than,
    shrink_towards_identity,
    spd_inverse,
)
from decoding.validation import check_option

#: How the predictive counts a class's signals (see `fit_student_t`).
STUDENT_T_COUNTS: tuple[str, ...] = ("class", "total")

#: Weight a class needs with ``counts="total"``: two signals give it a covariance.
MIN_CLASS_WEIGHT = 2.0

#: With ``counts="total"``, a class whose total variance is below this fraction of its
#: signals' mean squared norm holds copies of one signal (rounding leaves ~1e-16): no
#: covariance of its own.
MIN_RELATIVE_SPREAD = 1e-9


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
    statistics: ClassStatistics,
    shrinkage: float = DEFAULT_SHRINKAGE,
    counts: str = "class",
) -> StudentTDecoders:
    """Student-t predictive decoders from class statistics (batched over leading axes).

    Parameters
    ----------
    statistics : ClassStatistics
        Class statistics, batch shape ``B``.
    shrinkage : float, default 0.5
        Weight of the scaled-identity target in each class scatter, in [0, 1].
    counts : {"class", "total"}, default "class"
        The ``n`` of each class's predictive: its own weight, or the training set's total
        weight for every class (the thesis code's, see the module docstring).
    """
    check_option("counts", counts, STUDENT_T_COUNTS)
    means, covariances = statistics.class_moments()
    n_features = means.shape[-1]
    own = statistics.counts
    if counts == "class":  # S: the class's scatter about its mean
        counts, present, scatter_weight = own, more_than(own, n_features), own
    else:  # S = Sigma (N - 1), as the thesis code computes it
        counts = np.broadcast_to(own.sum(axis=-1, keepdims=True), own.shape)
        present = more_than(counts, n_features) & _has_own_covariance(
            statistics, covariances, shrinkage
        )
        scatter_weight = counts - 1.0
    dof = np.maximum(counts - n_features, 1.0)
    scatter = shrink_towards_identity(covariances * scatter_weight[..., None, None], shrinkage)
    scale = scatter * ((counts + 1.0) / (np.maximum(counts, 1.0) * dof))[..., None, None]
    scale = np.where(present[..., None, None], scale, np.eye(n_features))
    precisions, log_det = spd_inverse(scale)
    log_norm = (
        gammaln(0.5 * (dof + n_features))
        - gammaln(0.5 * dof)
        - 0.5 * n_features * np.log(np.pi * dof)
        - 0.5 * log_det
    )
    return StudentTDecoders(
        means=means,
        precisions=precisions,
        log_norm=np.where(present, log_norm, -np.inf),
        dof=dof,
        present=present,
    )


def _has_own_covariance(
    statistics: ClassStatistics, covariances: np.ndarray, shrinkage: float
) -> np.ndarray:
    """Classes whose shrunk covariance is positive definite, shape (*B, n_classes):
    weight at least `MIN_CLASS_WEIGHT` (more than ``d`` without shrinkage) and
    signals spread beyond `MIN_RELATIVE_SPREAD`."""
    counts = statistics.counts
    n_features = covariances.shape[-1]
    enough = (
        at_least(counts, MIN_CLASS_WEIGHT) if shrinkage > 0 else more_than(counts, n_features)
    )
    variance = np.trace(covariances, axis1=-2, axis2=-1)
    power = np.trace(statistics.scatters, axis1=-2, axis2=-1) / np.maximum(
        counts, np.finfo(float).tiny
    )
    return enough & (variance > MIN_RELATIVE_SPREAD * power)


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
