"""``cfbci replay FILE.mcap``: re-run the learner over a recording and check every decision.

The learner is rebuilt from the recorded configuration exactly as the service built it
(same world, settings, seed-derived streams and start state), fed the recorded epochs in
order (raw epochs go through the ErrP feature extractor again; a puddle epoch's ``reset``
flag restarts the agent as it did in the service), and every move, state
and target event it produces is compared with the recording: discrete fields exactly,
floating-point fields (confidences, balanced accuracy, class counts) exactly too, since
the computation is deterministic; timing fields are not compared.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.streams import session_streams
from calibration_free.world import World, transition_draws
from decoding.features import ErrPFeatures
from replay.recording import Recording, decode_array, read_recording
from session.config import (
    config_world,
    learner_settings,
    move_fields,
    start_state,
    state_fields,
    target_text,
)
from session.plane import PlaneStepper, is_plane, plane_stepper

MOVE_FIELDS = ("step", "from_state", "action", "to_state", "target_reached")
STATE_FIELDS = ("best_task", "confident", "n_signals", "class_counts", "balanced_accuracy")
#: A state message's fields (protocol version 4): the compared ones and the particles
#: (compared too in a plane world's recording; empty, and absent before version 4, elsewhere).
STATE_MESSAGE_FIELDS = (*STATE_FIELDS, "points")

#: ``on_observe(step, learner)``: called after the learner has observed the epoch of
#: ``step`` (1-based), before it proposes the next move.
Observer = Callable[[int, CalibrationFreeLearner], None]


@dataclass(frozen=True)
class Divergence:
    """The first place where the re-run differs from the recording."""

    topic: str
    index: int
    step: int
    field: str
    recorded: Any
    recomputed: Any

    def describe(self) -> str:
        return (
            f"first divergence at step {self.step} ({self.topic} #{self.index + 1}), field "
            f"{self.field!r}: recorded {self.recorded!r} vs recomputed {self.recomputed!r}"
        )


@dataclass(frozen=True)
class ReplayResult:
    """Counts of compared messages, and the first divergence (None when identical)."""

    moves: int
    states: int
    events: int
    divergence: Divergence | None


def recorded_learner(
    config: dict[str, Any], settings: LearnerConfig | None = None
) -> CalibrationFreeLearner:
    """The learner the service built for a recorded configuration (``.world`` its world).

    ``settings`` replaces the recorded learner settings (open-loop re-analysis); the
    learner's random stream is the session's all the same.
    """
    if settings is None:
        settings = learner_settings(config["learner"], config["frame"])
    return CalibrationFreeLearner(
        config_world(config), settings, session_streams(config["seed"])[2]
    )


def signal_extractor(config: dict[str, Any], first_epoch: np.ndarray) -> ErrPFeatures | None:
    """The feature extractor of a session of raw epochs, fitted on its first epoch (as the
    service fits it); None for a session of feature vectors."""
    if config.get("signal") != "epochs":
        return None
    extractor = ErrPFeatures(config["sfreq"], config["tmin"], config["ch_names"])
    return extractor.fit(first_epoch[None])


def recorded_resets(recording: Recording) -> list[bool]:
    """The ``reset`` flag of every accepted recorded epoch (False where it has none)."""
    return [bool(message.get("reset", False)) for message in recording.accepted_epochs()]


def recorded_signals(recording: Recording) -> list[np.ndarray]:
    """The learner's inputs, float32, from the accepted recorded epochs (raw or features)."""
    epochs = [decode_array(message) for message in recording.accepted_epochs()]
    if not epochs:
        return []
    extractor = signal_extractor(recording.config, epochs[0])
    if extractor is None:
        return [np.asarray(e, dtype=np.float32) for e in epochs]
    return [extractor.transform(e[None])[0].astype(np.float32) for e in epochs]


