"""Checks of the values a message gives the browser view: each field of the types and in
the ranges the protocol and the session's world allow (`WorldRules`), or a
``ValueError`` that names the field, its value and what it must be; and the layout, the
threshold and the config fields the view keeps of a session."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration_free.config import LearnerConfig
from calibration_free.puddle import puddle_tasks
from session.config import config_world, learner_settings
from session.plane import PROBE, PUDDLE_MOVES
from wire import protocol

#: Largest grid side drawn as a grid (a larger one, which the service would refuse
#: anyway, is shown as a list rather than as millions of cells).
MAX_GRID_SIDE = 64
#: Steps remembered per session while they wait for their pair, per kind (epochs waiting
#: for the move after them, moves for their epoch, truths for their target): the oldest
#: beyond it are forgotten.
PENDING_STEPS = 256
#: Most tasks a state may hold (its confidences); a state with more is refused.
MAX_TASKS = 65_536
#: The int64 range's end: the protocol's integers lie below it.
INT64 = 2**63

def show(value: Any) -> str:
    """A value as an error message shows it (at most 60 characters)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def is_point(value: Any, unit: bool) -> bool:
    """A point ``[x, y]`` of two finite numbers (``unit``: of the unit square)."""
    return (
        isinstance(value, list) and len(value) == 2
        and all(is_number(v) and (not unit or 0 <= v <= 1) for v in value)
    )


def field_of(fields: dict[str, Any], name: str) -> Any:
    if name not in fields:
        raise ValueError(f"field {name!r} is missing")
    return fields[name]


def integer_of(fields: dict[str, Any], name: str, low: int, high: int = INT64 - 1) -> int:
    """Field ``name``, an integer from ``low`` to ``high``."""
    value = field_of(fields, name)
    if not is_int(value) or not low <= value <= high:
        span = f">= {low} in the int64 range" if high == INT64 - 1 else f"from {low} to {high}"
        raise ValueError(f"field {name!r} must be an integer {span}; got {show(value)}")
    return value


def flag_of(fields: dict[str, Any], name: str) -> bool:
    value = field_of(fields, name)
    if not isinstance(value, bool):
        raise ValueError(f"field {name!r} must be true or false; got {show(value)}")
    return value


def text_of(fields: dict[str, Any], name: str, choices: tuple[str, ...] = ()) -> str:
    value = field_of(fields, name)
    if not isinstance(value, str) or (choices and value not in choices):
        expected = f"one of {', '.join(choices)}" if choices else "a string"
        raise ValueError(f"field {name!r} must be {expected}; got {show(value)}")
    return value


def is_fraction(value: Any) -> bool:
    return is_number(value) and 0 <= value <= 1


def remember(mapping: dict[int, Any], key: int, value: Any) -> None:
    """``mapping[key] = value``, forgetting the oldest entries beyond `PENDING_STEPS`."""
    mapping.pop(key, None)
    mapping[key] = value
    while len(mapping) > PENDING_STEPS:
        del mapping[next(iter(mapping))]


@dataclass(frozen=True)
class WorldRules:
    """What the messages of a session may hold in its world (from the session's config).

    Attributes
    ----------
    name : str
        The config's ``world``.
    actions : tuple of str
        The world's action names (a move's ``action``).
    n_states : int or None
        States are ``0 .. n_states - 1``; None: points ``[x, y]`` of the unit square.
    n_tasks : int or None
        A truth's target is a task ``0 .. n_tasks - 1``; None: a point of the unit square.
    task_states : tuple of int or None
        The state each task wants the agent in; None in a world that declares no targets
        (the worlds in the plane).
    """

    name: str
    actions: tuple[str, ...]
    n_states: int | None
    n_tasks: int | None
    task_states: tuple[int, ...] | None = None

    def state(self, fields: dict[str, Any], name: str) -> int | list[float]:
        """Field ``name``, a state of this world."""
        value = field_of(fields, name)
        if self.n_states is None:
            ok, expected = is_point(value, True), "a point [x, y] of the unit square"
        else:
            ok = is_int(value) and 0 <= value < self.n_states
            expected = f"a state from 0 to {self.n_states - 1}"
        if not ok:
            raise ValueError(f"field {name!r} must be {expected} (the {self.name} world); "
                             f"got {show(value)}")
        return value

    def task(self, value: Any) -> bool:
        """Whether ``value`` is one of this world's tasks (a truth's target)."""
        if self.n_tasks is None:
            return is_point(value, True)
        return is_int(value) and 0 <= value < self.n_tasks

    def target(self, fields: dict[str, Any]) -> int | list[float]:
        """A truth's ``target``, a task of this world."""
        value = field_of(fields, "target")
        if not self.task(value):
            expected = ("a point [x, y] of the unit square" if self.n_tasks is None
                        else f"a task from 0 to {self.n_tasks - 1}")
            raise ValueError(f"field 'target' must be {expected} (the {self.name} world); "
                             f"got {show(value)}")
        return value


