"""Choosing the next action: random, greedy, or planning upon uncertainty (method.md §6)."""

from __future__ import annotations

import numpy as np

from calibration_free.frames import Frame
from calibration_free.world import World, value_iteration

PLANNERS: tuple[str, ...] = ("uncertainty", "greedy", "random")
DEFAULT_DISCOUNT = 0.9
#: Indicator elements the uncertainty planner builds at a time (bounds its temporaries).
_CHUNK_ELEMENTS = 1 << 22


def random_action(world: World, rng: np.random.Generator) -> int:
    """An action drawn uniformly among all actions (the grid's ``goal`` included)."""
    return int(rng.integers(world.n_actions))


def greedy_action(world: World, state: int, task: int, rng: np.random.Generator) -> int:
    """An optimal action towards ``task``, ties drawn at random; in the task's state, the
    world's declaration action (the grid's ``goal``) where it has one."""
    if state == world.task_states[task]:
        declaration = world.declaration_action(state)
        if declaration is not None:
            return declaration
    return int(rng.choice(np.flatnonzero(world.optimal[task, state])))


class UncertaintyPlanner:
    """Rewards state-actions whose expected signal would best tell hypotheses apart.

    For sampled past signals ``e`` and every (s, a, t), the expected match is
    ``m_t(s, a, e) = sum_l p(l | s, a, t) q_t(e)_l``. The reward of (s, a) is the
    variance of ``m_t`` across tasks, weighted by the task weights, summed over the
    signals; value iteration on that reward gives the action to take.

    The frame has few distinct label rows ``D_r`` (:class:`~calibration_free.frames.Frame`),
    so ``m_t(s, a, e) = M[t, e, r]`` with ``M = q D^T`` and ``r`` the row of (t, s, a).
    Both moments over tasks are then sums over the rows of ``(weights x M)`` times the
    indicator of row ``r`` (T x columns): per step ``(n_rows - 1)`` products of an
    ``(n_signals + 1, T)`` matrix with an indicator built chunk by chunk from the frame's
    uint8 row table, nothing precomputed; exactly the old formula up to rounding. Where the
    frame's labels do not depend on the action (guidance) the columns are states, not
    (state, action) pairs.

    Parameters
    ----------
    frame : Frame
        The interaction frame (and through it the world) the tasks are judged in.
    discount : float, default 0.9
        Discount of the value iteration.
    """

    def __init__(self, frame: Frame, discount: float = DEFAULT_DISCOUNT) -> None:
        self.frame = frame
        self.world = frame.world
        self.discount = discount

    def rewards(self, corrected: np.ndarray, task_weights: np.ndarray) -> np.ndarray:
        """Uncertainty of every state-action.

        Parameters
        ----------
        corrected : ndarray, shape (n_tasks, n_signals, n_classes)
            ``q_t(e)`` of the sampled signals.
        task_weights : ndarray, shape (n_tasks,)
            Non-negative, summing to 1.

        Returns
        -------
        ndarray, shape (n_states, n_actions)
        """
        index = self.frame.row_index
        n_tasks, n_states, n_kinds = index.shape
        columns = index.reshape(n_tasks, n_states * n_kinds)
        matches = corrected @ self.frame.distribution_rows.T  # (T, n, R)
        weighted = matches * task_weights[:, None, None]
        # Per task and row: [w m(e) for every signal e, sum_e w m(e)^2], (T, n + 1, R).
        moments = np.concatenate(
            [weighted, np.einsum("tnr,tnr->tr", weighted, matches)[:, None]], axis=1
        )
        # Row 0 everywhere, plus what each other row changes where it applies.
        base = moments[:, :, 0].sum(axis=0)
        offsets = np.ascontiguousarray(  # (R - 1, n + 1, T), contiguous for BLAS
            (moments[:, :, 1:] - moments[:, :, :1]).transpose(2, 1, 0)
        )
        variance = np.empty(columns.shape[1])
        chunk = max(1, _CHUNK_ELEMENTS // n_tasks)
        for start in range(0, columns.shape[1], chunk):
            block = columns[:, start : start + chunk]
            totals = np.repeat(base[:, None], block.shape[1], axis=1)
            for row, offset in enumerate(offsets, start=1):
                totals += offset @ (block == row).astype(float)
            variance[start : start + chunk] = totals[-1] - np.sum(totals[:-1] ** 2, axis=0)
        variance = np.maximum(variance, 0.0).reshape(n_states, n_kinds)
        return np.broadcast_to(variance, (n_states, self.world.n_actions)).copy()

    def action(
        self,
        state: int,
        corrected: np.ndarray,
        task_weights: np.ndarray,
        rng: np.random.Generator,
        novelty: np.ndarray | None = None,
    ) -> int:
        """The best action from ``state`` under the uncertainty reward, ties drawn at random.

        ``novelty`` (n_states,), optional, is added to the uncertainty reward scaled to a
        maximum of 1, for every action taken in that state.
        """
        reward = self.rewards(corrected, task_weights)
        if novelty is not None:
            reward = reward / max(reward.max(), np.finfo(float).tiny) + novelty[:, None]
        q = value_iteration(reward, self.world.transitions, discount=self.discount)[state]
        best = np.flatnonzero(q >= q.max() - 1e-12 * max(1.0, abs(q.max())))
        return int(rng.choice(best))
