"""The sessions of the worlds in the plane (`ContinuousSession`,
`PuddleSession`; `plane_session`), their settings and memory estimates.

A session config of ``world`` "continuous" (frame "cardinal") carries the
`calibration_free.continuous_goals.ContinuousConfig` settings in its ``learner``
object (``n_hypotheses``, ``sampling``, ``probing``, ...). `ContinuousSession` runs
the `ContinuousGoalLearner` on the session's
learner stream (``session_streams(seed)[2]``) in the order of
`cfbci.offline.continuous.run_continuous_session`: ``move`` proposes the next probe point
(resampling the particles), ``observe`` scores them with the epoch of that probe. A move's
``from_state`` and ``to_state`` both hold the probe point ``[x, y]`` (the device
teleports there; its ``action`` is "probe"); the state accompanying it holds the
particles (``points``) and their confidences *as scored by the latest epoch*, before the
resampling of the move it accompanies, so that ``points[best_task]`` is the estimate of
``run_continuous_session`` after that epoch.

The learner's sums depend on the number of BLAS threads (a product split over threads
adds in another order: differences of 1e-8 in the confidences, which an argmax or a
resampling draw can turn into another decision), so every step is computed with one BLAS
thread (`ONE_BLAS_THREAD`), whatever the process's setting, as
``run_continuous_session`` computes it.

A config of ``world`` "puddle" (frame "mixed") carries the
`calibration_free.puddle_learner.PuddleConfig` settings in its ``learner`` object.
`PuddleSession` runs the `PuddleLearner` in
the order of `cfbci.offline.puddle.run_puddle_session`, and owns the agent's state and the
session's world stream (`calibration_free.streams.world_stream`), which the source
never sees: the start state is its first draw (``uniform(size=2)``); ``move`` proposes the
action at the state and draws its outcome at once (`PuddleWorld.move`), so that the
``move`` carries ``from_state``, ``action`` (north, south, east or west) and ``to_state``;
``observe`` gives the learner the epoch of that move and, when the epoch says ``reset``
(the environment, which knows the task, saw ``to_state`` in the goal cell), draws the
restart state from the world stream before the next move, as the offline loop draws it
after that step. The learner never sees ``reset``: only the next move's ``from_state``.
The world's policy tables (value iteration for the 660 tasks, 3-4 s and about 300 MiB of
temporaries) are built once per process (`puddle_world`; the service builds them on
a thread of their own before its first puddle session starts, see
`cfbci.service`).
"""

from __future__ import annotations

import dataclasses
import functools
import threading
from abc import abstractmethod
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from calibration_free.continuous_goals import ContinuousConfig, ContinuousGoalLearner
from calibration_free.puddle import ACTIONS as PUDDLE_ACTIONS
from calibration_free.puddle import MIXED_LABELS, TASK_CELLS, PuddleWorld, puddle_tasks
from calibration_free.puddle_learner import PuddleConfig, PuddleLearner
from calibration_free.streams import session_streams, world_stream
from session.core import Observer, Session, State, Step
from session.settings import check_setting_kinds
from session.vocabulary import PLANE_FRAMES, PROBE

#: The learner settings (``learner`` object) of each plane world.
PLANE_SETTINGS: dict[str, type] = {"continuous": ContinuousConfig, "puddle": PuddleConfig}
#: The puddle world's actions, in its order (a move's ``action``).
PUDDLE_MOVES: tuple[str, ...] = PUDDLE_ACTIONS
#: ``threadpool_limits`` arguments of every plane-learner computation.
ONE_BLAS_THREAD: dict[str, Any] = {"limits": 1, "user_api": "blas"}


def is_plane(config: dict[str, Any]) -> bool:
    """Whether a config message's fields (or a recorded configuration) are a plane world's."""
    return config.get("world") in PLANE_FRAMES


