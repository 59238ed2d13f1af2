"""The continuous-goal world through the live path: one stepper for the service and replay.

A session config of ``world`` "continuous" (frame "cardinal") carries the
:class:`calibration_free.continuous_goals.ContinuousConfig` settings in its ``learner``
object (``n_hypotheses``, ``sampling``, ``probing``, ...). :class:`ContinuousStepper` runs
the :class:`~calibration_free.continuous_goals.ContinuousGoalLearner` on the session's
learner stream (``session_streams(seed)[2]``) in the order of
:func:`cfbci.continuous.run_continuous_session`: ``move`` proposes the next probe point
(resampling the particles), ``observe`` scores them with the epoch of that probe. A move's
``from_state`` and ``to_state`` both hold the probe point ``[x, y]`` (the device
teleports there; its ``action`` is "probe"); the state accompanying it holds the
particles (``points``) and their confidences *as scored by the latest epoch*, before the
resampling of the move it accompanies, so that ``points[best_task]`` is the estimate of
``run_continuous_session`` after that epoch.

The learner's sums depend on the number of BLAS threads (a product split over threads
adds in another order: differences of 1e-8 in the confidences, which an argmax or a
resampling draw can turn into another decision), so every step is computed with one BLAS
thread (:data:`ONE_BLAS_THREAD`), whatever the process's setting, as
``run_continuous_session`` computes it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from calibration_free.continuous_goals import ContinuousConfig, ContinuousGoalLearner
from calibration_free.session import session_streams

#: The plane worlds the live path runs, and the frame each requires.
PLANE_FRAMES: dict[str, str] = {"continuous": "cardinal"}
#: The continuous world's only action: teleport to the probe point.
PROBE = "probe"
#: ``threadpool_limits`` arguments of every continuous-learner computation.
ONE_BLAS_THREAD: dict[str, Any] = {"limits": 1, "user_api": "blas"}


def is_plane(config: dict[str, Any]) -> bool:
    """Whether a config message's fields (or a recorded configuration) are a plane world's."""
    return config.get("world") in PLANE_FRAMES


def plane_settings(config: dict[str, Any]) -> ContinuousConfig:
    """The continuous learner's settings of a config message's fields.

    Raises
    ------
    ValueError
        Naming the field: a ``frame`` other than the world's, an unknown ``learner``
        setting, a value of the wrong type or out of range.
    """
    world, frame = config["world"], config["frame"]
    if frame != PLANE_FRAMES[world]:
        raise ValueError(
            f"field 'frame' must be {PLANE_FRAMES[world]!r} in world {world!r}; got {frame!r}"
        )
    defaults = {f.name: f.default for f in dataclasses.fields(ContinuousConfig)}
    values = config["learner"]
    unknown = sorted(set(values) - set(defaults))
    if unknown:
        raise ValueError(
            f"unknown learner setting(s) {', '.join(map(repr, unknown))} for world {world!r}; "
            f"the known ones are {', '.join(defaults)}"
        )
    for name, value in values.items():
        default = defaults[name]
        if isinstance(default, str):
            ok = isinstance(value, str)
        elif isinstance(default, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = isinstance(value, int | float) and not isinstance(value, bool)
        if not ok:
            raise ValueError(
                f"learner setting {name!r} must be a {type(default).__name__}; got {value!r}"
            )
    return ContinuousConfig(**values)


def continuous_memory_bytes(settings: ContinuousConfig, steps: int, n_features: int = 0) -> int:
    """An upper estimate of the continuous learner's peak memory, bytes (float64 arrays).

    With H particles, J sampled classifiers, K = 4 classes, d features, n = ``steps``
    signals, C candidates and S map signals: the sampled precision factors and their
    temporaries ``4 H J K d^2``, the sampled densities ``2 K H J n``, the signals' outer
    products ``2 n d^2``, the class scatters ``4 H K d^2``, the uncertainty map ``2 H C S +
    C H K`` and the relabelled history ``3 H n K``.
    """
    h, j, k, d, n = settings.n_hypotheses, settings.n_draws, 4, n_features, steps
    c, s = settings.n_candidates, min(settings.n_map_signals, steps)
    return 8 * (
        4 * h * j * k * d * d + 2 * k * h * j * n + 2 * n * d * d + 4 * h * k * d * d
        + 2 * h * c * s + c * h * k + 3 * h * n * k
    )


class ContinuousStepper:
    """The continuous learner of a config, stepped as the service steps it.

    Parameters
    ----------
    config : dict
        A config message's fields (``world`` "continuous").

    Attributes
    ----------
    learner : ContinuousGoalLearner
    steps : int
        Steps of the session.
    moves : list of dict
        The ``move`` fields so far.
    state : tuple of (dict, ndarray)
        The ``state`` fields and payload (confidence of every particle, float32, shape
        (n_hypotheses,)) after the latest epoch (before any: the initial pool).
    """

    def __init__(self, config: dict[str, Any]) -> None:
        self.steps = config["steps"]
        with threadpool_limits(**ONE_BLAS_THREAD):
            self.learner = ContinuousGoalLearner(
                plane_settings(config), session_streams(config["seed"])[2]
            )
        self.moves: list[dict[str, Any]] = []
        self._point: np.ndarray | None = None
        self.state = self._state_fields()

    @property
    def n_signals(self) -> int:
        return self.learner.n_signals

    @property
    def finished(self) -> bool:
        """Every step's epoch has been observed."""
        return self.n_signals >= self.steps

    def move(self) -> dict[str, Any]:
        """Propose the probe of the next step; its ``move`` fields."""
        with threadpool_limits(**ONE_BLAS_THREAD):
            self._point = self.learner.propose()
        point = [float(x) for x in self._point]
        fields = {
            "step": len(self.moves) + 1, "from_state": point, "action": PROBE,
            "to_state": point, "target_reached": False,
        }
        self.moves.append(fields)
        return fields

    def observe(self, signal: np.ndarray) -> None:
        """The epoch (feature vector, shape (d,)) answering the last probe."""
        if self._point is None:
            raise ValueError("an epoch before the first move")
        with threadpool_limits(**ONE_BLAS_THREAD):
            self.learner.observe(self._point, signal)
        self.state = self._state_fields()

    def _state_fields(self) -> tuple[dict[str, Any], np.ndarray]:
        learner = self.learner
        fields = {
            "best_task": int(np.argmax(learner.confidence)),
            "confident": False,  # the continuous learner declares no target
            "n_signals": learner.n_signals,
            "class_counts": [],
            "balanced_accuracy": None,
            "points": [[float(x), float(y)] for x, y in learner.particles],
        }
        return fields, learner.confidence.astype(np.float32)
