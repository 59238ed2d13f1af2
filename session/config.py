"""From a session config's fields to the objects a session runs with.

``config_world`` builds a config's world and ``learner_settings`` reads its ``learner``
object; ``resolved_config`` completes a config with every setting's default and
``recorded_config`` an older recording's with the settings it predates
(docs/protocol.md).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

from calibration_free.config import SETTINGS_BEFORE_THEY_EXISTED, LearnerConfig
from calibration_free.streams import session_streams
from calibration_free.world import GridWorld, World
from calibration_free.worlds import make_world
from decoding.lda import DEFAULT_SHRINKAGE
from session.plane import is_plane, plane_settings
from session.settings import check_setting_kinds


def config_world(config: dict[str, Any]) -> World:
    """The world of a config message's fields (or of a recorded configuration).

    A configuration without ``world`` (protocol version 2, grid worlds only) is a grid.
    Worlds are immutable: one instance per kind and side is built and shared (its tables,
    built on first use, too), so that a config costs no world construction (32 ms for
    pick-and-place).

    Raises
    ------
    ValueError
        On an unknown world or a grid side outside 2..64.
    """
    kind = config.get("world", "grid")
    return _world(kind, config["grid"] if kind == "grid" else None)


@functools.cache
def _world(kind: str, grid: int | None) -> World:
    return make_world(kind) if grid is None else make_world(kind, grid=grid)


def world_text(world: World) -> str:
    """A short description of a world, e.g. ``5 x 5 grid`` or ``line world (5 states, 2
    tasks)``."""
    if isinstance(world, GridWorld):
        return f"{world.size} x {world.size} grid"
    return f"{world.name} world ({world.n_states} states, {world.n_tasks} tasks)"


def start_state(seed: int, world: World) -> int:
    """The agent's start state in a session of ``seed``: `World.start_state` on the
    session's user stream, as `acquisition.user.SimulatedUser` draws it first."""
    return world.start_state(session_streams(seed)[1])


def learner_settings(values: dict[str, Any], frame: str) -> LearnerConfig:
    """The learner configuration of a config message's ``learner`` object and ``frame``.

    Every value must have a JSON type its setting's annotation allows (a number for a
    float setting, an integer for an integer one, a number or a string for ``shrinkage``,
    a number or null for ``novelty_bonus``, ...).

    Raises
    ------
    ValueError
        On an unknown setting, a value of the wrong type or out of range, or a ``frame``
        setting that differs from the config's.
    """
    check_setting_kinds(values, LearnerConfig)
    if values.get("frame", frame) != frame:
        raise ValueError(
            f"learner frame {values['frame']!r} differs from the config's frame {frame!r}"
        )
    return LearnerConfig.from_dict({**values, "frame": frame})


def recorded_config(config: dict[str, Any]) -> dict[str, Any]:
    """A config as a recording holds it, with the learner settings the recording lacks
    because they did not exist yet set to the values that reproduce the learner of that
    time (`calibration_free.config.SETTINGS_BEFORE_THEY_EXISTED`; a missing
    ``first_target_shrinkage``, the recording's own ``shrinkage``), so that an older
    recording replays and resumes as it ran. Plane worlds' configs and configs without a
    ``learner`` object are returned as they are."""
    if "learner" not in config or is_plane(config):
        return config
    learner = {**SETTINGS_BEFORE_THEY_EXISTED, **config["learner"]}
    # One shrinkage throughout, before the setting existed.
    learner.setdefault("first_target_shrinkage", learner.get("shrinkage", DEFAULT_SHRINKAGE))
    return {**config, "learner": learner}


def resolved_config(config: dict[str, Any]) -> dict[str, Any]:
    """A config's fields with its ``learner`` object complete: every setting its learner
    runs with, defaults included (`LearnerConfig.to_dict`, or the plane world's
    settings). The service records and compares configs in this form, so that a recording
    replays under the settings it ran with, whatever later versions' defaults are.

    Raises
    ------
    ValueError
        As `learner_settings` and `session.plane.plane_settings`.
    """
    if is_plane(config):
        settings = dataclasses.asdict(plane_settings(config))
    else:
        settings = learner_settings(config["learner"], config["frame"]).to_dict()
    return {**config, "learner": settings}