def plane_settings(config: dict[str, Any]) -> ContinuousConfig | PuddleConfig:
    """The learner settings of a plane world's config message fields: a
    `ContinuousConfig` (world "continuous") or a `PuddleConfig` ("puddle").

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
    settings = PLANE_SETTINGS[world]
    defaults = {f.name: f.default for f in dataclasses.fields(settings)}
    values = config["learner"]
    unknown = sorted(set(values) - set(defaults))
    if unknown:
        raise ValueError(
            f"unknown learner setting(s) {', '.join(map(repr, unknown))} for world {world!r}; "
            f"the known ones are {', '.join(defaults)}"
        )
    check_setting_kinds(values, settings)
    return settings(**values)


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


def puddle_memory_bytes(settings: PuddleConfig, steps: int, n_features: int = 0) -> int:
    """An upper estimate of a puddle session's peak memory, bytes.

    With T = 660 tasks, S = 2500 discretisation cells, A = 4 actions, K = 6 labels, n =
    ``steps`` signals of d features, P = ``n_map_states`` and M = ``n_map_signals``: the
    optimal-action table ``T S A`` booleans for the whole session, plus the larger of
    building it (value iteration over every task at once: ``7 T S A`` floats; once per
    process, counted for every session as the discrete worlds count theirs) and an
    update's peak: the relabelled history and its log-probabilities ``10 T n K`` floats,
    the decoders ``6 T (K + 1) d``, the uncertainty map ``3 T P M + 2 T (P + M) K`` and the
    history ``2 n d``; 25 % allocator slack and 1 MiB. Measured (peak resident growth, one
    BLAS thread): 294 MiB for the tables' building, 54 MiB for a 150-step session and 144
    MiB for 525 steps after it; estimated 450 MiB for either (the building dominates).
    """
    world = PuddleWorld()  # its tables are not built here
    t, a, k = world.n_tasks, world.n_actions, len(MIXED_LABELS)
    cells = world.resolution**2
    n, d = steps, n_features
    p, m = settings.n_map_states, min(settings.n_map_signals, steps)
    build = 7 * t * cells * a * 8
    update = 8 * (10 * t * n * k + 6 * t * (k + 1) * d + 3 * t * p * m + 2 * t * (p + m) * k
                  + 2 * n * d)
    return int(1.25 * (t * cells * a + max(build, update))) + 2**20


_PUDDLE_WORLD_LOCK = threading.Lock()


def puddle_world() -> PuddleWorld:
    """The puddle world, its policy tables built: once per process (see the module
    docstring); a thread calling it while another builds them waits for that build."""
    with _PUDDLE_WORLD_LOCK:
        return _built_puddle_world()


def puddle_world_built() -> bool:
    """Whether `puddle_world` has built the tables in this process (it returns at
    once then)."""
    return _built_puddle_world.cache_info().currsize > 0


@functools.cache
def _built_puddle_world() -> PuddleWorld:
    world = PuddleWorld()
    world.optimal  # noqa: B018 - builds the cached tables
    return world


class _PlaneSession(Session):
    """What the plane worlds' sessions share: the state accompanying a move is the one
    the latest signal left (before the move's own proposal), computed when the signal is
    observed."""

    learner: Any
    _state: State

    def start(self) -> Step:
        return Step(self._move())

    def observe(
        self, signal: np.ndarray, reset: bool = False, on_observe: Observer | None = None
    ) -> Step:
        self._take(signal, reset)
        if on_observe is not None:
            on_observe(self.n_signals, self.learner)
        self._state = self._snapshot()
        return Step(None) if self.finished else Step(self._move())

    def state(self) -> State:
        return self._state

    @abstractmethod
    def _move(self) -> dict[str, Any]:
        """Choose the move of the next step; its ``move`` fields."""

    @abstractmethod
    def _take(self, signal: np.ndarray, reset: bool) -> None:
        """Give the learner the signal answering the last move."""

    @abstractmethod
    def _snapshot(self) -> State:
        """The ``state`` message of the learner now."""


class ContinuousSession(_PlaneSession):
    """The continuous learner of a config, stepped as the service steps it.

    Parameters
    ----------
    config : dict
        A config message's fields (``world`` "continuous").
    learner : ContinuousGoalLearner, optional
        A caller's own learner (offline, on a stream of its own); default the config's, on
        the session's learner stream.

    Attributes
    ----------
    learner : ContinuousGoalLearner
    steps : int
        Steps of the session.
    moves : list of dict
        The ``move`` fields so far.

    The state's payload is the confidence of every particle (float32, shape
    (n_hypotheses,)) after the latest signal (before any: the initial pool).
    """

    def __init__(
        self, config: dict[str, Any], learner: ContinuousGoalLearner | None = None
    ) -> None:
        self.steps = config["steps"]
        if learner is None:
            with threadpool_limits(**ONE_BLAS_THREAD):
                learner = ContinuousGoalLearner(
                    plane_settings(config), session_streams(config["seed"])[2]
                )
        self.learner = learner
        self.moves: list[dict[str, Any]] = []
        self._point: np.ndarray | None = None
        self._state = self._snapshot()

    @property
    def n_signals(self) -> int:
        return self.learner.n_signals

    def _move(self) -> dict[str, Any]:
        with threadpool_limits(**ONE_BLAS_THREAD):
            self._point = self.learner.propose()
        point = [float(x) for x in self._point]
        fields = {
            "step": len(self.moves) + 1, "from_state": point, "action": PROBE,
            "to_state": point, "target_reached": False,
        }
        self.moves.append(fields)
        return fields

    def _take(self, signal: np.ndarray, reset: bool) -> None:
        if self._point is None:
            raise ValueError("an epoch before the first move")
        if reset:
            raise ValueError("the continuous world has no reset")
        with threadpool_limits(**ONE_BLAS_THREAD):
            self.learner.observe(self._point, signal)

    def _snapshot(self) -> State:
        learner = self.learner
        fields = {
            "best_task": int(np.argmax(learner.confidence)),
            "confident": False,  # the continuous learner declares no target
            "n_signals": learner.n_signals,
            "class_counts": [],
            "balanced_accuracy": None,
            "points": [[float(x), float(y)] for x, y in learner.particles],
        }
        return State(fields, learner.confidence.astype(np.float32))


class PuddleSession(_PlaneSession):
    """The puddle learner of a config, the agent's state and the world stream, stepped as
    the service steps them (see the module docstring).

    Parameters
    ----------
    config : dict
        A config message's fields (``world`` "puddle").
    world : PuddleWorld, optional
        The world, its policy tables built or not; default `puddle_world`, shared
        by every session of the process.

    Attributes
    ----------
    world : PuddleWorld
    learner : PuddleLearner
    agent : ndarray, shape (2,)
        The agent's state: where the next move starts (after the last move, before its
        signal: where it started).
    restarts : list of int
        Steps whose signal said ``reset`` (the agent restarted after them).

    The state's payload is every task's normalised likelihood (float32, shape (660,))
    after the latest signal.
    """

    def __init__(self, config: dict[str, Any], world: PuddleWorld | None = None) -> None:
        self.steps = config["steps"]
        self.world = puddle_world() if world is None else world
        settings = plane_settings(config)
        assert isinstance(settings, PuddleConfig)
        self._draws = world_stream(config["seed"])
        self.learner = PuddleLearner(self.world, settings, session_streams(config["seed"])[2])
        self.agent = self._draws.uniform(size=2)
        self.moves: list[dict[str, Any]] = []
        self.restarts: list[int] = []
        self._pending: tuple[np.ndarray, int, np.ndarray] | None = None
        self._observed = 0
        self._state = self._snapshot()

    @property
    def n_signals(self) -> int:
        return self._observed

    def _move(self) -> dict[str, Any]:
        """Propose the action at the agent's state and draw its outcome."""
        if self._pending is not None:
            raise ValueError(f"the move of step {len(self.moves)} has no epoch yet")
        with threadpool_limits(**ONE_BLAS_THREAD):
            action = self.learner.propose(self.agent)
        outcome = self.world.move(self.agent, action, self._draws)
        self._pending = (self.agent, action, outcome)
        fields = {
            "step": len(self.moves) + 1, "from_state": [float(x) for x in self.agent],
            "action": PUDDLE_MOVES[action], "to_state": [float(x) for x in outcome],
            "target_reached": False,
        }
        self.moves.append(fields)
        return fields

    def _take(self, signal: np.ndarray, reset: bool) -> None:
        """``reset``: the agent restarts from a uniform state of the world stream instead
        of the move's outcome."""
        if self._pending is None:
            raise ValueError("an epoch before its move")
        state, action, outcome = self._pending
        with threadpool_limits(**ONE_BLAS_THREAD):
            self.learner.observe(state, action, signal)
        self._pending = None
        self._observed += 1
        if reset:
            self.restarts.append(self._observed)
            self.agent = self._draws.uniform(size=2)
        else:
            self.agent = outcome

    def _snapshot(self) -> State:
        probabilities = self.learner.probabilities
        fields = {
            "best_task": int(np.argmax(probabilities)),
            "confident": False,  # the puddle learner declares no task
            "n_signals": self._observed,
            "class_counts": [],
            "balanced_accuracy": None,
            "points": [],
        }
        return State(fields, probabilities.astype(np.float32))


