"""Message fields the service publishes and replay recomputes: one definition for both.

``learner_settings`` reads a config message's ``learner`` object; ``move_fields`` and
``state_fields`` build a ``move`` and a ``state`` message from the learner's proposal and
beliefs (docs/protocol.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner, Proposal
from calibration_free.world import ACTIONS, GridWorld


def learner_settings(values: dict[str, Any], frame: str) -> LearnerConfig:
    """The learner configuration of a config message's ``learner`` object and ``frame``.

    Every value must have the JSON type of its setting's default (a number for a float
    setting, an integer for an integer one, ...).

    Raises
    ------
    ValueError
        On an unknown setting, a value of the wrong type or out of range, or a ``frame``
        setting that differs from the config's.
    """
    defaults = LearnerConfig().to_dict()
    for name, value in values.items():
        default = defaults.get(name)
        if isinstance(default, bool | str):
            ok = isinstance(value, type(default))
        elif isinstance(default, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:  # a float setting takes any number
            ok = isinstance(value, int | float) and not isinstance(value, bool)
        if name in defaults and not ok:
            raise ValueError(
                f"learner setting {name!r} must be a {type(default).__name__}; got {value!r}"
            )
    if values.get("frame", frame) != frame:
        raise ValueError(
            f"learner frame {values['frame']!r} differs from the config's frame {frame!r}"
        )
    return LearnerConfig.from_dict({**values, "frame": frame})


def move_fields(world: GridWorld, step: int, state: int, proposal: Proposal) -> dict[str, Any]:
    """The fields of the ``move`` message of ``proposal`` taken in ``state`` at ``step``."""
    return {
        "step": step,
        "from_state": state,
        "action": ACTIONS[proposal.action],
        "to_state": world.step(state, proposal.action),
        "target_reached": proposal.declares_target,
    }


def state_fields(learner: CalibrationFreeLearner) -> tuple[dict[str, Any], np.ndarray]:
    """The fields of a ``state`` message, and its payload: the confidence of every task
    (float32, shape (n_tasks,))."""
    beliefs = learner.beliefs()
    counts = (
        learner.history.task_label_weights(beliefs.best_task).sum(axis=0)
        if beliefs.n_signals
        else np.zeros(learner.frame.n_classes)
    )
    fields = {
        "best_task": beliefs.best_task,
        "confident": beliefs.confident,
        "n_signals": beliefs.n_signals,
        "class_counts": [float(c) for c in counts],
        "balanced_accuracy": (
            learner.balanced_accuracy(beliefs.best_task) if beliefs.n_signals else None
        ),
    }
    return fields, beliefs.confidence.astype(np.float32)


