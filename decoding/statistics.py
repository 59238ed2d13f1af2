"""Sufficient statistics of the decoders: per-class weighted counts, sums and scatters, and
the pooled form that many labellings of the same signals share.

Every decoder of the project is a function of these statistics only, so the decoders of
many label hypotheses over the same signals can share and update them incrementally.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Self

import numpy as np

from decoding.scatter_eigen import ScatterEigen

#: Weight below which a class (or the unlabelled rest of the signals) counts as empty: a
#: held-out fold's count of a class whose weight is all in that fold is the difference of
#: two sums, and may be a rounding residue of either sign.
EMPTY_WEIGHT = 1e-9


def at_least(counts: np.ndarray, minimum: float) -> np.ndarray:
    """Where the (weighted) ``counts`` reach ``minimum`` up to a rounding residue
    (`EMPTY_WEIGHT`): soft labels split in halves sum to a whole count in exact
    arithmetic, and a decoder's classes must not turn on the last bit of that sum."""
    return counts >= minimum - EMPTY_WEIGHT


def more_than(counts: np.ndarray, minimum: float) -> np.ndarray:
    """Where the (weighted) ``counts`` exceed ``minimum`` by more than a rounding residue
    (`EMPTY_WEIGHT`): a count equal to it in exact arithmetic does not, whatever
    its last bit (see `at_least`)."""
    return counts > minimum + EMPTY_WEIGHT


@dataclass(frozen=True)
class ClassStatistics:
    """Weighted per-class statistics, with any leading batch shape ``B``.

    Attributes
    ----------
    counts : ndarray, shape (*B, n_classes)
        Sum of the class weights of the signals (the number of signals for hard labels).
    sums : ndarray, shape (*B, n_classes, n_features)
        Weighted sum of the signals of each class.
    scatters : ndarray, shape (*B, n_classes, n_features, n_features)
        Weighted sum of the outer products ``x x^T`` (not centred).
    """

    counts: np.ndarray
    sums: np.ndarray
    scatters: np.ndarray

    @classmethod
    def from_signals(cls, X: np.ndarray, weights: np.ndarray) -> ClassStatistics:
        """Statistics of signals ``X`` (n, d) with class weights ``weights`` (n, *B, K)."""
        X = np.asarray(X, dtype=float)
        weights = np.asarray(weights, dtype=float)
        return cls(
            counts=weights.sum(axis=0),
            sums=np.einsum("n...k,ni->...ki", weights, X),
            scatters=np.einsum("n...k,ni,nj->...kij", weights, X, X, optimize=True),
        )

    def class_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Class means (*B, K, d) and biased class covariances (*B, K, d, d).

        Classes with no weight (at most `EMPTY_WEIGHT`, a rounding residue) get zero
        mean and covariance (their decoder is marked uninformative by the caller).
        """
        empty = self.counts <= EMPTY_WEIGHT
        counts = np.where(empty, 1.0, self.counts)
        means = self.sums / counts[..., None]
        means[empty] = 0.0
        covariances = self.scatters / counts[..., None, None]
        covariances -= means[..., :, None] * means[..., None, :]
        covariances[empty] = 0.0
        return means, covariances


@dataclass(frozen=True)
class PooledStatistics:
    """What pooled-covariance decoders need of a batch of labellings of shared signals.

    The signals of a training set are shared by every labelling (task hypothesis) of it;
    only their split into classes differs. So the d x d statistic is one per training
    set, and per labelling only class counts and sums are kept.

    A signal's class weights sum to 1, or to less: the rest of its unit weight (all of it
    for a signal a labelling gives no label) belongs to no class. Such signals form a
    class of their own for the pooled covariance (their spread around their own mean
    joins it) but no decoder class.

    Attributes
    ----------
    scatter : ndarray, shape (*J, n_features, n_features)
        Uncentred scatter ``sum_i x_i x_i^T`` of each training set's signals.
    n_signals : ndarray, shape (*J,)
        Number of signals of each training set.
    signal_sum : ndarray, shape (*J, n_features)
        Sum of each training set's signals.
    counts : ndarray, shape (*J, *T, n_classes)
        Per training set and labelling, the class weights summed over the signals.
    sums : ndarray, shape (*J, *T, n_classes, n_features)
        Per training set and labelling, the class-weighted sums of the signals.
    eigen : ScatterEigen or None
        ``scatter`` as an earlier eigendecomposition plus the signals added since
        (`decoding.scatter_eigen`), or None: the decoders decompose ``scatter``.
    """

    scatter: np.ndarray
    n_signals: np.ndarray
    signal_sum: np.ndarray
    counts: np.ndarray
    sums: np.ndarray
    eigen: ScatterEigen | None = None

    @classmethod
    def from_class_statistics(cls, statistics: ClassStatistics) -> PooledStatistics:
        """One labelling (no ``T`` axes) from its class statistics; every signal's weights
        must sum to 1 (hard or soft labels, every signal labelled)."""
        return cls(
            scatter=statistics.scatters.sum(axis=-3),
            n_signals=statistics.counts.sum(axis=-1),
            signal_sum=statistics.sums.sum(axis=-2),
            counts=statistics.counts,
            sums=statistics.sums,
        )

    @property
    def n_task_axes(self) -> int:
        """Number of labelling axes ``T``."""
        return self.counts.ndim - self.n_signals.ndim - 1

    def per_task(self, shared: np.ndarray, trailing: int) -> np.ndarray:
        """A shared array (*J, *trailing) with unit axes for ``T``: (*J, 1.., *trailing)."""
        lead = shared.shape[: shared.ndim - trailing]
        return shared.reshape((*lead, *(1,) * self.n_task_axes, *shared.shape[len(lead) :]))


class BatchedDecoders:
    """What every batch of decoders shares (subclasses are dataclasses with a ``present``
    field, shape (*B, n_classes), bool, and compute `_known_log_proba`)."""

    present: np.ndarray

    @property
    def informative(self) -> np.ndarray:
        """Decoders with at least two present classes, shape (*B,), bool."""
        return self.present.sum(axis=-1) >= 2

    def _known_log_proba(self, X: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def log_proba(self, X: np.ndarray) -> np.ndarray:
        """Log class probabilities of signals ``X`` (n, d) under every decoder: (*B, n, K).

        ``X`` may also have leading axes that broadcast against ``B`` (e.g. (n_folds, 1,
        n, d) against B = (n_folds, n_tasks): each fold's decoders score their own
        signals).

        Absent classes get probability 0; uninformative decoders give uniform probabilities.
        """
        uniform = -np.log(self.present.shape[-1])
        return np.where(self.informative[..., None, None], self._known_log_proba(X), uniform)

    def proba(self, X: np.ndarray) -> np.ndarray:
        """Class probabilities, as `log_proba` (subclasses may compute them directly)."""
        return np.exp(self.log_proba(X))

    def select(self, index: object) -> Self:
        """The decoders at ``index`` of the leading batch axes (numpy indexing)."""
        return type(self)(*(getattr(self, f.name)[index] for f in fields(self)))


def one_hot(labels: np.ndarray, n_classes: int) -> np.ndarray:
    """Hard labels (n,) in 0..n_classes-1 as weights (n, n_classes)."""
    return np.eye(n_classes)[np.asarray(labels, dtype=np.intp)]


def spd_inverse(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses and log-determinants of symmetric positive-definite matrices.

    From one Cholesky factorisation ``A = L L^T``: ``A^-1 = L^-T L^-1`` with ``L^-1``
    by forward substitution, one row at a time over the whole batch, and
    ``log det A = 2 sum log diag L``. About twice as fast as ``np.linalg.inv`` with
    ``np.linalg.slogdet`` on batches of small matrices, whose cost is per matrix.

    Parameters
    ----------
    matrices : ndarray, shape (*B, d, d)

    Returns
    -------
    inverses : ndarray, shape (*B, d, d)
    log_det : ndarray, shape (*B,)

    Raises
    ------
    numpy.linalg.LinAlgError
        A matrix is not positive definite.
    """
    factor = np.linalg.cholesky(matrices)
    diagonal = np.diagonal(factor, axis1=-2, axis2=-1)
    inverse = np.zeros_like(factor)  # L^-1, lower triangular
    for j in range(matrices.shape[-1]):
        if j:
            inverse[..., j, :j] = -np.einsum(
                "...i,...ik->...k", factor[..., j, :j], inverse[..., :j, :j]
            )
        inverse[..., j, j] = 1.0
        inverse[..., j, : j + 1] /= diagonal[..., j, None]
    return np.swapaxes(inverse, -1, -2) @ inverse, 2.0 * np.log(diagonal).sum(axis=-1)


