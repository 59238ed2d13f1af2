"""A running session in the service: an epoch's path from the wire to the next move.

`RunningSession` holds what the service knows of one session (the learner's side:
no labels): its `session.core.Session` (world, learner and streams, built by
`session.sessions.open_session`), the `session.core.SignalPath` of its
epochs, its recorder and the sequence of its epochs. `RunningSession.take` is an
accepted epoch's path: the session's checks, the features, the recording of the epoch and
its features, the step of the core session, and the move published (and recorded) in answer;
the move's state and target events follow a few milliseconds later (`STATE_DELAY`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cfbci.service.admission import Rejection, check_memory
from cfbci.service.priors import check_features
from cfbci.service.recordings import record_beliefs
from replay.recording import SessionRecorder
from session.config import world_text
from session.core import Session, SignalPath, State, Step
from wire import protocol
from wire.protocol import ProtocolError, SequenceTracker
from wire.transport import Outbox

#: ``event(session, kind, text)``: publish (and record and log) an event of the session.
EventSink = Callable[[str, str, str], None]

#: Seconds between a move and its state and target events. The move goes out first, and the
#: service leaves the processor to the move's way to the screen (the source, the stimulus
#: program, the browser) before its own bookkeeping: on a 2-core machine running the whole
#: lab loop, the move then reached the subject page 0.6 ms sooner at the median and 1.5 ms
#: at the p99 (docs/results/timing.md). Nothing waits for the state that soon.
STATE_DELAY = 0.004


def next_due(sessions: Iterable[RunningSession], wait: float) -> float:
    """Seconds until the first of ``sessions``' states is due (`RunningSession.settle`),
    at most ``wait``."""
    due = [s.following[1] for s in sessions if s.following is not None]
    if not due:
        return wait
    return min(wait, max(0.0, (min(due) - time.monotonic_ns()) / 1e9))


@dataclass
class RunningSession:
    """One running session (see the module docstring).

    Attributes
    ----------
    id : str
    config : dict
        The config message's fields, resolved (every learner setting).
    config_t_ns : int
        The config message's ``t_ns`` (which ``session_started`` and a rejection name).
    core : Session
        The session's world, learner and streams, stepped.
    recorder : SessionRecorder or None
    outbox : Outbox
        Where its messages are published.
    event : EventSink
    active_ns : int
        ``time.monotonic_ns()`` of the start, the last accepted epoch or the resumption.
    epochs : SequenceTracker
        Sequence numbers of the session's accepted epochs.
    last_epoch : tuple of int or None
        ``(step, seq, t_ns)`` of the last accepted epoch: a re-send of it is answered again.
    answer : tuple or None
        The last move's fields and the state that accompanied it (fields, confidence).
    following : tuple or None
        ``(step, due_ns)``: the last move's `Step`, whose state and target events are
        still to be published (`settle`), due at ``time.monotonic_ns()`` ``due_ns``.
    answer_unheard : bool
        The session was resumed and its answer re-sent before its source could have
        reconnected: it is sent again before the next new epoch is taken (a source that
        saw the move but not its state before the kill needs the state).
    signals : SignalPath
        The learner's signal of an epoch (the feature extractor fitted on the first).
    shape : tuple of int or None
        Payload shape of the session's first accepted epoch.
    update_ns : list of int
        The learner's time per epoch, ns: the core's step (``observe`` of the epoch plus
        ``propose`` of the next move; `time.perf_counter_ns` differences; none for
        the last epoch).
    queued_ms : list of float
        Per epoch with a next move, as ``update_ns``: its queueing delay in ms, from its
        arrival (the intake's pump) to the start of its computation.
    """

    id: str
    config: dict[str, Any]
    config_t_ns: int
    core: Session
    recorder: SessionRecorder | None
    outbox: Outbox
    event: EventSink
    active_ns: int
    epochs: SequenceTracker = field(default_factory=SequenceTracker)
    last_epoch: tuple[int, int, int] | None = None
    answer: tuple[dict[str, Any], dict[str, Any], np.ndarray] | None = None
    answer_unheard: bool = False
    following: tuple[Step, int] | None = None
    signals: SignalPath = field(init=False)
    shape: tuple[int, ...] | None = None
    update_ns: list[int] = field(default_factory=list)
    queued_ms: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.signals = SignalPath(self.config)

    @property
    def step(self) -> int:
        """The last move's step (1-based): the step the next epoch must carry."""
        return self.core.step

    def world_text(self) -> str:
        """A short description of the session's world, e.g. ``5 x 5 grid``."""
        world = getattr(self.core, "world", None)
        if world is None or self.config["world"] == "puddle":
            return f"{self.config['world']} world"
        return world_text(world)

    def start(self) -> None:
        """Publish the first move and its state."""
        self.publish(self.core.start())

    def signal(self, message: protocol.Message, limits: Any) -> np.ndarray:
        """The learner's float32 signal of an epoch, after the session's checks.

        Raises
        ------
        ProtocolError
            On an epoch of another step, signal kind, channels, shape or world than the
            session's, over ``limits``' size, or whose features cannot be extracted.
        """
        fields, payload = message.fields, message.payload
        where = {"session": message.session, "seq": message.seq}
        assert payload is not None  # decode guarantees an epoch's payload
        if fields["step"] != self.step:
            raise ProtocolError(
                f"epoch of step {fields['step']}, but the last move is of step {self.step}",
                **where,
            )
        if fields["signal"] != self.config["signal"]:
            raise ProtocolError(
                f"epoch signal {fields['signal']!r} differs from the config's "
                f"{self.config['signal']!r}",
                **where,
            )
        if fields.get("ch_names") != self.config.get("ch_names"):
            raise ProtocolError(
                f"epoch ch_names {fields.get('ch_names')} differ from the config's "
                f"{self.config.get('ch_names')}",
                **where,
            )
        if "reset" in fields and self.config["world"] != "puddle":
            raise ProtocolError(
                f"field 'reset' is allowed only in the puddle world; this session's world is "
                f"{self.config['world']!r}",
                **where,
            )
        if self.shape is not None and payload.shape != self.shape:
            raise ProtocolError(
                f"epoch shape {list(payload.shape)} differs from the session's first epoch's "
                f"{list(self.shape)}",
                **where,
            )
        limit = limits.max_epoch_values if fields["signal"] == "epochs" else (
            limits.max_features)
        if payload.size > limit:
            raise ProtocolError(
                f"epoch of {payload.size} values, more than the limit of {limit}", **where
            )
        try:
            return self.signals(payload)
        except ValueError as exc:
            raise ProtocolError(f"cannot extract ErrP features: {exc}", **where) from None

    def epoch(
        self, message: protocol.Message, received_ns: int, queued_ms: float, limits: Any
    ) -> bool:
        """An epoch of this session: answered again if it is a re-send of the last one,
        else checked and taken (`signal`, the sequence, the memory limit once the
        size of the features is known, `take`); True when it was the last.

        Raises
        ------
        ProtocolError
            As `signal`, for a duplicate or late ``seq``, and a `Rejection`
            over the memory limit or for a prior of another feature size.
        """
        self.settle()
        if self.last_epoch == (message.fields["step"], message.seq, message.t_ns):
            self.answer_again()
            return False
        if self.answer_unheard:
            self.answer_again()
        signal = self.signal(message, limits)
        problem = self.epochs.check(message.seq)
        if problem is not None and not problem.startswith("gap"):
            raise ProtocolError(problem, session=self.id, seq=message.seq)  # duplicate, late
        if problem is not None:
            self.event(self.id, "info", problem)
        if self.shape is None:
            def reject(problem: str) -> Rejection:
                return Rejection(problem, self.id, message.seq, self.config_t_ns)

            check_memory(self.config, signal.shape[0], limits, reject)
            check_features(self.core, signal.shape[0], reject)
        return self.take(message, signal, received_ns, queued_ms)

    def take(
        self, message: protocol.Message, signal: np.ndarray, received_ns: int, queued_ms: float
    ) -> bool:
        """Record an accepted epoch and its features, step the core session with it and
        publish the answer; True when that was the session's last epoch."""
        assert message.payload is not None
        self.shape = message.payload.shape
        self.last_epoch = (message.fields["step"], message.seq, message.t_ns)
        self.active_ns = time.monotonic_ns()
        if self.recorder is not None:
            header = {"seq": message.seq, "t_ns": message.t_ns, "units": "uV", **message.fields}
            self.recorder.record_array("/epoch", header, message.payload, received_ns)
            header = {"seq": message.seq, "t_ns": message.t_ns, "step": self.step}
            self.recorder.record_array("/features", header, signal, received_ns)
        started_ns = time.perf_counter_ns()
        step = self.core.observe(signal, message.fields.get("reset", False))
        if step.move is None:
            self.send_state()
            return True
        self.publish(step, started_ns, queued_ms)
        return False

    def publish(
        self, step: Step, started_ns: int | None = None, queued_ms: float | None = None
    ) -> None:
        """Publish and record a step's move; its state and target events follow
        `STATE_DELAY` later (`settle`).

        ``started_ns``: `time.perf_counter_ns` before the core observed the epoch
        that led here (None for the first move); the learner's time is then appended to
        `update_ns`. ``queued_ms``: how long that epoch waited in the intake. Both
        are recorded with the move (``update_ms``, ``queued_ms``).
        """
        assert step.move is not None
        timing: dict[str, float] = {}
        if started_ns is not None:
            self.update_ns.append(time.perf_counter_ns() - started_ns)
            timing["update_ms"] = self.update_ns[-1] / 1e6
        if queued_ms is not None:
            self.queued_ms.append(queued_ms)
            timing["queued_ms"] = queued_ms
        sent = self.send("move", step.move, recorded_only=timing)
        self.record_position(step.move, sent.t_ns)
        self.following = (step, time.monotonic_ns() + round(STATE_DELAY * 1e9))

    def settle(self, now_ns: int | None = None) -> None:
        """Publish and record the last move's state, then its target events, if they are
        due at ``now_ns`` (`time.monotonic_ns`), or in any case without it. The
        state is the core session's after that move: every path that steps the core, or
        answers with the state, settles first."""
        if self.following is None or (now_ns is not None and now_ns < self.following[1]):
            return
        step, _ = self.following
        self.following = None
        assert step.move is not None
        state = self.send_state()
        self.answer = (step.move, state.fields, state.confidence)
        for text in step.events:
            self.event(self.id, "target_reached", text)

    def record_position(self, move: dict[str, Any], t_ns: int) -> None:
        """Record a puddle-world move's positions on ``/position`` (other worlds: none)."""
        if self.recorder is not None and self.config.get("world") == "puddle":
            self.recorder.record_position(
                move["from_state"], move["to_state"], move["step"], t_ns
            )

    def send_state(self, record: bool = True, state: State | None = None) -> State:
        """Publish (and record) the state: the core session's, or ``state`` when given;
        return what was sent."""
        state = self.core.state() if state is None else state
        confidence = np.asarray(state.confidence, dtype=np.float32)
        message = self.send("state", state.fields, confidence, record=record)
        if self.recorder is not None and record:
            record_beliefs(self.recorder, self.config, self.core, state, message.t_ns)
        return State(state.fields, confidence, state.rule, state.threshold)

    def answer_again(self) -> None:
        """A re-sent epoch already answered: publish its move and state again (unrecorded)."""
        assert self.answer is not None
        self.answer_unheard = False
        fields, state, confidence = self.answer
        self.send("move", fields, record=False)
        self.send("state", state, confidence, record=False)

    def send(
        self,
        kind: str,
        fields: dict[str, Any],
        payload: Any = None,
        recorded_only: dict[str, Any] | None = None,
        record: bool = True,
    ) -> protocol.Message:
        """Publish a message of the session; record it (unless not ``record``) with
        ``recorded_only`` fields added."""
        message = self.outbox.send(kind, self.id, fields, payload)
        if self.recorder is not None and record:
            record_ = {"seq": message.seq, "t_ns": message.t_ns, **fields, **(recorded_only or {})}
            if payload is not None:
                record_["confidence"] = [float(x) for x in payload]
            self.recorder.record(f"/{kind}", record_, message.t_ns)
        return message
