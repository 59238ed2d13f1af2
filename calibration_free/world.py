"""The grid world: states, actions, deterministic moves, optimal actions, value iteration.

States are the cells of an ``n x n`` grid, indexed ``s = row * n + col`` with row 0 at
the top. Actions are :data:`ACTIONS`: four moves that clamp at the walls, and ``goal``
("I am at the target"), which keeps the state. Task hypotheses are the cells themselves:
task ``t`` means "the user's target is cell ``t``".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from decoding.validation import check_range

ACTIONS: tuple[str, ...] = ("up", "down", "left", "right", "goal")
MOVES: tuple[str, ...] = ACTIONS[:4]
GOAL: int = ACTIONS.index("goal")
_DELTAS = ((-1, 0), (1, 0), (0, -1), (0, 1), (0, 0))


@dataclass(frozen=True)
class GridWorld:
    """Deterministic ``size x size`` grid with 5 actions (up, down, left, right, goal).

    Attributes
    ----------
    size : int
        Side of the grid; there are ``size ** 2`` states and as many tasks.
    next_state : ndarray, shape (n_states, n_actions), int
        ``next_state[s, a]`` is the cell reached by action ``a`` from ``s``.
    optimal : ndarray, shape (n_tasks, n_states, n_actions), bool
        ``optimal[t, s, a]`` is True iff ``a`` is optimal for reaching ``t`` from ``s``:
        a move that reduces the Manhattan distance to ``t``, or ``goal`` at ``t`` itself.
    """

    size: int
    next_state: np.ndarray = field(init=False, repr=False)
    optimal: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.size, int | np.integer) or self.size < 2:
            raise ValueError(f"grid size must be an integer >= 2; got {self.size!r}")
        check_range("grid size", self.size, 2, 64)
        n = self.size
        rows, cols = np.divmod(np.arange(n * n), n)
        next_state = np.empty((n * n, len(ACTIONS)), dtype=np.intp)
        for a, (dr, dc) in enumerate(_DELTAS):
            next_state[:, a] = np.clip(rows + dr, 0, n - 1) * n + np.clip(cols + dc, 0, n - 1)
        distance = self.distances()
        # A move is optimal iff it brings the agent one step closer to the task's cell.
        closer = distance[:, next_state] < distance[:, :, None]
        at_task = np.eye(n * n, dtype=bool)
        optimal = closer.copy()
        optimal[:, :, GOAL] = at_task
        object.__setattr__(self, "next_state", next_state)
        object.__setattr__(self, "optimal", optimal)

    @property
    def n_states(self) -> int:
        return self.size * self.size

    @property
    def n_tasks(self) -> int:
        return self.n_states

    @property
    def n_actions(self) -> int:
        return len(ACTIONS)

    def distances(self) -> np.ndarray:
        """Manhattan distances between cells, shape (n_states, n_states), int."""
        rows, cols = np.divmod(np.arange(self.n_states), self.size)
        return np.abs(rows[:, None] - rows[None, :]) + np.abs(cols[:, None] - cols[None, :])

    def step(self, state: int, action: int) -> int:
        """The cell reached by ``action`` from ``state``."""
        return int(self.next_state[state, action])

    def cell(self, state: int) -> tuple[int, int]:
        """(row, column) of a state."""
        return divmod(int(state), self.size)


def value_iteration(
    reward: np.ndarray,
    next_state: np.ndarray,
    *,
    discount: float = 0.9,
    tolerance: float = 1e-8,
    max_iterations: int = 1000,
) -> np.ndarray:
    """Action values of a deterministic MDP by value iteration.

    Parameters
    ----------
    reward : ndarray, shape (n_states, n_actions)
        Immediate reward of taking action ``a`` in state ``s``.
    next_state : ndarray, shape (n_states, n_actions), int
        Deterministic transition table.
    discount : float
        Discount factor in [0, 1).
    tolerance : float
        Stop when the largest change of a value is below this.
    max_iterations : int
        Upper bound on sweeps.

    Returns
    -------
    q : ndarray, shape (n_states, n_actions)
        ``q[s, a] = reward[s, a] + discount * max_a' q[next_state[s, a], a']``.
    """
    check_range("discount", discount, 0.0, 1.0)
    if discount >= 1.0:
        raise ValueError("discount must be < 1 for value iteration to converge")
    values = np.zeros(reward.shape[0])
    q = reward.astype(float, copy=True)
    for _ in range(max_iterations):
        q = reward + discount * values[next_state]
        new_values = q.max(axis=1)
        if np.max(np.abs(new_values - values)) < tolerance:
            break
        values = new_values
    return q
