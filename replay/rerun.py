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

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calibration_free.config import LearnerConfig
from replay.recording import Recording, decode_array, read_recording
from session.core import Observer, SignalPath, Step
from session.plane import is_plane
from session.sessions import open_session

MOVE_FIELDS = ("step", "from_state", "action", "to_state", "target_reached")
STATE_FIELDS = ("best_task", "confident", "n_signals", "class_counts", "balanced_accuracy")
#: A state message's fields (protocol version 4): the compared ones and the particles
#: (compared too in a plane world's recording; empty, and absent before version 4, elsewhere).
STATE_MESSAGE_FIELDS = (*STATE_FIELDS, "points")

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


def recorded_signals(recording: Recording) -> list[np.ndarray]:
    """The learner's inputs, float32, from the accepted recorded epochs (raw or features),
    through the session's :class:`session.core.SignalPath` as the service computed them."""
    path = SignalPath(recording.config)
    return [path(decode_array(message)) for message in recording.accepted_epochs()]


def recorded_resets(recording: Recording) -> list[bool]:
    """The ``reset`` flag of every accepted recorded epoch (False where it has none)."""
    return [bool(message.get("reset", False)) for message in recording.accepted_epochs()]


class Rerun:
    """The session of a recorded configuration, stepped as the service steps it, and the
    messages it produced.

    Built, it has chosen the move of step 1; each :meth:`observe` takes the epoch of the
    last move's step and chooses the next move (none after the session's last step).

    Attributes
    ----------
    session : Session
        Opened from the configuration (:func:`session.sessions.open_session`).
    states : list of dict
        The state messages so far (with ``confidence``; outside the plane also the
        decision ``rule`` and ``threshold`` in force), one per move and one at the end.
    events : list of str
        Texts of the target events so far.
    """

    def __init__(self, config: dict[str, Any], settings: LearnerConfig | None = None) -> None:
        self.session = open_session(config, settings)
        self.steps = config["steps"]
        self.states: list[dict[str, Any]] = []
        self.events: list[str] = []
        self._take(self.session.start())

    @property
    def moves(self) -> list[dict[str, Any]]:
        return self.session.moves

    @property
    def finished(self) -> bool:
        """Every step's epoch has been observed."""
        return self.session.finished

    def observe(
        self, signal: np.ndarray, on_observe: Observer | None = None, reset: bool = False
    ) -> None:
        """Observe the epoch of the last move's step (and its ``reset`` flag); choose the
        next move if one is due."""
        self._take(self.session.observe(signal, reset, on_observe))

    def _take(self, step: Step) -> None:
        state = self.session.state()
        decision = {} if state.rule is None else {
            "rule": state.rule, "threshold": state.threshold}
        self.states.append(
            {**state.fields, "confidence": [float(x) for x in state.confidence], **decision}
        )
        self.events.extend(step.events)


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
    rerun = Rerun(recording.config)
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
