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
from calibration_free.prior import Prior
from replay.damage import Damage
from replay.extent import usable_part
from replay.recorded_prior import recorded_prior
from replay.recording import Recording, read_recording
from replay.signals import recorded_resets, recorded_signals
from session.core import Observer, Step
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
    """Counts of compared messages, and the first divergence (None when identical).

    ``complete``: the file is closed and intact, so the whole recording was compared; else
    ``notes`` say what was not (where the file is cut or damaged, a step cut between its
    messages, the steps not in the file) and ``warning`` is the reading's (byte offsets).
    """

    moves: int
    states: int
    events: int
    divergence: Divergence | None
    complete: bool = True
    steps_compared: int | None = None
    steps_configured: int | None = None
    notes: tuple[str, ...] = ()
    warning: str | None = None
    damage: tuple[Damage, ...] = ()

    @property
    def status(self) -> int:
        """The exit status of ``cfbci replay``: `IDENTICAL` (0), `DIVERGED`
        (1) or `IDENTICAL_SO_FAR` (3)."""
        if self.divergence is not None:
            return DIVERGED
        return IDENTICAL if self.complete else IDENTICAL_SO_FAR

    def to_json(self, file: str | Path) -> dict[str, Any]:
        divergence = self.divergence
        return {
            "file": str(file), "status": self.status, "identical": divergence is None,
            "complete": self.complete, "moves": self.moves, "states": self.states,
            "events": self.events, "steps_compared": self.steps_compared,
            "steps_configured": self.steps_configured, "warning": self.warning,
            "notes": list(self.notes), "damage": [d.to_json() for d in self.damage],
            "divergence": None if divergence is None else vars(divergence),
        }


#: Exit statuses of ``cfbci replay`` (plain check): identical and the file complete; a
#: divergence; identical as far as a cut or damaged file goes (2: an error, no comparison).
IDENTICAL, DIVERGED, IDENTICAL_SO_FAR = 0, 1, 3


class Rerun:
    """The session of a recorded configuration, stepped as the service steps it, and the
    messages it produced.

    Built, it has chosen the move of step 1; each `observe` takes the epoch of the
    last move's step and chooses the next move (none after the session's last step).

    Attributes
    ----------
    session : Session
        Opened from the configuration (`session.sessions.open_session`), with the
        prior its ``prior`` names (`replay.recorded_prior.recorded_prior`).
    states : list of dict
        The state messages so far (with ``confidence``; outside the plane also the
        decision ``rule`` and ``threshold`` in force), one per move and one at the end.
    events : list of str
        Texts of the target events so far.
    """

    def __init__(
        self,
        config: dict[str, Any],
        settings: LearnerConfig | None = None,
        prior: Prior | None = None,
    ) -> None:
        self.session = open_session(config, settings, prior=prior)
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
    rerun = Rerun(recording.config, prior=recorded_prior(recording))
    inputs = zip(recorded_signals(recording), recorded_resets(recording), strict=True)
    for signal, reset in list(inputs)[: rerun.steps]:
        rerun.observe(signal, on_observe, reset)
    return rerun.moves, rerun.states, rerun.events


def replay_check(path: str | Path) -> ReplayResult:
    """Re-run the learner over a recording and compare (see the module docstring).

    A cut or damaged file (read with ``salvage``) is compared as far as its steps go
    (`replay.extent.usable_part`; `first_divergence` on a file not complete).
    """
    recording = read_recording(path, salvage=True)
    if not recording.config:
        detail = f" ({recording.warning})" if recording.warning else ""
        raise ValueError(f"{path}: the recording holds no session configuration{detail}")
    extent = usable_part(recording)
    usable = extent.recording
    if not usable.messages.get("/move"):
        raise ValueError(f"{path}: no move of the session could be read, nothing to compare "
                         f"({recording.warning or 'the session has no step'})")
    moves, states, events = recompute(usable)
    extent_of = compared_extent(usable, moves, states, events)
    divergence = first_divergence(usable, moves, states, events)
    notes = [*extent.notes(), *extent_of.notes] if not usable.complete else []
    if extent.unaccepted and not usable.complete:
        notes.append(f"{extent.unaccepted} epoch{'s' * (extent.unaccepted != 1)} recorded "
                     "without features (not accepted by the service) not fed")
    return ReplayResult(
        extent_of.moves, extent_of.states, extent_of.events, divergence,
        complete=usable.complete, steps_compared=extent_of.steps,
        steps_configured=usable.config.get("steps"), notes=tuple(notes),
        warning=recording.warning, damage=recording.damage,
    )