@functools.cache
def _goal_cells() -> np.ndarray:
    """The goal cell of every puddle task, in task order."""
    return np.array([task.goal for task in puddle_tasks()])


def goal_probabilities(probabilities: np.ndarray) -> np.ndarray:
    """Every goal cell's probability (``row * 5 + col``, row 0 at the bottom): the
    puddle tasks' normalised likelihoods summed over their puddles, shape (25,)."""
    return np.bincount(_goal_cells(), weights=np.asarray(probabilities, dtype=np.float64),
                       minlength=TASK_CELLS**2)


def plane_config(
    seed: int, steps: int, settings: ContinuousConfig | PuddleConfig
) -> dict[str, Any]:
    """The config message fields of a plane-world session of ``settings`` (its world and
    frame those of the settings' class)."""
    world = "puddle" if isinstance(settings, PuddleConfig) else "continuous"
    return {
        "seed": seed, "steps": steps, "world": world, "frame": PLANE_FRAMES[world],
        "learner": dataclasses.asdict(settings),
    }


def plane_session(config: dict[str, Any]) -> ContinuousSession | PuddleSession:
    """The session of a plane world's config."""
    return PuddleSession(config) if config["world"] == "puddle" else ContinuousSession(config)


def plane_memory_bytes(config: dict[str, Any], n_features: int = 0) -> int:
    """The memory estimate of a plane world's config (`continuous_memory_bytes` or
    `puddle_memory_bytes`)."""
    settings = plane_settings(config)
    if isinstance(settings, PuddleConfig):
        return puddle_memory_bytes(settings, config["steps"], n_features)
    return continuous_memory_bytes(settings, config["steps"], n_features)
