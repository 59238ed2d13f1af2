"""The pipeline service: runs the calibration-free learner on the epochs sources send.

:class:`PipelineService` subscribes to ``cfbci/*/config`` and ``cfbci/*/epoch`` and keeps
one :class:`_Session` per session id: the learner, the agent's cell, the step of the last
move and the sequence tracker of the epochs. It answers every accepted epoch with the next
``move`` and a ``state`` (docs/protocol.md), and every message it cannot accept with an
``error`` event; a rejected message never reaches the learner.

**Labels never reach the learner.** The service does not subscribe to ``truth`` for
itself: a separate :class:`Recordings` object, which holds the session recorders and no
learner, owns the only ``cfbci/*/truth`` subscription and writes what arrives there to the
recordings. :class:`_Session`, the learner's side, is never given a truth message.

The agent's start cell is the first draw of the session's *user* stream
(:func:`calibration_free.session.session_streams` ``[1]``), as
:class:`acquisition.user.SimulatedUser` draws it, so that a live session replays
``cfbci simulate`` exactly; the learner's stream is ``session_streams(seed)[2]``.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from queue import SimpleQueue
from typing import Any

import numpy as np
import zenoh

from calibration_free.learner import CalibrationFreeLearner
from calibration_free.session import session_streams, start_cell
from calibration_free.world import GridWorld
from cfbci.memory import keep_freed_memory
from decoding.features import ErrPFeatures
from replay.recording import SessionRecorder
from wire import protocol
from wire.messages import learner_settings, move_fields, state_fields
from wire.protocol import NO_SESSION, ProtocolError, SequenceTracker
from wire.transport import Outbox, Pump, Received, wait_for_subscribers
from wire.zenoh_config import peer_config

log = logging.getLogger("cfbci.service")

#: Seconds the service waits for a new session's source to be subscribed to its events.
SUBSCRIBER_TIMEOUT = 5.0
#: Largest grid side the service accepts (the world's tables grow as grid ** 4).
MAX_GRID = 32
#: foxglove.Log levels of the event kinds.
_LOG_LEVELS = {"error": 4, "info": 2}
_STOP = None  # queue sentinel: shut the service down


class Recordings:
    """The session recorders, and the only reader of ``truth``.

    One MCAP file per session, ``<directory>/<session>.mcap``. A recording is closed when
    its session has ended and the truth of its last step has been recorded (at once if no
    truth arrived at all), or by :meth:`close`.

    Parameters
    ----------
    directory : Path or None
        Where recordings go; None records nothing.
    """

    def __init__(self, directory: Path | None) -> None:
        self.directory = directory
        self._recorders: dict[str, SessionRecorder] = {}
        self._last_truth: dict[str, int] = {}  # session -> step of its latest truth
        self._awaiting: dict[str, int] = {}  # ended session -> step whose truth closes it

    def open(self, session: str, config: dict[str, Any]) -> SessionRecorder | None:
        """Start the recording of a session (None when not recording)."""
        if self.directory is None:
            return None
        self.directory.mkdir(parents=True, exist_ok=True)
        if session in self._recorders:  # an ended session's id reused before its last truth
            self._close(session)
        recorder = SessionRecorder(self.directory / f"{session}.mcap", session, config)
        self._recorders[session] = recorder
        return recorder

    def get(self, session: str) -> SessionRecorder | None:
        """The open recorder of a session, if any."""
        return self._recorders.get(session)

    def truth(self, received: Received) -> None:
        """Record a ``truth`` message on its session's ``/truth`` (else log why not)."""
        try:
            message = protocol.decode(received.data, key_expr=received.key_expr)
        except ProtocolError as error:
            log.warning("truth not recorded: %s", error)
            return
        recorder = self._recorders.get(message.session)
        if recorder is None:
            log.debug("truth of session %r not recorded: no open recording", message.session)
            return
        record = {"seq": message.seq, "t_ns": message.t_ns, **message.fields}
        recorder.record("/truth", record, received.t_ns)
        self._last_truth[message.session] = message.fields["step"]
        if self._awaiting.get(message.session) == message.fields["step"]:
            self._close(message.session)

    def end(self, session: str, last_step: int) -> None:
        """The session ended at ``last_step``: close now, or once that step's truth is in."""
        if session not in self._recorders:
            return
        if self._last_truth.get(session, last_step) == last_step:
            self._close(session)
        else:
            self._awaiting[session] = last_step

    def _close(self, session: str) -> None:
        self._recorders.pop(session).close()
        self._last_truth.pop(session, None)
        self._awaiting.pop(session, None)

    def close(self) -> None:
        """Close every recording."""
        for session in list(self._recorders):
            self._close(session)