class Rerun:
    """The learner of a recorded configuration, stepped as the service steps it.

    Built, it has chosen the move of step 1; each :meth:`observe` takes the epoch of the
    last move's step and chooses the next move (none after the session's last step).

    Attributes
    ----------
    learner : CalibrationFreeLearner
    world : World
    draws : TransitionDraws
        The session's world stream (stochastic moves).
    state : int
        The agent's state before the last move (after it, once the session is over).
    action : int
        The last move's action.
    moves, states : list of dict
        Moves and states (with ``confidence``) so far, as the service sends them.
    events : list of str
        Texts of the target events so far.
    """

    def __init__(self, config: dict[str, Any], settings: LearnerConfig | None = None) -> None:
        self.steps = config["steps"]
        self.learner = recorded_learner(config, settings)
        self.world: World = self.learner.world
        self.draws = transition_draws(config["seed"])
        self.state = start_state(config["seed"], self.world)
        self.moves: list[dict] = []
        self.states: list[dict] = []
        self.events: list[str] = []
        self.action = self._move()

    @property
    def finished(self) -> bool:
        """Every step's epoch has been observed."""
        return self.learner.n_signals >= self.steps

    def _record_state(self) -> None:
        """The state message's fields and confidences, and the decision rule in force
        (``rule``, ``threshold``: not in the message; the report's calibration per rule)."""
        beliefs = self.learner.beliefs()
        fields, confidence = state_fields(self.learner, beliefs)
        self.states.append({**fields, "confidence": [float(x) for x in confidence],
                            "rule": beliefs.rule, "threshold": beliefs.threshold})

    def _move(self) -> int:
        proposal = self.learner.propose(self.state)
        step = len(self.moves) + 1
        self.moves.append(move_fields(self.world, step, self.state, proposal, self.draws))
        self._record_state()
        if proposal.declares_target:
            self.events.append(target_text(self.world, step, self.state))
        return proposal.action

    def observe(
        self, signal: np.ndarray, on_observe: Observer | None = None, reset: bool = False
    ) -> None:
        """Observe the epoch of the last move's step; choose the next move if one is due
        (``reset``: never true in these worlds)."""
        if reset:
            raise ValueError("only the puddle world's epochs may say reset")
        self.learner.observe(self.state, self.action, signal)
        if on_observe is not None:
            on_observe(self.learner.n_signals, self.learner)
        self.state = self.world.step(self.state, self.action, self.draws.uniform(len(self.moves)))
        if self.finished:
            self._record_state()
        else:
            self.action = self._move()


class PlaneRerun:
    """The learner of a recorded plane-world configuration, stepped as the service steps
    it: :class:`Rerun`'s interface (``world`` and ``draws`` None, ``learner`` the world's
    :class:`session.plane.PlaneStepper`, ``action`` 0)."""

    world = None
    draws = None
    action = 0

    def __init__(self, config: dict[str, Any]) -> None:
        self.learner: PlaneStepper = plane_stepper(config)
        self.steps = config["steps"]
        self.events: list[str] = []
        self.states: list[dict] = []
        self._record_state()
        self.learner.move()

    @property
    def moves(self) -> list[dict]:
        return self.learner.moves

    @property
    def finished(self) -> bool:
        return self.learner.finished

    def _record_state(self) -> None:
        fields, confidence = self.learner.state
        self.states.append({**fields, "confidence": [float(x) for x in confidence]})

    def observe(
        self, signal: np.ndarray, on_observe: Observer | None = None, reset: bool = False
    ) -> None:
        """Observe the epoch of the last move (and its ``reset`` flag); choose the next
        move if one is due."""
        self.learner.observe(signal, reset)
        if on_observe is not None:
            on_observe(self.learner.n_signals, self.learner)  # type: ignore[arg-type]
        self._record_state()
        if not self.finished:
            self.learner.move()


def rerun_of(config: dict[str, Any]) -> Rerun | PlaneRerun:
    """The re-run of a recorded configuration: :class:`PlaneRerun` in a plane world."""
    return PlaneRerun(config) if is_plane(config) else Rerun(config)