@dataclass(frozen=True)
class Compared:
    """How much of a recording `first_divergence` compares: moves, states and target
    events (recomputed ones beyond these are not in the file), the steps whose messages
    are all compared, and notes on what is not."""

    moves: int
    states: int
    events: int
    steps: int
    notes: tuple[str, ...]


def compared_extent(
    recording: Recording, moves: list[dict], states: list[dict], events: list[str]
) -> Compared:
    """What of `recompute`'s output a recording is compared with.

    A complete recording (closed, intact): all of it, a different count being a
    divergence. A cut or damaged one (its usable part): the re-run observed its ``K``
    accepted epochs, so steps ``1..K`` are whole in the file (the service wrote a step's
    move, state and target event before it could receive its epoch): their messages must
    all be there. The next step's (its epoch never recorded, or the final state after the
    last epoch) may be cut between its messages: each one the file holds is compared, the
    others are not (a note says which). Steps after it are not in the file.
    """
    if recording.complete:
        return Compared(len(moves), len(states), len(events), len(moves), ())
    n_steps = len(states) - 1  # epochs observed
    recorded = _recorded(recording)
    n_moves = max(min(n_steps, len(moves)), min(len(recorded[0]), len(moves)))
    n_states = max(n_steps, min(len(recorded[1]), len(states)))
    whole_events = sum(bool(m.get("target_reached")) for m in moves[:n_steps])
    n_events = max(whole_events, min(len(recorded[2]), len(events)))
    notes = []
    cut = [what for what, missing in (
        (f"its move (step {n_steps + 1})", n_moves < len(moves)),
        (f"its state (after {n_steps} epochs)", n_states < len(states)),
        ("its target event", n_events < len(events)),
    ) if missing]
    if cut:
        step = f"step {n_steps + 1}" if n_steps < len(moves) else "the end of the session"
        notes.append(f"{step} is cut: {' and '.join(cut)} not in the file, not compared")
    configured = recording.config.get("steps")
    if isinstance(configured, int) and n_steps < configured:
        notes.append(f"steps {n_steps + 1}-{configured} of {configured} have no epoch in the "
                     f"file: compared steps 1-{n_steps} whole"
                     + (f" and what the file holds of step {n_steps + 1}"
                        if n_moves > n_steps or n_states > n_steps else ""))
    return Compared(n_moves, n_states, n_events, n_steps, tuple(notes))


def _recorded(recording: Recording) -> tuple[list[dict], list[dict], list[str]]:
    """The recorded moves, states and target events' texts."""
    return (
        [m for _, m in recording.messages.get("/move", [])],
        [m for _, m in recording.messages.get("/state", [])],
        [m["message"] for _, m in recording.messages.get("/event", [])
         if m.get("event") == "target_reached"],
    )


def first_divergence(
    recording: Recording, moves: list[dict], states: list[dict], events: list[str]
) -> Divergence | None:
    """The first difference between a recording and `recompute`'s output, or None.

    Moves first, then states, then target events; a different count is a divergence. Of
    a recording not complete (cut or damaged: its usable part), only what
    `compared_extent` says is compared.
    """
    extent = compared_extent(recording, moves, states, events)
    moves, states, events = moves[:extent.moves], states[:extent.states], events[:extent.events]
    recorded_moves, recorded_states, recorded_events = _recorded(recording)
    fields = STATE_MESSAGE_FIELDS if is_plane(recording.config) else STATE_FIELDS
    return move_divergence(recorded_moves, moves) or state_divergence(
        recorded_states, states, recorded_events, events, moves, fields
    )


def replay_verdict(recording: Recording) -> tuple[bool | None, str | None]:
    """Whether `recompute` reproduces the recording, and the first divergence's
    description; ``(None, why)`` if the re-run failed. A recording not complete is
    compared as far as its steps go (`first_divergence`)."""
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
