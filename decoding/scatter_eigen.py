"""Eigendecompositions of growing scatter matrices, each refreshed in turn.

A learner's training sets (the whole history and every fold's complement) grow by one
signal per step, and the pooled LDA (`decoding.lda.fit_pooled_lda`) needs each
set's scatter ``S`` in an eigenbasis. Decomposing every set at every step is most of a
small world's step. Instead, each set keeps the eigendecomposition of its scatter at
some earlier step and the signals added since:

    ``S = V diag(e) V^T + Y^T Y``,  ``Y`` (r, d): the r signals added since.

The LDA absorbs ``Y`` into its Woodbury solve exactly (the same identity that already
absorbs every task's class sums), and a set is decomposed again every ``period`` signals,
the sets in turn, so that about ``n_sets / period`` eigendecompositions are made per
step. Which decomposition a set holds depends only on the signals added, never on when
decoders are fitted: a session replayed signal by signal reaches the same numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ScatterEigen:
    """Each training set's scatter as ``V diag(e) V^T + Y^T Y``.

    Attributes
    ----------
    basis : ndarray, shape (*J, n_features, n_features)
        Orthonormal eigenvectors ``V`` (columns) of the scatter when last decomposed.
    eigenvalues : ndarray, shape (*J, n_features)
        Their eigenvalues ``e``.
    pending : ndarray, shape (*J, r, n_features)
        The signals ``Y`` added since; a set with fewer than ``r`` has zero rows.
    """

    basis: np.ndarray
    eigenvalues: np.ndarray
    pending: np.ndarray

    def select(self, index: object) -> ScatterEigen:
        """The training sets ``index`` selects along the first axis."""
        return ScatterEigen(self.basis[index], self.eigenvalues[index], self.pending[index])


#: Distinct labellings the tasks form between two targets, per square root of the number
#: of tasks (tasks that agree on every label share their decoders): on average 11.7 of 25
#: and 47 of 400 in feedback sessions on 5 x 5 and 20 x 20 grids (synthetic data, seed 0).
LABELLINGS_PER_ROOT_TASK = 2.4


def refresh_period(n_tasks: int, n_features: int) -> int:
    """Signals between two decompositions of one set: the d^3 eigendecomposition against
    the pending signals' cost, which grows with the decoders fitted, one per distinct
    labelling (each solves an (r + K)-sized system per set), about ``L = 2.4 sqrt(T)`` of
    them (`LABELLINGS_PER_ROOT_TASK`, at most T). About ``d / sqrt(4 L)`` signals, at
    least 1 (every set at every step) and at most 8."""
    labellings = min(n_tasks, LABELLINGS_PER_ROOT_TASK * np.sqrt(n_tasks))
    return int(np.clip(n_features / np.sqrt(4.0 * labellings), 1, 8))


class RollingScatterEigen:
    """The eigendecompositions of ``n_sets`` growing scatters, refreshed in turn.

    Set ``j`` is decomposed again after signal ``n`` (counted from 0) when ``n % period ==
    j % period``, from the scatter its owner passes, so each set holds at most ``period``
    pending signals.

    Parameters
    ----------
    n_sets, n_features : int
    period : int
        Signals between two decompositions of one set (1: every set after every signal).
    """

    def __init__(self, n_sets: int, n_features: int, period: int) -> None:
        if period < 1:
            raise ValueError(f"period must be >= 1; got {period}")
        self.period = period
        self._phase = np.arange(n_sets) % period
        self._basis = np.broadcast_to(np.eye(n_features), (n_sets, n_features, n_features)).copy()
        self._eigenvalues = np.zeros((n_sets, n_features))
        self._pending = np.zeros((n_sets, period, n_features))
        self._n_pending = np.zeros(n_sets, dtype=int)
        self._n_added = 0

    def add(self, signal: np.ndarray, members: np.ndarray, scatters: np.ndarray) -> None:
        """Add ``signal`` (n_features,) to the sets where ``members`` (n_sets,) is true;
        ``scatters`` (n_sets, d, d): every set's scatter with the signal, of which the
        sets due are decomposed."""
        due = self._phase == self._n_added % self.period
        self._n_added += 1
        growing = members & ~due
        self._pending[growing, self._n_pending[growing]] = signal
        self._n_pending[growing] += 1
        if np.any(due):
            self._eigenvalues[due], self._basis[due] = np.linalg.eigh(scatters[due])
            self._pending[due] = 0.0
            self._n_pending[due] = 0

    def current(self) -> ScatterEigen:
        """Every set's decomposition now (copies)."""
        r = int(self._n_pending.max())
        return ScatterEigen(
            self._basis.copy(), self._eigenvalues.copy(), self._pending[:, :r].copy()
        )
