"""Per-class sufficient statistics: weighted counts, sums and scatter matrices.

Every decoder of the project is a function of these statistics only, so the decoders of
many label hypotheses over the same signals can share and update them incrementally.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Self

import numpy as np
from scipy.linalg import lapack


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

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(counts, sums, scatters)."""
        return self.counts, self.sums, self.scatters

    @classmethod
    def from_signals(cls, X: np.ndarray, weights: np.ndarray) -> ClassStatistics:
        """Statistics of signals ``X`` (n, d) with class weights ``weights`` (n, K)."""
        X = np.asarray(X, dtype=float)
        weights = np.asarray(weights, dtype=float)
        return cls(
            counts=weights.sum(axis=0),
            sums=weights.T @ X,
            scatters=np.einsum("nk,ni,nj->kij", weights, X, X, optimize=True),
        )

    def weighted_scatter(self, weights: np.ndarray) -> np.ndarray:
        """``sum_k weights[..., k] * scatters[..., k, :, :]``: (*B, K) -> (*B, d, d)."""
        n_features = self.scatters.shape[-1]
        flat = self.scatters.reshape(*self.scatters.shape[:-2], n_features * n_features)
        return (weights[..., None, :] @ flat).reshape(*weights.shape[:-1], n_features, n_features)

    def class_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Class means (*B, K, d) and biased class covariances (*B, K, d, d).

        Classes with a zero count get zero mean and covariance (their decoder is marked
        uninformative by the caller).
        """
        counts = np.maximum(self.counts, np.finfo(float).tiny)
        means = self.sums / counts[..., None]
        covariances = self.scatters / counts[..., None, None] - (
            means[..., :, None] * means[..., None, :]
        )
        return means, covariances


@dataclass(frozen=True)
class HeldOutStatistics:
    """The statistics of a whole minus each of its parts, in turn (k-fold training sets).

    ``whole`` has batch shape ``B`` and ``parts`` ``(*B, n_parts)``; the result behaves as
    :class:`ClassStatistics` of batch shape ``(*B, n_parts)``. :meth:`weighted_scatter`,
    all a shrinkage LDA needs of the scatters, is computed from ``whole`` and ``parts``
    without forming the held-out scatter matrices (one pass less over the largest array).
    """

    whole: ClassStatistics
    parts: ClassStatistics

    def _held_out(self, whole: np.ndarray, parts: np.ndarray) -> np.ndarray:
        return np.expand_dims(whole, self.whole.counts.ndim - 1) - parts

    @property
    def counts(self) -> np.ndarray:
        return self._held_out(self.whole.counts, self.parts.counts)

    @property
    def sums(self) -> np.ndarray:
        return self._held_out(self.whole.sums, self.parts.sums)

    @property
    def scatters(self) -> np.ndarray:
        return self._held_out(self.whole.scatters, self.parts.scatters)

    def weighted_scatter(self, weights: np.ndarray) -> np.ndarray:
        """As :meth:`ClassStatistics.weighted_scatter`, with ``weights`` (*B, n_parts, K)."""
        whole = ClassStatistics(
            np.expand_dims(self.whole.counts, -2),
            np.expand_dims(self.whole.sums, -3),
            np.expand_dims(self.whole.scatters, -4),
        )
        result = whole.weighted_scatter(weights)
        result -= self.parts.weighted_scatter(weights)
        return result

    def class_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`ClassStatistics.class_moments` (forms the held-out scatters)."""
        return ClassStatistics(self.counts, self.sums, self.scatters).class_moments()


Statistics = ClassStatistics | HeldOutStatistics


class BatchedDecoders:
    """What every batch of decoders shares (subclasses are dataclasses with a ``present``
    field, shape (*B, n_classes), bool, and compute :meth:`_known_log_proba`)."""

    present: np.ndarray

    @property
    def informative(self) -> np.ndarray:
        """Decoders with at least two present classes, shape (*B,), bool."""
        return self.present.sum(axis=-1) >= 2

    def _known_log_proba(self, X: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def log_proba(self, X: np.ndarray) -> np.ndarray:
        """Log class probabilities of signals ``X`` (n, d) under every decoder: (*B, n, K).

        ``X`` may also have leading axes that broadcast against ``B`` (e.g. (n_folds, n, d)
        against B = (n_tasks, n_folds): each fold's decoders score their own signals).

        Absent classes get probability 0; uninformative decoders give uniform probabilities.
        """
        uniform = -np.log(self.present.shape[-1])
        return np.where(self.informative[..., None, None], self._known_log_proba(X), uniform)

    def select(self, index: object) -> Self:
        """The decoders at ``index`` of the batch axes (numpy indexing)."""
        return type(self)(*(getattr(self, f.name)[index] for f in fields(self)))


def one_hot(labels: np.ndarray, n_classes: int) -> np.ndarray:
    """Hard labels (n,) in 0..n_classes-1 as weights (n, n_classes)."""
    return np.eye(n_classes)[np.asarray(labels, dtype=np.intp)]


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


def solve_spd(matrices: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``A X = B`` for a batch of symmetric positive definite ``A``.

    ``matrices`` (*B, d, d), ``rhs`` (*B, d, k) -> (*B, d, k). LAPACK's Cholesky solver
    (``dposv``) per matrix: half the work of numpy's batched LU, which is what the
    per-step cost of the learner is made of. A matrix that is not numerically positive
    definite falls back to least squares, as scikit-learn's ``lsqr`` solver does.
    """
    batch = matrices.shape[:-2]
    flat_a = matrices.reshape(-1, *matrices.shape[-2:])
    flat_b = rhs.reshape(-1, *rhs.shape[-2:])
    out = np.empty(flat_b.shape)
    for i, (a, b) in enumerate(zip(flat_a, flat_b, strict=True)):
        # C-ordered and symmetric: the "lower" triangle LAPACK sees is our upper one.
        _, x, info = lapack.dposv(a, b, lower=1)
        out[i] = x if info == 0 else np.linalg.lstsq(a, b, rcond=None)[0]
    return out.reshape(*batch, *rhs.shape[-2:])


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
