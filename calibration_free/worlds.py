"""The worlds besides the grid (method-extensions.md §4 and §6.1), and choosing one by name.

* `LineWorld`: 5 states in a row, actions right, left and no-move; moving into a
  wall leads, with probability 0.5, to the neighbour and otherwise stays (the "edge
  trick"), so that no-move is the unique optimal action at the goal. Two tasks, G1 =
  state 1 and G2 = state 5 (the thesis's numbering; indices 0 and 4); start in the middle.
  The target is declared with no-move in it. Without no-move (``actions=2``) G1 and G2
  cannot be told apart (see `calibration_free.identifiability`) and no target can
  be declared.
* `PickAndPlaceWorld`: a robot over 4 columns and 3 cubes (624 valid states),
  actions right, left, grasp, release; an illegal grasp or release changes nothing. One
  task per state. The target is declared, in the task's state, with the action that is
  a no-op there: grasp when holding a cube, release when the hand is empty.

Both define their tasks' optimal actions by value iteration with discount 0.95 on a reward
of 1 in the task's state (the thesis's code). Guidance classes stand for the actions, in
action order (line: right, left, no-move; pick-and-place: right, left, grasp, release).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from calibration_free.world import GridWorld, Transitions, World
from decoding.validation import check_option, check_range

WORLDS: tuple[str, ...] = ("grid", "line", "pick-and-place")


class _StateRewardWorld(World):
    """Tasks rewarded for being in their state, whatever the action (the thesis's VI)."""

    def task_reward(self, task: int) -> np.ndarray:
        reward = np.zeros((self.n_states, self.n_actions))
        reward[int(self.task_states[task])] = 1.0
        return reward


@dataclass(frozen=True, eq=False)
class LineWorld(_StateRewardWorld):
    """States in a row with the edge trick (method-extensions.md §4).

    Parameters
    ----------
    length : int, default 5
        Number of states.
    no_move : bool, default True
        Whether the third action, no-move, exists.
    """

    length: int = 5
    no_move: bool = True

    name = "line"
    RIGHT, LEFT, NO_MOVE = 0, 1, 2
    #: Probability that pushing into a wall moves the agent back to the neighbour.
    EDGE_BOUNCE = 0.5

    def __post_init__(self) -> None:
        check_range("line length", self.length, 3, 1000)

    @property
    def action_names(self) -> tuple[str, ...]:
        return ("right", "left", "no-move") if self.no_move else ("right", "left")

    @property
    def n_states(self) -> int:
        return self.length

    @cached_property
    def task_states(self) -> np.ndarray:
        return np.array([0, self.length - 1])

    @cached_property
    def transitions(self) -> Transitions:
        n = self.length
        states = np.arange(n)
        nxt = np.repeat(states[:, None, None], self.n_actions * 2, axis=1).reshape(
            n, self.n_actions, 2
        )
        prob = np.zeros((n, self.n_actions, 2))
        prob[:, :, 0] = 1.0
        nxt[:-1, self.RIGHT, 0] = states[:-1] + 1
        nxt[1:, self.LEFT, 0] = states[1:] - 1
        for edge, action, neighbour in ((n - 1, self.RIGHT, n - 2), (0, self.LEFT, 1)):
            nxt[edge, action] = (neighbour, edge)
            prob[edge, action] = (self.EDGE_BOUNCE, 1.0 - self.EDGE_BOUNCE)
        return Transitions(nxt, prob)

    @property
    def guidance_actions(self) -> tuple[int, ...]:
        return tuple(range(self.n_actions))

    def state_name(self, state: int) -> str:
        return f"state {int(state) + 1}"

    def task_name(self, task: int) -> str:
        return f"G{int(task) + 1} ({self.state_name(int(self.task_states[task]))})"

    def declaration_action(self, state: int) -> int | None:
        return self.NO_MOVE if self.no_move else None

    def start_state(self, rng: np.random.Generator) -> int:
        """The middle state (draws nothing)."""
        return self.length // 2


#: Cube positions: 0-3 the bottom of columns 0-3, 4-7 the top of column p - 4, 8 the hand.
_COLUMNS = 4
_HAND = 2 * _COLUMNS
_N_CUBES = 3


def _valid(holding: bool, cubes: tuple[int, ...]) -> bool:
    if len(set(cubes)) != len(cubes):
        return False
    if any(p >= _COLUMNS and p != _HAND and p - _COLUMNS not in cubes for p in cubes):
        return False
    return (cubes.count(_HAND) == 1) == holding


@dataclass(frozen=True, eq=False)
class PickAndPlaceWorld(_StateRewardWorld):
    """A robot over 4 columns and 3 cubes (method-extensions.md §6.1), 624 states.

    A state is (holding, robot column, position of each cube); a cube is at the bottom or
    on top of a column (a top cube stands on another) or in the hand, which holds at most
    one. Actions: right and left (capped at the ends), grasp (takes the top cube of the
    robot's column if the hand is empty), release (puts the held cube on the column's
    bottom if empty, else on top if free). An illegal grasp or release is a no-op.
    """

    states: tuple[tuple[bool, int, tuple[int, ...]], ...] = field(init=False, repr=False)

    name = "pick-and-place"
    RIGHT, LEFT, GRASP, RELEASE = 0, 1, 2, 3

    def __post_init__(self) -> None:
        positions = range(_HAND + 1)
        states = tuple(
            (holding, column, cubes)
            for holding in (False, True)
            for column in range(_COLUMNS)
            for cubes in itertools.product(positions, repeat=_N_CUBES)
            if _valid(holding, cubes)
        )
        object.__setattr__(self, "states", states)

    @property
    def action_names(self) -> tuple[str, ...]:
        return ("right", "left", "grasp", "release")

    @property
    def n_states(self) -> int:
        return len(self.states)

    @cached_property
    def task_states(self) -> np.ndarray:
        return np.arange(self.n_states)

    def _after(self, state: tuple[bool, int, tuple[int, ...]], action: int):
        holding, column, cubes = state
        if action in (self.RIGHT, self.LEFT):
            step = 1 if action == self.RIGHT else -1
            return holding, min(max(column + step, 0), _COLUMNS - 1), cubes
        bottom, top = column, column + _COLUMNS
        if action == self.GRASP and not holding:
            source = top if top in cubes else bottom if bottom in cubes else None
            if source is None:
                return state
            return True, column, tuple(_HAND if p == source else p for p in cubes)
        if action == self.RELEASE and holding and top not in cubes:
            target = top if bottom in cubes else bottom
            return False, column, tuple(target if p == _HAND else p for p in cubes)
        return state

    @cached_property
    def transitions(self) -> Transitions:
        index = {state: i for i, state in enumerate(self.states)}
        next_state = np.array(
            [[index[self._after(s, a)] for a in range(self.n_actions)] for s in self.states]
        )
        return Transitions.deterministic(next_state)

    @property
    def guidance_actions(self) -> tuple[int, ...]:
        return tuple(range(self.n_actions))

    def holding(self, state: int) -> bool:
        return self.states[int(state)][0]

    def state_name(self, state: int) -> str:
        holding, column, cubes = self.states[int(state)]

        def where(p: int) -> str:
            if p == _HAND:
                return "in the hand"
            return f"on top of column {p - _COLUMNS + 1}" if p >= _COLUMNS else f"on column {p + 1}"

        hand = "holding" if holding else "hand empty"
        placed = ", ".join(f"cube {c + 1} {where(p)}" for c, p in enumerate(cubes))
        return f"robot at column {column + 1}, {hand}; {placed}"

    def declaration_action(self, state: int) -> int:
        """The action that is a no-op in the state: grasp when holding, else release."""
        return self.GRASP if self.holding(state) else self.RELEASE


def make_world(kind: str, *, grid: int = 5, actions: int | None = None) -> World:
    """A world by name.

    Parameters
    ----------
    kind : {"grid", "line", "pick-and-place"}
    grid : int, default 5
        Side of the grid (grid only).
    actions : {2, 3}, optional
        Line world only: 3 (right, left, no-move; default) or 2 (no no-move).
    """
    check_option("world", kind, WORLDS)
    if actions is not None and kind != "line":
        raise ValueError(f"--actions applies to the line world only, not to {kind!r}")
    if kind == "grid":
        return GridWorld(grid)
    if kind == "line":
        if actions not in (None, 2, 3):
            raise ValueError(f"the line world has 2 or 3 actions; got {actions!r}")
        return LineWorld(no_move=actions != 2)
    return PickAndPlaceWorld()
