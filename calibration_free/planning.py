"""Choosing the next action: random, greedy, or planning upon uncertainty (method.md §6)."""

from __future__ import annotations

import numpy as np

from calibration_free.world import GOAL, GridWorld, value_iteration

PLANNERS: tuple[str, ...] = ("uncertainty", "greedy", "random")
DEFAULT_DISCOUNT = 0.9


def random_action(world: GridWorld, rng: np.random.Generator) -> int:
    """An action drawn uniformly among all actions, ``goal`` included."""
    return int(rng.integers(world.n_actions))


def greedy_action(world: GridWorld, state: int, task: int, rng: np.random.Generator) -> int:
    """An optimal action towards ``task`` (``goal`` at the task's cell), ties drawn at random."""
    if state == task:
        return GOAL
    return int(rng.choice(np.flatnonzero(world.optimal[task, state])))


class UncertaintyPlanner:
    """Rewards state-actions whose expected signal would best tell hypotheses apart.

    For sampled past signals ``e`` and every (s, a, t), the expected match is
    ``m_t(s, a, e) = sum_l p(l | s, a, t) q_t(e)_l``. The reward of (s, a) is the
    variance of ``m_t`` across tasks, weighted by the task weights, summed over the
    signals; value iteration on that reward gives the action to take.

    Parameters
    ----------
    world : GridWorld
    label_distribution : ndarray, shape (n_tasks, n_states, n_actions, n_classes)
        ``p(l | s, a, t)`` of the frame.
    discount : float, default 0.9
        Discount of the value iteration.
    """

    def __init__(
        self, world: GridWorld, label_distribution: np.ndarray, discount: float = DEFAULT_DISCOUNT
    ) -> None:
        self.world = world
        self.discount = discount
        n_tasks, n_states, n_actions, n_classes = label_distribution.shape
        flat = label_distribution.reshape(n_tasks, n_states * n_actions, n_classes)
        # Precomputed once: p(l|s,a,t) and its pairwise products, so both moments of m over
        # tasks are two matrix products per step.
        self._first = flat.transpose(0, 2, 1).reshape(n_tasks * n_classes, -1)
        self._second = np.einsum("tpk,tpl->tklp", flat, flat).reshape(
            n_tasks * n_classes * n_classes, -1
        )

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
        n_signals = corrected.shape[1]
        weighted = corrected * task_weights[:, None, None]
        mean = weighted.transpose(1, 0, 2).reshape(n_signals, -1) @ self._first
        pairs = weighted[..., :, None] * corrected[..., None, :]
        second = pairs.transpose(1, 0, 2, 3).reshape(n_signals, -1) @ self._second
        variance = np.maximum(second - mean**2, 0.0).sum(axis=0)
        return variance.reshape(self.world.n_states, self.world.n_actions)

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
        q = value_iteration(reward, self.world.next_state, discount=self.discount)[state]
        best = np.flatnonzero(q >= q.max() - 1e-12 * max(1.0, abs(q.max())))
        return int(rng.choice(best))