@dataclass
class _Session:
    """What the service knows of one running session (the learner's side: no labels).

    Attributes
    ----------
    id : str
    config : dict
        The config message's fields.
    world : GridWorld
    learner : CalibrationFreeLearner
    state : int
        The agent's cell before the last move.
    action : int
        The last move's action (index into ACTIONS).
    step : int
        The last move's step (1-based): the step the next epoch must carry.
    epochs : SequenceTracker
        Sequence numbers of the session's epochs.
    recorder : SessionRecorder or None
    extractor : ErrPFeatures or None
        Fitted on the first raw epoch (``signal`` "epochs").
    shape : tuple of int or None
        Payload shape of the session's first accepted epoch.
    update_ns : list of int
        The learner's time per epoch, ns: ``observe`` of the epoch plus ``propose`` of the
        next move (:data:`time.perf_counter_ns` differences; none for the last epoch).
    """

    id: str
    config: dict[str, Any]
    world: GridWorld
    learner: CalibrationFreeLearner
    state: int
    recorder: SessionRecorder | None
    action: int = 0
    step: int = 0
    epochs: SequenceTracker = field(default_factory=SequenceTracker)
    extractor: ErrPFeatures | None = None
    shape: tuple[int, ...] | None = None
    update_ns: list[int] = field(default_factory=list)


#: Called with a session's id and its :attr:`_Session.update_ns` when the session ends.
SessionEndHook = Callable[[str, list[int]], None]


