"""The puddle world of method-extensions §2 (thesis §7.4): continuous states, 660 tasks.

The agent's state is a point of ``[0, 1]^2``; the four actions move it north, south, east or
west by a length drawn from ``N(0.1, 0.01^2)``, clipped at the borders. A task is a goal cell
of the 5 x 5 grid of 0.2 x 0.2 cells (+1 on reaching it) and a *puddle*: three consecutive
cells of a row or column not holding the goal (-100 in them); 30 segments x 22 free goal
cells = 660 tasks.

Policies (a documented stand-in for the thesis's tile-coded Q-learning, which any
continuous-state method may replace): value iteration, discount 0.99, on a 50 x 50
discretisation of the square (cells of 0.02) with the mean move of 5 cells, the goal
absorbing. A continuous state takes the optimal actions of its discretisation cell; an
action is optimal where its value is within 1e-9 of the best, so ties are kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

ACTIONS: tuple[str, ...] = ("north", "south", "east", "west")
_DIRECTIONS = np.array([[0.0, 1.0], [0.0, -1.0], [1.0, 0.0], [-1.0, 0.0]])
TASK_CELLS = 5  # the task grid is TASK_CELLS x TASK_CELLS
MOVE_MEAN, MOVE_SD = 0.1, 0.01
GOAL_REWARD, PUDDLE_REWARD = 1.0, -100.0


def puddle_segments() -> list[tuple[int, ...]]:
    """The 30 puddles: three consecutive task cells (index ``row * 5 + column``) of a row or
    a column."""
    segments = []
    for line in range(TASK_CELLS):
        for first in range(TASK_CELLS - 2):
            segments.append(tuple(line * TASK_CELLS + first + k for k in range(3)))  # row
            segments.append(tuple((first + k) * TASK_CELLS + line for k in range(3)))  # column
    return segments


@dataclass(frozen=True)
class PuddleTask:
    """A goal cell and a puddle (task-grid cell indices ``row * 5 + column``, row 0 at the
    bottom)."""

    goal: int
    puddle: tuple[int, ...]


def puddle_tasks() -> list[PuddleTask]:
    """All 660 tasks, puddle by puddle, goals in cell order."""
    return [
        PuddleTask(goal, segment)
        for segment in puddle_segments()
        for goal in range(TASK_CELLS**2)
        if goal not in segment
    ]


class PuddleWorld:
    """States, moves and every task's optimal actions.

    Parameters
    ----------
    resolution : int, default 50
        Cells per side of the value-iteration discretisation.
    discount : float, default 0.99
    """

    def __init__(self, resolution: int = 50, discount: float = 0.99) -> None:
        if resolution % TASK_CELLS:
            raise ValueError(f"resolution must be a multiple of {TASK_CELLS}; got {resolution}")
        self.resolution, self.discount = resolution, discount
        self.tasks = puddle_tasks()
        self.n_tasks, self.n_actions = len(self.tasks), len(ACTIONS)

    def move(self, state: np.ndarray, action: int, rng: np.random.Generator) -> np.ndarray:
        """The next state: one draw of the move length from ``rng``, clipped to the square."""
        length = rng.normal(MOVE_MEAN, MOVE_SD)
        return np.clip(state + length * _DIRECTIONS[action], 0.0, 1.0)

    def cell(self, states: np.ndarray) -> np.ndarray:
        """Discretisation cell of states (..., 2) -> (...) int, ``row * resolution + col``."""
        index = np.minimum((np.asarray(states) * self.resolution).astype(int), self.resolution - 1)
        return index[..., 1] * self.resolution + index[..., 0]

    def task_cell(self, states: np.ndarray) -> np.ndarray:
        """Task-grid cell of states (..., 2) -> (...) int."""
        index = np.minimum((np.asarray(states) * TASK_CELLS).astype(int), TASK_CELLS - 1)
        return index[..., 1] * TASK_CELLS + index[..., 0]

    @cached_property
    def transitions(self) -> np.ndarray:
        """Next discretisation cell of every cell and action with the mean move, clipped:
        shape (resolution ** 2, 4), int."""
        n = self.resolution
        rows, cols = np.divmod(np.arange(n * n), n)
        step = round(MOVE_MEAN * n)
        return np.stack([
            np.minimum(rows + step, n - 1) * n + cols,
            np.maximum(rows - step, 0) * n + cols,
            rows * n + np.minimum(cols + step, n - 1),
            rows * n + np.maximum(cols - step, 0),
        ], axis=1)

    @cached_property
    def cell_centres(self) -> np.ndarray:
        """Centre of every discretisation cell, shape (resolution ** 2, 2)."""
        rows, cols = np.divmod(np.arange(self.resolution**2), self.resolution)
        return (np.stack([cols, rows], axis=1) + 0.5) / self.resolution

    @cached_property
    def optimal(self) -> np.ndarray:
        """Optimal actions of every task in every discretisation cell, shape
        (n_tasks, resolution ** 2, 4), bool."""
        n = self.resolution
        rows, cols = np.divmod(np.arange(n * n), n)
        targets = self.transitions
        cell_of_state = (rows * TASK_CELLS // n) * TASK_CELLS + cols * TASK_CELLS // n
        goal = np.array([t.goal for t in self.tasks])[:, None] == cell_of_state[None]
        puddle = np.zeros_like(goal)
        for t, task in enumerate(self.tasks):
            puddle[t] = np.isin(cell_of_state, task.puddle)
        reward = np.where(goal, GOAL_REWARD, np.where(puddle, PUDDLE_REWARD, 0.0))  # (T, S)
        values = np.zeros(goal.shape)
        for _ in range(2000):
            q = reward[:, targets] + self.discount * np.where(goal, 0.0, values)[:, targets]
            new = np.where(goal, 0.0, q.max(axis=2))
            if np.max(np.abs(new - values)) < 1e-10:
                break
            values = new
        q = reward[:, targets] + self.discount * np.where(goal, 0.0, values)[:, targets]
        return q >= q.max(axis=2, keepdims=True) - 1e-9

    def optimal_at(self, states: np.ndarray) -> np.ndarray:
        """Optimal actions at continuous states (n, 2): (n_tasks, n, 4) bool."""
        return self.optimal[:, self.cell(states)]


#: Labels of the mixed frame: feedback's two, then guidance's four directions.
MIXED_LABELS: tuple[str, ...] = ("correct", "incorrect", *ACTIONS)


def mixed_frame(
    optimal: np.ndarray, actions: np.ndarray, mixing: float, alpha: float
) -> np.ndarray:
    """Label distributions of the mixed feedback + guidance frame.

    ``p(l | s, a, t) = mixing * p_feedback(l | s, a, t)`` on the two feedback labels and
    ``(1 - mixing) * p_guidance(l | s, t)`` on the four directions; feedback is correct with
    ``1 - alpha`` for an optimal action, guidance spreads ``1 - alpha`` over the optimal
    directions and ``alpha`` over the others (all of it uniformly when every direction is
    optimal).

    Parameters
    ----------
    optimal : ndarray of bool, shape (n_tasks, n, 4)
        Optimal actions at each step's state.
    actions : ndarray of int, shape (n,)
        The action taken at each step.
    mixing : float
        ``phi``, the weight of feedback.
    alpha : float

    Returns
    -------
    ndarray, shape (n_tasks, n, 6)
        Each row sums to 1; labels in `MIXED_LABELS` order.
    """
    taken = np.take_along_axis(optimal, actions[None, :, None], axis=2)[..., 0]
    correct = np.where(taken, 1.0 - alpha, alpha)
    n_optimal = optimal.sum(axis=2, keepdims=True)
    n_other = optimal.shape[2] - n_optimal
    guidance = np.where(
        optimal,
        (1.0 - np.where(n_other > 0, alpha, 0.0)) / np.maximum(n_optimal, 1),
        alpha / np.maximum(n_other, 1),
    )
    guidance = np.where(n_optimal > 0, guidance, 1.0 / optimal.shape[2])
    return np.concatenate(
        [mixing * np.stack([correct, 1.0 - correct], axis=2), (1.0 - mixing) * guidance], axis=2
    )