def world_rules(config: dict[str, Any]) -> WorldRules | None:
    """The rules of a config's world (its fields ``world`` and, for a grid, ``grid``); None
    for one the service refuses (a grid side outside 2..64): its messages are checked as
    those of a world not known."""
    try:
        return built_world_rules(config["world"], config.get("grid"))
    except ValueError:
        return None


@functools.cache  # a world that cannot be built raises, and is not cached
def built_world_rules(world: str, grid: int | None) -> WorldRules:
    if world == "continuous":
        return WorldRules(world, (PROBE,), None, None)
    if world == "puddle":
        return WorldRules(world, PUDDLE_MOVES, None, len(puddle_tasks()))
    built = config_world({"world": world, "grid": grid})
    tasks = tuple(int(s) for s in built.task_states)
    return WorldRules(world, tuple(built.action_names), built.n_states, len(tasks), tasks)


def any_state(fields: dict[str, Any], name: str) -> int | list[float]:
    """Field ``name``, a state (or a target) of a world not known: an index or a point."""
    value = field_of(fields, name)
    if not ((is_int(value) and 0 <= value < INT64) or is_point(value, False)):
        raise ValueError(f"field {name!r} must be an index from 0 to {INT64 - 1} or a point "
                         f"[x, y] of two finite numbers; got {show(value)}")
    return value


def layout_of(
    config: dict[str, Any] | None, n_tasks: int = 0, grid_actions: bool = True
) -> dict[str, Any]:
    """How to draw a session's world: ``{"kind": "grid", "side": n, "inferred": bool}`` or
    ``{"kind": "list"}``.

    A config with a ``grid`` side and no ``world`` description other than a grid is a grid
    world (cells ``row * side + col``); a config of another world is drawn as the agent's
    state and a ranked list of the hypotheses. Without a config (the view missed it: started
    later, or the source reached it after sending it), a session whose number of tasks is a
    square and whose moves are all grid actions is taken for a grid (``inferred``: protocol
    version 1 has grid worlds only); otherwise it is a list.

    Parameters
    ----------
    config : dict or None
        The config message's fields.
    n_tasks : int
        Length of the latest state's confidences (0: none yet).
    grid_actions : bool
        Whether every move seen so far was one of the grid's actions.
    """
    if config is None:
        side = math.isqrt(n_tasks)
        if n_tasks and side * side == n_tasks and grid_actions and side <= MAX_GRID_SIDE:
            return {"kind": "grid", "side": side, "inferred": True}
        return {"kind": "list"}
    world = config.get("world")
    kind = world.get("kind") if isinstance(world, dict) else world
    side = config.get("grid")
    if kind not in (None, "grid") or not isinstance(side, int) or not 1 <= side <= MAX_GRID_SIDE:
        return {"kind": "list"}
    return {"kind": "grid", "side": side, "inferred": False}


def threshold_of(config: dict[str, Any] | None) -> tuple[float, bool]:
    """The confidence threshold beta of a session and whether it is known from its config
    (else the default of `LearnerConfig`)."""
    if config is not None:
        try:
            return learner_settings(config.get("learner", {}), config["frame"]).frame_beta, True
        except (KeyError, ValueError):  # the service rejects such a config
            pass
    return LearnerConfig().frame_beta, False


def config_of(fields: dict[str, Any]) -> dict[str, Any]:
    """What the view keeps of a config message's fields (``world``, ``grid`` of a grid,
    ``frame``, ``steps``), checked."""
    world = text_of(fields, "world", protocol.CONFIG_WORLDS)
    kept = {
        "world": world, "frame": text_of(fields, "frame"),
        "steps": integer_of(fields, "steps", 0),
    }
    if not isinstance(field_of(fields, "learner"), dict):
        raise ValueError(f"field 'learner' must be a JSON object; got {show(fields['learner'])}")
    if world == "grid":
        kept["grid"] = integer_of(fields, "grid", 0)
    return kept


def confidences_of(payload: Any) -> list[float]:
    """A state's payload, checked: 1 to `MAX_TASKS` confidences in [0, 1]."""
    array = isinstance(payload, np.ndarray)
    if not array or payload.ndim != 1 or not 1 <= len(payload) <= MAX_TASKS:
        shape = payload.shape if array else type(payload).__name__
        raise ValueError(f"the payload must hold 1 to {MAX_TASKS} confidences; got {shape}")
    values = payload.astype(np.float64)
    bad = ~((values >= 0) & (values <= 1))  # NaN is neither
    if bad.any():
        first = int(np.argmax(bad))
        raise ValueError(f"the payload's confidences must lie in [0, 1]; got {values[first]} "
                         f"at task {first}")
    return [round(float(c), 6) for c in values]
