"""A session from a config: `open_session`, the one way a session is built.

The config is a ``config`` message's fields (docs/protocol.md), as the service receives
them and a recording holds them, its ``learner`` object complete
(`session.config.resolved_config`). Offline callers that hold the objects already
(a simulated user's target for the calibrated baseline) build their learner with
`task_learner` and a `session.tasks.TaskSession` around it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration_free.baseline import CalibratedBaseline
from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner, TaskLearner
from calibration_free.prior import Prior, ReturningLearner
from calibration_free.streams import session_streams
from calibration_free.world import World
from session.config import config_world, learner_settings
from session.core import Session
from session.plane import is_plane, plane_session
from session.tasks import OpenLoop, TaskSession


def task_learner(
    world: World,
    settings: LearnerConfig,
    rng: np.random.Generator,
    calibration: tuple[int, int] | None = None,
    prior: Prior | None = None,
) -> TaskLearner | ReturningLearner:
    """The calibration-free learner of ``world``, or the calibrated baseline; with a
    prior, the calibration-free learner started from it and checked against the blank
    learner (`calibration_free.prior.ReturningLearner`).

    Parameters
    ----------
    world : World
    settings : LearnerConfig
    rng : Generator
        The session's learner stream.
    calibration : (int, int), optional
        ``(target, trials)``: the calibrated baseline, told the user's first target and
        calibrated on that many actions (its only calibration input, given here and
        nowhere else); None for the calibration-free learner.
    prior : Prior, optional
        Earlier sessions of the user (`calibration_free.prior`), given here and nowhere
        else; not with the calibrated baseline.

    Raises
    ------
    ValueError
        On a prior with the calibrated baseline.
    """
    if prior is not None:
        if calibration is not None:
            raise ValueError("the calibrated baseline takes no prior: it calibrates")
        return ReturningLearner(world, settings, rng, prior)
    if calibration is None:
        return CalibrationFreeLearner(world, settings, rng)
    target, trials = calibration
    return CalibratedBaseline(world, target, trials, settings, rng)


def open_session(
    config: dict[str, Any],
    settings: LearnerConfig | None = None,
    decisions: bool = False,
    prior: Prior | None = None,
) -> Session:
    """The session of a config's fields, before its first move.

    Parameters
    ----------
    config : dict
        The config's fields, its ``learner`` object complete.
    settings : LearnerConfig, optional
        Replaces the config's learner settings (open-loop re-analysis of a recording under
        other settings); the session's streams are the config's all the same. Discrete
        worlds only.
    decisions : bool
        Keep the beliefs each move was chosen with (`session.core.Step.decision`).
    prior : Prior, optional
        The prior the config's ``prior`` names (its files read); exactly when the config
        has one.

    Raises
    ------
    ValueError
        On an unknown world, a grid side out of range, invalid learner settings, or a
        prior given without the config's ``prior`` or missing for it.
    """
    if bool(config.get("prior")) != (prior is not None):
        raise ValueError("the config names a prior, but none was given" if prior is None
                         else "a prior was given, but the config names none")
    if is_plane(config):
        return plane_session(config)
    world = config_world(config)
    if settings is None:
        settings = learner_settings(config["learner"], config["frame"])
    learner = task_learner(world, settings, session_streams(config["seed"])[2], prior=prior)
    return TaskSession(world, learner, config["seed"], config["steps"], decisions)


def open_loop(
    config: dict[str, Any], settings: LearnerConfig, prior: Prior | None = None
) -> OpenLoop:
    """The open-loop re-analysis of a recorded discrete-world config under ``settings``
    (the learner on the session's own learner stream, started from the session's
    ``prior`` if it had one)."""
    learner = task_learner(
        config_world(config), settings, session_streams(config["seed"])[2], prior=prior
    )
    return OpenLoop(learner)