def shrink_towards_identity(covariance: np.ndarray, shrinkage: float) -> np.ndarray:
    """``(1 - shrinkage) * C + shrinkage * (trace(C) / d) * I`` over the last two axes.

    scikit-learn's fixed-shrinkage covariance (``sklearn.covariance.shrunk_covariance``):
    shrinkage towards the identity scaled to the mean variance. Works in place on
    ``covariance`` (callers pass a fresh array) and returns it.
    """
    n_features = covariance.shape[-1]
    mean_variance = np.trace(covariance, axis1=-2, axis2=-1) / n_features
    covariance *= 1.0 - shrinkage
    index = np.arange(n_features)
    covariance[..., index, index] += shrinkage * mean_variance[..., None]
    return covariance


def _reduce_classes(ufunc: np.ufunc, values: np.ndarray) -> np.ndarray:
    """``ufunc.reduce`` over the short last (class) axis, keeping it as length 1.

    As K - 1 elementwise calls, first to last: numpy's own reduction over a last axis of
    2 or 4 elements runs an inner loop per row and is several times slower.
    """
    classes = np.moveaxis(values, -1, 0)
    result = classes[0].copy()
    for column in classes[1:]:
        ufunc(result, column, out=result)
    return result[..., None]


def log_softmax(scores: np.ndarray) -> np.ndarray:
    """Log of the softmax over the last axis, computed stably."""
    top = _reduce_classes(np.maximum, scores)
    shifted = scores - np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):  # an all -inf row (no class) is NaN
        return shifted - np.log(_reduce_classes(np.add, np.exp(shifted)))
