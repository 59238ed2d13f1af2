"""Worlds: states, actions, transitions, task hypotheses, optimal actions, value iteration.

A `World` is what the learner, the planners, the simulated user and the frames
know of the environment:

* ``n_states`` states and ``n_actions`` actions with readable names
  (`World.state_name`, `World.action_names`);
* `World.transitions`: for every (state, action) a few possible next states and their
  probabilities (one outcome with probability 1 in a deterministic world);
* the task hypotheses: task ``t`` means "the user wants the agent in state
  ``task_states[t]``"; the tasks may be any subset of the states;
* `World.optimal`, every task's optimal actions: by value iteration on the task's
  reward (`World.task_reward`), or by a closed form where a world has one (the grid);
* how a target is declared: performing `World.declaration_action` in the task's
  state (`World.declares`); the device does so when it is confident in that task;
* `World.guidance_actions`: the actions the guidance frame's classes stand for
  (class ``k`` means "do ``guidance_actions[k]``").

Large tables (``optimal``, ``(n_tasks, n_states, n_actions)`` booleans) are computed when
first used, not when the world is built, so that building a session's world is cheap.

Stochastic transitions draw from the session's *world stream* (`transition_draws`):
step ``k`` of a session (1-based) uses its ``k``-th uniform number, whichever process
computes the move, so that a live session equals its offline simulation.

`GridWorld` is today's world: the cells of an ``n x n`` grid, indexed
``s = row * n + col`` with row 0 at the top, and the actions `ACTIONS`: four moves
that clamp at the walls, and ``goal`` ("I am at the target"), which keeps the state. Every
cell is a task; the target is declared with ``goal``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from calibration_free.ties import near_best
from decoding.validation import check_range

ACTIONS: tuple[str, ...] = ("up", "down", "left", "right", "goal")
MOVES: tuple[str, ...] = ACTIONS[:4]
GOAL: int = ACTIONS.index("goal")
_DELTAS = ((-1, 0), (1, 0), (0, -1), (0, 1), (0, 0))
#: Tasks whose optimal actions are computed together (bounds the temporaries' size).
_TASK_CHUNK_ELEMENTS = 1 << 22
#: Index of the world stream among the session seed's spawned streams (see
#: `calibration_free.streams`: 0 data, 1 user, 2 learner).
WORLD_STREAM = 3


@dataclass(frozen=True)
class Transitions:
    """Where an action may lead: a few outcomes per (state, action), with probabilities.

    Attributes
    ----------
    next_states : ndarray, shape (n_states, n_actions, n_outcomes), int
    probabilities : ndarray, shape (n_states, n_actions, n_outcomes), float
        Sum to 1 over the outcomes; unused outcome slots have probability 0.
    """

    next_states: np.ndarray
    probabilities: np.ndarray

    @classmethod
    def deterministic(cls, next_state: np.ndarray) -> Transitions:
        """One outcome per (state, action): ``next_state`` (n_states, n_actions)."""
        return cls(next_state[..., None], np.ones((*next_state.shape, 1)))

    @property
    def is_deterministic(self) -> bool:
        return self.next_states.shape[-1] == 1

    def expected(self, values: np.ndarray) -> np.ndarray:
        """Expected next value, ``(..., n_states)`` values -> ``(..., n_states, n_actions)``.

        A deterministic world gathers ``values[..., next_state]`` exactly (no product).
        """
        if self.is_deterministic:
            return values[..., self.next_states[..., 0]]
        return (values[..., self.next_states] * self.probabilities).sum(axis=-1)

    def outcome(self, state: int, action: int, draw: float | None) -> int:
        """The next state of one move; ``draw`` in [0, 1) picks the outcome if several."""
        certain = np.flatnonzero(self.probabilities[state, action] == 1.0)
        if len(certain):
            return int(self.next_states[state, action, certain[0]])
        if draw is None or not 0.0 <= draw < 1.0:
            raise ValueError(
                f"a stochastic move needs a uniform draw in [0, 1) from the world stream; "
                f"got {draw!r}"
            )
        cumulative = np.cumsum(self.probabilities[state, action])
        index = min(int(np.searchsorted(cumulative, draw, side="right")), len(cumulative) - 1)
        return int(self.next_states[state, action, index])


class World(ABC):
    """What every world provides (see the module docstring).

    Subclasses define `action_names`, `n_states`, `task_states`,
    `transitions`, `guidance_actions`, `state_name` and
    `declaration_action`; they may override `task_reward`,
    `start_state` and `_optimal_table`.
    """

    #: Short name of the world kind (``cfbci simulate --world``).
    name: str = ""
    #: Discount of the value iteration that defines the tasks' optimal actions.
    discount: float = 0.95

    @property
    @abstractmethod
    def action_names(self) -> tuple[str, ...]:
        """Readable name of every action, in action order."""

    @property
    @abstractmethod
    def n_states(self) -> int:
        """Number of states."""

    @property
    @abstractmethod
    def task_states(self) -> np.ndarray:
        """The state each task wants the agent in, shape (n_tasks,), int."""

    @property
    @abstractmethod
    def transitions(self) -> Transitions:
        """The world's transition model."""

    @property
    @abstractmethod
    def guidance_actions(self) -> tuple[int, ...]:
        """The action each guidance class stands for (class k: ``guidance_actions[k]``)."""

    @abstractmethod
    def state_name(self, state: int) -> str:
        """A readable name of a state."""

    @abstractmethod
    def declaration_action(self, state: int) -> int | None:
        """The action that declares a target reached when performed in it (None: none)."""

    @property
    def n_actions(self) -> int:
        return len(self.action_names)

    @property
    def n_tasks(self) -> int:
        return len(self.task_states)

    def task_name(self, task: int) -> str:
        """A readable name of a task (by default its state's)."""
        return self.state_name(int(self.task_states[task]))

    def step(self, state: int, action: int, draw: float | None = None) -> int:
        """The state reached by ``action`` from ``state``.

        ``draw`` (a uniform number of the world stream, see `transition_draws`) is
        needed only where the move is stochastic.
        """
        return self.transitions.outcome(int(state), int(action), draw)

    def start_state(self, rng: np.random.Generator) -> int:
        """The agent's start state; by default uniform (one draw from ``rng``)."""
        return int(rng.integers(self.n_states))

    def declares(self, state: int, action: int, task: int) -> bool:
        """True iff ``action`` in ``state`` declares ``task`` reached."""
        return int(state) == int(self.task_states[task]) and action == self.declaration_action(
            int(state)
        )

    def task_reward(self, task: int) -> np.ndarray:
        """Reward of the task's value iteration, shape (n_states, n_actions).

        By default 1 for performing the declaration action in the task's state.
        """
        reward = np.zeros((self.n_states, self.n_actions))
        state = int(self.task_states[task])
        action = self.declaration_action(state)
        if action is None:
            raise ValueError(f"{self.name} world: state {state} has no declaration action")
        reward[state, action] = 1.0
        return reward

    @cached_property
    def optimal(self) -> np.ndarray:
        """``optimal[t, s, a]``: is ``a`` optimal for task ``t`` in ``s``, (T, S, A) bool.

        Computed on first use.
        """
        return self._optimal_table()

    def _optimal_table(self) -> np.ndarray:
        """Every task's optimal actions by value iteration (tasks in chunks)."""
        table = np.empty((self.n_tasks, self.n_states, self.n_actions), dtype=bool)
        chunk = max(1, _TASK_CHUNK_ELEMENTS // (self.n_states * self.n_actions))
        for start in range(0, self.n_tasks, chunk):
            tasks = range(start, min(start + chunk, self.n_tasks))
            table[tasks.start : tasks.stop] = optimal_actions(
                np.stack([self.task_reward(t) for t in tasks]), self.transitions, self.discount
            )
        return table


def optimal_actions(
    reward: np.ndarray, transitions: Transitions, discount: float
) -> np.ndarray:
    """The optimal actions of MDPs sharing a transition model.

    Parameters
    ----------
    reward : ndarray, shape (n_mdps, n_states, n_actions)
        Non-negative rewards.
    transitions : Transitions
    discount : float
        In [0, 1).

    Returns
    -------
    ndarray, shape (n_mdps, n_states, n_actions), bool
        True where an action's value is within a relative 1e-9 of the state's best.

    Notes
    -----
    Value iteration starts from ``max_a reward / (1 - discount)``, the exact value of a
    state whose best reward can be collected for ever, and 0 elsewhere: it converges to the
    same fixed point as from 0, in about as many sweeps as the world's diameter for sparse
    goal rewards instead of ``log(tolerance) / log(discount)``.
    """
    initial = reward.max(axis=-1) / (1.0 - discount)
    q = value_iteration(
        reward, transitions, discount=discount, tolerance=1e-13 * max(1.0, initial.max()),
        max_iterations=100_000, initial_values=initial,
    )
    return near_best(q)


def transition_draws(seed: int) -> TransitionDraws:
    """The world stream of a session seed: ``SeedSequence(seed).spawn(4)[3]``.

    The first three spawned streams are the data, user and learner streams
    (`calibration_free.streams.session_streams`); this fourth one is consumed only
    by stochastic moves, so deterministic worlds' sessions are unchanged by it.
    """
    child = np.random.SeedSequence(seed).spawn(WORLD_STREAM + 1)[WORLD_STREAM]
    return TransitionDraws(np.random.default_rng(child))


class TransitionDraws:
    """Uniform numbers of a world stream, one per session step (1-based), kept.

    Asking for the same step twice gives the same number, so every part of a process
    (or several processes) computing a move agree on it.
    """

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._draws: list[float] = []

    def uniform(self, step: int) -> float:
        """The uniform number of session step ``step`` (>= 1)."""
        if step < 1:
            raise ValueError(f"steps are counted from 1; got {step!r}")
        while len(self._draws) < step:
            self._draws.append(float(self._rng.random()))
        return self._draws[step - 1]


@dataclass(frozen=True, eq=False)
class GridWorld(World):
    """Deterministic ``size x size`` grid with 5 actions (up, down, left, right, goal).

    Attributes
    ----------
    size : int
        Side of the grid; there are ``size ** 2`` states and as many tasks.
    next_state : ndarray, shape (n_states, n_actions), int
        ``next_state[s, a]`` is the cell reached by action ``a`` from ``s``.
    optimal : ndarray, shape (n_tasks, n_states, n_actions), bool
        ``optimal[t, s, a]`` is True iff ``a`` is optimal for reaching ``t`` from ``s``:
        a move that reduces the Manhattan distance to ``t``, or ``goal`` at ``t`` itself
        (what value iteration on a reward for ``goal`` at ``t`` gives, computed in closed
        form, on first use).
    """

    size: int
    next_state: np.ndarray = field(init=False, repr=False)

    name = "grid"
    discount = 0.9

    def __post_init__(self) -> None:
        if not isinstance(self.size, int | np.integer) or self.size < 2:
            raise ValueError(f"grid size must be an integer >= 2; got {self.size!r}")
        check_range("grid size", self.size, 2, 64)
        n = self.size
        rows, cols = np.divmod(np.arange(n * n), n)
        next_state = np.empty((n * n, len(ACTIONS)), dtype=np.intp)
        for a, (dr, dc) in enumerate(_DELTAS):
            next_state[:, a] = np.clip(rows + dr, 0, n - 1) * n + np.clip(cols + dc, 0, n - 1)
        object.__setattr__(self, "next_state", next_state)

    @property
    def action_names(self) -> tuple[str, ...]:
        return ACTIONS

    @property
    def n_states(self) -> int:
        return self.size * self.size

    @cached_property
    def task_states(self) -> np.ndarray:
        return np.arange(self.n_states)

    @cached_property
    def transitions(self) -> Transitions:
        return Transitions.deterministic(self.next_state)

    @property
    def guidance_actions(self) -> tuple[int, ...]:
        return tuple(range(len(MOVES)))

    def state_name(self, state: int) -> str:
        row, col = self.cell(state)
        return f"({row}, {col})"

    def declaration_action(self, state: int) -> int:
        return GOAL

    def _optimal_table(self) -> np.ndarray:
        """A move is optimal iff it brings the agent one step closer; goal at the task."""
        distance = self.distances().astype(np.int32)
        optimal = np.empty((self.n_tasks, self.n_states, self.n_actions), dtype=bool)
        chunk = max(1, _TASK_CHUNK_ELEMENTS // (self.n_states * self.n_actions))
        for start in range(0, self.n_tasks, chunk):
            d = distance[start : start + chunk]
            optimal[start : start + chunk] = d[:, self.next_state] < d[:, :, None]
        optimal[:, :, GOAL] = np.eye(self.n_states, dtype=bool)
        return optimal

    def distances(self) -> np.ndarray:
        """Manhattan distances between cells, shape (n_states, n_states), int."""
        rows, cols = np.divmod(np.arange(self.n_states), self.size)
        return np.abs(rows[:, None] - rows[None, :]) + np.abs(cols[:, None] - cols[None, :])

    def step(self, state: int, action: int, draw: float | None = None) -> int:
        """The cell reached by ``action`` from ``state`` (``draw`` is not used)."""
        return int(self.next_state[state, action])

    def cell(self, state: int) -> tuple[int, int]:
        """(row, column) of a state."""
        return divmod(int(state), self.size)


#: Largest state space `optimal_action_values` solves by policy iteration (a dense
#: S x S solve per policy, S^3; value iteration's sweeps grow as S).
POLICY_ITERATION_STATES = 100


def optimal_action_values(
    reward: np.ndarray, transitions: Transitions, discount: float
) -> np.ndarray:
    """Action values ``q`` (n_states, n_actions) of one MDP: exact by
    `policy_iteration` up to ``POLICY_ITERATION_STATES`` states, by
    `value_iteration` (to its tolerance) beyond."""
    if reward.shape[0] <= POLICY_ITERATION_STATES:
        return policy_iteration(reward, transitions, discount=discount)
    return value_iteration(reward, transitions, discount=discount)


def policy_iteration(
    reward: np.ndarray,
    transitions: Transitions,
    *,
    discount: float = 0.9,
    max_iterations: int = 1000,
) -> np.ndarray:
    """Action values of one MDP by policy iteration: the exact fixed point of
    ``q[s, a] = reward[s, a] + discount * E[max_a' q[s', a']]``, up to rounding.

    Each policy's values solve ``(I - discount P) v = r`` (one dense solve); the policy
    then moves, in the states where some action is better by more than a relative
    1e-12, to the best one, until none is.

    Parameters
    ----------
    reward : ndarray, shape (n_states, n_actions)
    transitions : Transitions
    discount : float
        In [0, 1).
    max_iterations : int
        Upper bound on policies evaluated.

    Returns
    -------
    q : ndarray, shape (n_states, n_actions)
    """
    _check_discount(discount, max_iterations)
    n_states = reward.shape[0]
    states = np.arange(n_states)
    policy = reward.argmax(axis=1)
    for _ in range(max_iterations):
        outcomes = transitions.next_states[states, policy]  # (S, O)
        weights = transitions.probabilities[states, policy] * discount
        system = np.eye(n_states).ravel()
        system -= np.bincount(
            (states[:, None] * n_states + outcomes).ravel(), weights.ravel(), n_states**2
        )
        values = np.linalg.solve(system.reshape(n_states, n_states), reward[states, policy])
        q = reward + discount * transitions.expected(values)
        best = q.max(axis=1)
        better = best > q[states, policy] + 1e-12 * np.maximum(1.0, np.abs(best))
        if not better.any():
            break
        policy = np.where(better, q.argmax(axis=1), policy)
    return q


def _check_discount(discount: float, max_iterations: int) -> None:
    """Value and policy iteration converge only with a discount below 1."""
    check_range("discount", discount, 0.0, 1.0)
    if discount >= 1.0:
        raise ValueError("discount must be < 1 for value or policy iteration to converge")
    check_range("max_iterations", max_iterations, 1, np.inf)


#: Value-iteration sweeps between two stopping tests (see `value_iteration`), and
#: the state values kept for them at most (many MDPs at once test after every sweep).
_SWEEPS_PER_BLOCK = 32
_BLOCK_ELEMENTS = 1 << 16


def value_iteration(
    reward: np.ndarray,
    next_state: np.ndarray | Transitions,
    *,
    discount: float = 0.9,
    tolerance: float = 1e-8,
    max_iterations: int = 1000,
    initial_values: np.ndarray | None = None,
) -> np.ndarray:
    """Action values by value iteration.

    Parameters
    ----------
    reward : ndarray, shape (..., n_states, n_actions)
        Immediate reward of taking action ``a`` in state ``s`` (leading axes: several
        MDPs on the same transitions, solved together).
    next_state : ndarray, shape (n_states, n_actions), int, or Transitions
        Deterministic transition table, or a (possibly stochastic) transition model.
    discount : float
        Discount factor in [0, 1).
    tolerance : float
        Stop when the largest change of a value is below this.
    max_iterations : int
        Upper bound on sweeps.
    initial_values : ndarray, shape (..., n_states), optional
        Starting state values (default 0).

    Returns
    -------
    q : ndarray, shape (..., n_states, n_actions)
        ``q[s, a] = reward[s, a] + discount * E[max_a' q[s', a']]`` over the next states.
    """
    _check_discount(discount, max_iterations)
    if not isinstance(next_state, Transitions):
        next_state = Transitions.deterministic(np.asarray(next_state))
    # Sweeps work on (..., n_actions, n_states) arrays, so that the best action of every
    # state is an elementwise maximum over a short leading axis (numpy reduces a short
    # last axis one row at a time, five times slower here).
    reward_by_action = np.ascontiguousarray(np.swapaxes(np.asarray(reward, dtype=float), -1, -2))
    outcomes = np.ascontiguousarray(np.swapaxes(next_state.next_states, 0, 1))  # (A, S, O)
    probabilities = np.ascontiguousarray(np.swapaxes(next_state.probabilities, 0, 1))

    def sweep(values: np.ndarray) -> np.ndarray:
        """``reward + discount * E[values(next state)]``, (..., n_actions, n_states)."""
        if next_state.is_deterministic:
            q = values[..., outcomes[..., 0]]
        else:
            q = (values[..., outcomes] * probabilities).sum(axis=-1)
        q *= discount
        q += reward_by_action
        return q

    def action_values(values: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.swapaxes(sweep(values), -1, -2))

    # Sweeps run in blocks whose state values are kept, so that the stopping test (the
    # first sweep whose largest change is below the tolerance) is one array operation per
    # block: the same sweeps and the same q as testing after every sweep, bit for bit.
    n_values = int(np.prod(reward.shape[:-1]))
    block = int(np.clip(_BLOCK_ELEMENTS // max(n_values, 1), 1, _SWEEPS_PER_BLOCK))
    history = np.empty((block + 1, *reward.shape[:-1]))
    history[0] = 0.0 if initial_values is None else initial_values
    done = 0
    while True:
        sweeps = min(block, max_iterations - done)
        if next_state.is_deterministic:  # sweep() inlined: a third of the time here
            gather = outcomes[..., 0]
            for j in range(sweeps):
                q = history[j][..., gather]
                q *= discount
                q += reward_by_action
                np.maximum.reduce(q, axis=-2, out=history[j + 1])
        else:
            for j in range(sweeps):
                np.maximum.reduce(sweep(history[j]), axis=-2, out=history[j + 1])
        changes = np.abs(history[1 : sweeps + 1] - history[:sweeps])
        changes = changes.reshape(sweeps, -1).max(axis=1)
        converged = np.flatnonzero(changes < tolerance)
        if len(converged):
            return action_values(history[converged[0]])
        done += sweeps
        if done >= max_iterations:
            return action_values(history[sweeps - 1])
        history[0] = history[sweeps]