class PipelineService:
    """Runs sessions for any number of sources; see the module docstring.

    Parameters
    ----------
    session : zenoh.Session
        An open Zenoh session (the caller closes it, after :meth:`close`).
    record_dir : Path or None
        Directory of the recordings, ``<session>.mcap``; None: no recording.
    subscriber_timeout : float
        Seconds to wait for a new session's source to subscribe before starting it.
    on_end : callable or None
        Called with ``(session id, update_ns)`` when a session ends normally: the learner's
        time per epoch in ns, as :attr:`_Session.update_ns` (``cfbci bench latency``).

    Use :meth:`run` to serve until :meth:`stop`; :meth:`handle` processes one message.
    """

    def __init__(
        self,
        session: zenoh.Session,
        record_dir: Path | None = None,
        subscriber_timeout: float = SUBSCRIBER_TIMEOUT,
        on_end: SessionEndHook | None = None,
    ) -> None:
        self.queue: SimpleQueue[Received | None] = SimpleQueue()
        self.recordings = Recordings(record_dir)
        self.subscriber_timeout = subscriber_timeout
        self.on_end = on_end
        self._outbox = Outbox(session)
        self._sessions: dict[str, _Session] = {}
        self._config_seq: dict[str, SequenceTracker] = {}
        prefix = protocol.PREFIX
        self._pumps = [
            Pump(session, f"{prefix}/*/config", "config", self.queue),
            Pump(session, f"{prefix}/*/epoch", "epoch", self.queue),
            # Recorder-only: truth goes to self.recordings, never to a _Session.
            Pump(session, f"{prefix}/*/truth", "truth", self.queue),
        ]

    @property
    def sessions(self) -> tuple[str, ...]:
        """Ids of the running sessions."""
        return tuple(self._sessions)

    def stop(self) -> None:
        """Make :meth:`run` return (safe to call from a signal handler)."""
        self.queue.put(_STOP)

    def run(self) -> None:
        """Handle messages in arrival order until :meth:`stop`; then :meth:`close`."""
        try:
            while (received := self.queue.get()) is not _STOP:
                self.handle(received)
        finally:
            self.close()

    def close(self) -> None:
        """Stop receiving, close every recording and undeclare the publishers."""
        for pump in self._pumps:
            pump.close()
        self.recordings.close()
        self._outbox.close()

    def handle(self, received: Received) -> None:
        """Process one received message; a bad one yields an ``error`` event, nothing else."""
        try:
            if received.tag == "truth":
                self.recordings.truth(received)
            elif received.tag == "config":
                self._on_config(received)
            else:
                self._on_epoch(received)
        except ProtocolError as error:
            self._reject(error)
        except Exception as exc:  # a bug must not stop the other sessions: report it
            log.exception("internal error on a message of %s", received.key_expr)
            try:
                session = protocol.split_key(received.key_expr)[0]
            except ProtocolError:
                session = None
            self._reject(ProtocolError(f"internal error: {exc!r}", session))

    # -- sessions ---------------------------------------------------------------------

    def _on_config(self, received: Received) -> None:
        message = protocol.decode(received.data, key_expr=received.key_expr)
        where = {"session": message.session, "seq": message.seq}
        if message.session in self._sessions:
            raise ProtocolError("a session with this id is already running", **where)
        key_expr = protocol.key(message.session, "config")
        gap = self._check_seq(self._config_seq.setdefault(key_expr, SequenceTracker()), where)
        config = message.fields
        if not 2 <= config["grid"] <= MAX_GRID:
            raise ProtocolError(f"field 'grid' must be in 2..{MAX_GRID}", **where)
        try:
            world = GridWorld(config["grid"])
            learner_config = learner_settings(config["learner"], config["frame"])
            learner_rng = session_streams(config["seed"])[2]
            start = start_cell(config["seed"], world.n_states)
        except (ValueError, TypeError) as exc:
            raise ProtocolError(f"bad config: {exc}", **where) from None
        if config["steps"] < 1:
            raise ProtocolError("field 'steps' must be at least 1", **where)
        learner = CalibrationFreeLearner(world, learner_config, learner_rng)
        event_publisher = self._outbox.publisher(protocol.key(message.session, "event"))
        if not wait_for_subscribers(event_publisher, self.subscriber_timeout):
            log.warning("session %r: no subscriber to its events; starting anyway", message.session)
        recorder = self.recordings.open(
            message.session, {"seq": message.seq, "t_ns": message.t_ns, **config}
        )
        session = _Session(message.session, config, world, learner, start, recorder)
        self._sessions[session.id] = session
        if gap is not None:
            self._event(session.id, "info", gap)
        self._event(
            session.id,
            "session_started",
            f"session {session.id!r}: {config['steps']} steps on a {config['grid']} x "
            f"{config['grid']} grid, {config['frame']} frame, {config['signal']}",
        )
        self._next_move(session)

    def _on_epoch(self, received: Received) -> None:
        message = protocol.decode(received.data, key_expr=received.key_expr)
        where = {"session": message.session, "seq": message.seq}
        session = self._sessions.get(message.session)
        if session is None:
            raise ProtocolError(
                "epoch for an unknown session (no running session has this id)", **where
            )
        gap = self._check_seq(session.epochs, where)
        if gap is not None:
            self._event(session.id, "info", gap)
        assert message.payload is not None  # decode guarantees an epoch's payload
        if session.recorder is not None:
            header = {"seq": message.seq, "t_ns": message.t_ns, "units": "uV", **message.fields}
            session.recorder.record_array("/epoch", header, message.payload, received.t_ns)
        signal_ = self._check_epoch(session, message, where)
        if session.recorder is not None:
            header = {"seq": message.seq, "t_ns": message.t_ns, "step": session.step}
            session.recorder.record_array("/features", header, signal_, received.t_ns)
        started_ns = time.perf_counter_ns()
        session.learner.observe(session.state, session.action, signal_)
        session.state = session.world.step(session.state, session.action)
        if session.step < session.config["steps"]:
            self._next_move(session, started_ns)
            return
        self._send_state(session)
        self._event(
            session.id, "session_ended", f"session {session.id!r} ended after {session.step} steps"
        )
        self._end(session)

    def _check_seq(self, tracker: SequenceTracker, where: dict[str, Any]) -> str | None:
        """The gap message of an in-order-or-later seq; a duplicate or late one is an error."""
        problem = tracker.check(where["seq"])
        if problem is not None and not problem.startswith("gap"):
            raise ProtocolError(problem, **where)
        return problem

    def _check_epoch(
        self, session: _Session, message: protocol.Message, where: dict[str, Any]
    ) -> np.ndarray:
        """The learner's float32 signal of an epoch, after the session checks."""
        fields, payload = message.fields, message.payload
        assert payload is not None
        if fields["step"] != session.step:
            raise ProtocolError(
                f"epoch of step {fields['step']}, but the last move is of step {session.step}",
                **where,
            )
        if fields["signal"] != session.config["signal"]:
            raise ProtocolError(
                f"epoch signal {fields['signal']!r} differs from the config's "
                f"{session.config['signal']!r}",
                **where,
            )
        if fields.get("ch_names") != session.config.get("ch_names"):
            raise ProtocolError(
                f"epoch ch_names {fields.get('ch_names')} differ from the config's "
                f"{session.config.get('ch_names')}",
                **where,
            )
        if session.shape is not None and payload.shape != session.shape:
            raise ProtocolError(
                f"epoch shape {list(payload.shape)} differs from the session's first epoch's "
                f"{list(session.shape)}",
                **where,
            )
        if fields["signal"] == "features":
            signal_ = payload
        else:
            try:
                if session.extractor is None:
                    session.extractor = ErrPFeatures(
                        session.config["sfreq"],
                        session.config["tmin"],
                        session.config["ch_names"],
                    ).fit(payload[None])
                signal_ = session.extractor.transform(payload[None])[0].astype(np.float32)
            except ValueError as exc:
                raise ProtocolError(f"cannot extract ErrP features: {exc}", **where) from None
        session.shape = payload.shape
        return signal_

    def _next_move(self, session: _Session, started_ns: int | None = None) -> None:
        """Choose, publish and record the move of the next step, then its state.

        ``started_ns``: :func:`time.perf_counter_ns` before the learner observed the epoch
        that led here (None for the first move); the learner's time is then appended to
        :attr:`_Session.update_ns`.
        """
        proposal = session.learner.propose(session.state)
        timing = {}
        if started_ns is not None:
            session.update_ns.append(time.perf_counter_ns() - started_ns)
            timing["update_ms"] = session.update_ns[-1] / 1e6
        session.step += 1
        session.action = proposal.action
        fields = move_fields(session.world, session.step, session.state, proposal)
        self._send(session, "move", fields, recorded_only=timing)
        self._send_state(session)
        if proposal.declares_target:
            self._event(
                session.id,
                "target_reached",
                f"step {session.step}: target reached in cell {session.state}",
            )

    def _send_state(self, session: _Session) -> None:
        fields, confidence = state_fields(session.learner)
        message = self._send(session, "state", fields, confidence)
        if session.recorder is not None:
            session.recorder.record_belief(confidence, session.config["grid"], message.t_ns)

    def _send(
        self,
        session: _Session,
        kind: str,
        fields: dict[str, Any],
        payload: Any = None,
        recorded_only: dict[str, Any] | None = None,
    ) -> protocol.Message:
        """Publish a message of the session; record it with ``recorded_only`` fields added."""
        message = self._outbox.send(kind, session.id, fields, payload)
        if session.recorder is not None:
            record = {"seq": message.seq, "t_ns": message.t_ns, **fields, **(recorded_only or {})}
            if payload is not None:
                record["confidence"] = [float(x) for x in payload]
            session.recorder.record(f"/{kind}", record, message.t_ns)
        return message

    def _end(self, session: _Session) -> None:
        if self.on_end is not None:
            self.on_end(session.id, session.update_ns)
        del self._sessions[session.id]
        self._config_seq.pop(protocol.key(session.id, "config"), None)
        self.recordings.end(session.id, session.step)
        self._outbox.forget(session.id)

    # -- events -----------------------------------------------------------------------

    def _event(self, session: str, event: str, text: str) -> None:
        """Publish an event on ``cfbci/<session>/event``; record and log it."""
        message = self._outbox.send("event", session, {"event": event, "message": text})
        (log.warning if event == "error" else log.info)("%s: %s", event, text)
        recorder = self.recordings.get(session)
        if recorder is not None:
            fields = {"seq": message.seq, "t_ns": message.t_ns, "event": event, "message": text}
            recorder.record("/event", fields, message.t_ns)
            recorder.record_log(_LOG_LEVELS.get(event, 2), f"{event}: {text}", message.t_ns)

    def _reject(self, error: ProtocolError) -> None:
        """Report a rejected message where the protocol says (its session, else ``_``)."""
        session = error.session if error.session is not None else NO_SESSION
        self._event(session, "error", str(error))
        if session not in self._sessions:
            self._outbox.forget(session)


def serve(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    record_dir: Path | None = None,
    on_end: SessionEndHook | None = None,
) -> None:
    """Run a :class:`PipelineService` until SIGINT or SIGTERM, then shut down cleanly.

    Recordings are closed and the Zenoh session is closed before returning. Meant as the
    main function of ``cfbci serve`` or of a spawned process.

    Parameters
    ----------
    listen, connect : sequence of str
        Zenoh endpoints (see :func:`wire.zenoh_config.peer_config`).
    record_dir : Path or None
        Directory of the recordings (``<session>.mcap``); None records nothing.
    on_end : callable or None
        See :class:`PipelineService`.
    """
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    keep_freed_memory()
    with zenoh.open(peer_config(listen, connect)) as session:
        service = PipelineService(session, record_dir, on_end=on_end)
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, lambda *_: service.stop())
        log.info("serving on listen=%s connect=%s", list(listen), list(connect))
        service.run()
    log.info("stopped")