def recompute(
    recording: Recording, on_observe: Observer | None = None
) -> tuple[list[dict], list[dict], list[str]]:
    """The moves, states (with ``confidence``; outside a plane world also the decision
    ``rule`` and ``threshold`` in force) and target events of the re-run.

    Parameters
    ----------
    recording : Recording
        A recording with its configuration; every recorded epoch is fed, in order.
    on_observe : callable, optional
        ``on_observe(step, learner)`` after the learner has observed the epoch of ``step``
        (1-based; ``learner.n_signals == step``), before it proposes the next move: the
        learner as the service had it then (if the re-run is identical). It must not
        change the learner.
    """
    rerun = rerun_of(recording.config)
    inputs = zip(recorded_signals(recording), recorded_resets(recording), strict=True)
    for signal, reset in list(inputs)[: rerun.steps]:
        rerun.observe(signal, on_observe, reset)
    return rerun.moves, rerun.states, rerun.events


def replay_check(path: str | Path) -> ReplayResult:
    """Re-run the learner over a recording and compare (see the module docstring)."""
    recording = read_recording(path)
    if not recording.config:
        raise ValueError(f"{path}: the recording holds no session configuration")
    moves, states, events = recompute(recording)
    divergence = first_divergence(recording, moves, states, events)
    return ReplayResult(len(moves), len(states), len(events), divergence)


def first_divergence(
    recording: Recording, moves: list[dict], states: list[dict], events: list[str]
) -> Divergence | None:
    """The first difference between a recording and :func:`recompute`'s output, or None.

    Moves first, then states, then target events; a different count is a divergence.
    """
    recorded_moves = [m for _, m in recording.messages.get("/move", [])]
    recorded_states = [m for _, m in recording.messages.get("/state", [])]
    recorded_events = [
        m["message"]
        for _, m in recording.messages.get("/event", [])
        if m.get("event") == "target_reached"
    ]
    fields = STATE_MESSAGE_FIELDS if is_plane(recording.config) else STATE_FIELDS
    return move_divergence(recorded_moves, moves) or state_divergence(
        recorded_states, states, recorded_events, events, moves, fields
    )


def replay_verdict(recording: Recording) -> tuple[bool | None, str | None]:
    """Whether :func:`recompute` reproduces the recording, and the first divergence's
    description; ``(None, why)`` if the re-run failed."""
    try:
        divergence = first_divergence(recording, *recompute(recording))
    except (ValueError, KeyError, TypeError) as error:
        return None, f"re-run failed: {error!r}"
    return divergence is None, divergence and divergence.describe()


def move_divergence(recorded: list[dict], moves: list[dict]) -> Divergence | None:
    """The first difference between recorded and recomputed moves (fields or count)."""
    return _first_difference("/move", recorded, moves, MOVE_FIELDS, moves)


def state_divergence(
    recorded_states: list[dict],
    states: list[dict],
    recorded_events: list[str],
    events: list[str],
    moves: list[dict],
    fields: tuple[str, ...] = STATE_FIELDS,
) -> Divergence | None:
    """The first difference in the states (``fields`` and the confidences), then in the
    target events' texts; ``moves`` (recomputed) give the steps."""
    return _first_difference(
        "/state", recorded_states, states, (*fields, "confidence"), moves
    ) or _first_difference(
        "/event",
        [{"message": e} for e in recorded_events],
        [{"message": e} for e in events],
        ("message",),
        moves,
    )


def _first_difference(
    topic: str,
    recorded: list[dict],
    recomputed: list[dict],
    fields: tuple[str, ...],
    moves: list[dict],
) -> Divergence | None:
    for index, (old, new) in enumerate(zip(recorded, recomputed, strict=False)):
        step = min(index + 1, len(moves)) if topic != "/event" else 0
        for name in fields:
            if old.get(name) != new.get(name):
                return Divergence(topic, index, step, name, old.get(name), new.get(name))
    if len(recorded) != len(recomputed):
        step = min(len(recorded), len(recomputed)) + 1
        return Divergence(
            topic,
            min(len(recorded), len(recomputed)),
            step,
            "count",
            len(recorded),
            len(recomputed),
        )
    return None
