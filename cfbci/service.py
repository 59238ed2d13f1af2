"""The pipeline service: runs the calibration-free learner on the epochs sources send.

:class:`PipelineService` subscribes to ``cfbci/*/config`` and ``cfbci/*/epoch`` and keeps
one :class:`_Session` per session id: the learner, the agent's cell, the step of the last
move and the sequence tracker of the epochs. It answers every accepted epoch with the next
``move`` and a ``state`` (docs/protocol.md), and every message it cannot accept with an
``error`` event; a rejected message never reaches the learner. A session it cannot run,
or stops running (a limit of :class:`cfbci.limits.ServiceLimits` exceeded, no subscriber,
idle), gets a ``session_rejected`` event instead.

**Isolation.** Messages wait in a :class:`wire.intake.Intake` (bounded, one FIFO per running
session served round-robin, per-session rate limit); the loop never blocks on anything but
the intake: a config whose source has not subscribed to its events yet waits as a
:class:`_Pending` entry, started by :meth:`PipelineService.housekeeping` once it has; so
does a puddle-world config while its world's policy tables, which every puddle session of
the process shares, are built on a thread of their own (:class:`_PuddleTables`: 3-4 s and
about 300 MiB of temporaries, once per process).

**Restart and resume.** Started on a record directory, the service resumes every session
recorded there that neither ended nor was rejected: it re-runs the learner over the
recorded epochs (:class:`replay.rerun.Rerun`, as ``cfbci replay`` does), checks that the
re-run reproduces the recorded moves, rewrites the recording in place and continues it
(one file, every step once), and publishes the current move and state again. The source
re-sends its unanswered epoch until the next move arrives; a re-sent epoch already
answered (same step, ``seq`` and ``t_ns``) is answered again, unrecorded.

**Labels never reach the learner.** The service does not subscribe to ``truth`` for
itself: a separate :class:`Recordings` object, which holds the session recorders and no
learner, owns the only ``cfbci/*/truth`` subscription and writes what arrives there to the
recordings. :class:`_Session`, the learner's side, is never given a truth message.

The world is the config's (:func:`session.config.config_world`). The agent's start state
is the world's :meth:`~calibration_free.world.World.start_state` on the session's *user*
stream (:func:`calibration_free.streams.session_streams` ``[1]``; the grid's: its first
draw), as :class:`acquisition.user.SimulatedUser` draws it, so that a live session replays
``cfbci simulate`` exactly; the learner's stream is ``session_streams(seed)[2]``, and a
stochastic move (the line world's edges) takes the number of its step from the world
stream (:func:`calibration_free.world.transition_draws`). A session of a world in the
plane has no World: its learner is a :class:`session.plane.PlaneStepper`. The continuous
world's (:class:`~session.plane.ContinuousStepper`: probe points and particles,
docs/protocol.md) is recorded with its particles on ``/particles``; the puddle world's
(:class:`~session.plane.PuddleStepper`) owns the agent's state and the world stream, draws
each move's outcome and, after an epoch that says ``reset``, the restart state, and is
recorded with the goal cells' probabilities on ``/belief`` and the agent's moves on
``/position``.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from calibration_free.learner import CalibrationFreeLearner
from calibration_free.streams import session_streams
from calibration_free.world import TransitionDraws, World, transition_draws
from cfbci.limits import ServiceLimits, world_memory_bytes
from cfbci.memory import keep_freed_memory
from decoding.features import ErrPFeatures
from replay.recording import Recording, SessionRecorder, decode_array, read_recording
from replay.rerun import (
    STATE_MESSAGE_FIELDS,
    move_divergence,
    recorded_resets,
    recorded_signals,
    rerun_of,
    signal_extractor,
)
from session.config import (
    config_world,
    learner_settings,
    move_fields,
    resolved_config,
    start_state,
    state_fields,
    target_text,
    world_text,
)
from session.plane import (
    TASK_CELLS,
    PlaneStepper,
    PuddleStepper,
    goal_probabilities,
    is_plane,
    plane_memory_bytes,
    plane_stepper,
    puddle_world,
    puddle_world_built,
)
from wire import protocol
from wire.intake import Intake, session_of
from wire.protocol import NO_SESSION, ProtocolError, SequenceTracker
from wire.services import ServiceRegistration, default_service_id
from wire.transport import Outbox, Pump, Received
from wire.zenoh_config import peer_config

log = logging.getLogger("cfbci.service")

#: Seconds the loop waits for a message while a session waits for its source to subscribe.
TICK = 0.02
#: Seconds the loop waits for a message otherwise (between two idle checks).
IDLE_TICK = 0.5
#: Error events published per session id per second; further ones are only counted.
ERRORS_PER_SECOND = 20
#: Error and rejection events published per second in all.
EVENTS_PER_SECOND = 200
#: Seconds an ended session's recording waits for the truth of its last step.
TRUTH_WAIT = 10.0
#: Configs that may wait for their source to subscribe, per session of ``max_sessions``.
PENDING_PER_SESSION = 4
#: foxglove.Log levels of the event kinds.
_LOG_LEVELS = {"error": 4, "session_rejected": 4, "info": 2}


class Recordings:
    """The session recorders, and the only reader of ``truth``.

    One MCAP file per session, ``<directory>/<session>.mcap``. A recording is closed when
    its session has ended and the truth of its last step has been recorded (at once if no
    truth arrived at all; after :data:`TRUTH_WAIT` seconds at the latest), or by
    :meth:`close`.

    Parameters
    ----------
    directory : Path or None
        Where recordings go; None records nothing.
    """

    def __init__(self, directory: Path | None) -> None:
        self.directory = directory
        self._recorders: dict[str, SessionRecorder] = {}
        self._truths: dict[str, set[int]] = {}  # session -> steps whose truth is recorded
        self._awaiting: dict[str, int] = {}  # ended session -> step whose truth closes it
        self._deadlines: dict[str, int] = {}  # ended session -> monotonic ns to close anyway

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

    def resume(self, recording: Recording) -> SessionRecorder | None:
        """Continue an unfinished recording in place (None when not recording).

        Its messages are written again, in log-time order, to a new file that then replaces
        it (so a crash meanwhile leaves the original intact); new messages follow them.
        """
        if self.directory is None:
            return None
        path = self.directory / f"{recording.session}.mcap"
        partial = path.with_suffix(".mcap.resuming")
        recorder = SessionRecorder(partial, recording.session, recording.config)
        # An epoch recorded without its features was not accepted (killed in between):
        # left out, since its re-sent copy (same seq) will be.
        accepted = {m["seq"] for _, m in recording.messages.get("/features", [])}
        messages = sorted(
            (log_time, order, index, topic, message)
            for order, (topic, entries) in enumerate(recording.messages.items())
            if topic != "/config"
            for index, (log_time, message) in enumerate(entries)
            if topic != "/epoch" or message["seq"] in accepted
        )
        for log_time, _, _, topic, message in messages:
            recorder.record(topic, message, log_time)
        os.replace(partial, path)
        recorder.path = path
        self._truths[recording.session] = {
            m["step"] for _, m in recording.messages.get("/truth", [])
        }
        self._recorders[recording.session] = recorder
        return recorder

    def get(self, session: str) -> SessionRecorder | None:
        """The open recorder of a session, if any."""
        return self._recorders.get(session)

    def truth(self, received: Received, latest_step: int) -> None:
        """Record a ``truth`` message on its session's ``/truth`` (else log why not).

        Only the truth of a step not recorded yet and at most ``latest_step`` (the
        session's last move; 0 when not running) is recorded: once per step.
        """
        try:
            message = protocol.decode(received.data, key_expr=received.key_expr)
        except ProtocolError as error:
            log.debug("truth not recorded: %s", error)
            return
        recorder = self._recorders.get(message.session)
        if recorder is None:
            log.debug("truth of session %r not recorded: no open recording", message.session)
            return
        step = message.fields["step"]
        recorded = self._truths.setdefault(message.session, set())
        if step in recorded or step > max(latest_step, self._awaiting.get(message.session, 0)):
            log.debug("truth of step %d of session %r not recorded", step, message.session)
            return  # re-sent with its epoch, or of no step yet
        record = {"seq": message.seq, "t_ns": message.t_ns, **message.fields}
        recorder.record("/truth", record, received.t_ns)
        recorded.add(step)
        if self._awaiting.get(message.session) == message.fields["step"]:
            self._close(message.session)

    def end(self, session: str, last_step: int) -> None:
        """The session ended at ``last_step``: close now, or once that step's truth is in."""
        if session not in self._recorders:
            return
        recorded = self._truths.get(session)
        if not recorded or last_step in recorded:
            self._close(session)
        else:
            self._awaiting[session] = last_step
            self._deadlines[session] = time.monotonic_ns() + int(TRUTH_WAIT * 1e9)

    def close_overdue(self) -> None:
        """Close the recordings of ended sessions whose last truth is overdue."""
        now = time.monotonic_ns()
        for session in [s for s, deadline in self._deadlines.items() if now >= deadline]:
            log.warning("session %r: the truth of its last step never came", session)
            self._close(session)

    def _close(self, session: str) -> None:
        self._recorders.pop(session).close()
        self._truths.pop(session, None)
        self._awaiting.pop(session, None)
        self._deadlines.pop(session, None)

    def close(self) -> None:
        """Close every recording."""
        for session in list(self._recorders):
            self._close(session)


class Rejection(ProtocolError):
    """A session the service cannot run, or stops running: a ``session_rejected`` event.

    ``config_t_ns`` is the ``t_ns`` of the config it answers (see docs/protocol.md).
    """

    def __init__(self, problem: str, session: str, seq: int | None, config_t_ns: int) -> None:
        super().__init__(problem, session, seq)
        self.config_t_ns = config_t_ns


@dataclass
class _Pending:
    """A started config whose source has not subscribed to the session's events yet."""

    message: protocol.Message
    publisher: zenoh.Publisher
    deadline_ns: int


@dataclass(frozen=True)
class _EndedAtResume:
    """What is kept of a session that ended when the service resumed it, to answer a
    re-send of its last epoch: its id, last step, that epoch's ``(step, seq, t_ns)`` and the
    last state's fields and confidence (the learner is not kept)."""

    id: str
    step: int
    last_epoch: tuple[int, int, int] | None
    beliefs: tuple[dict[str, Any], Any]


@dataclass
class _Session:
    """What the service knows of one running session (the learner's side: no labels).

    Attributes
    ----------
    id : str
    config : dict
        The config message's fields.
    config_t_ns : int
        The config message's ``t_ns`` (which ``session_started`` and a rejection name).
    world : World or None
        None in a plane world.
    draws : TransitionDraws or None
        The session's world stream (stochastic moves); None in a plane world.
    learner : CalibrationFreeLearner or PlaneStepper
        The stepper of a plane world's learner there.
    state : int or None
        The agent's state before the last move (None in a plane world).
    recorder : SessionRecorder or None
    active_ns : int
        ``time.monotonic_ns()`` of the start, the last accepted epoch or the resumption.
    action : int
        The last move's action (index into the world's actions).
    step : int
        The last move's step (1-based): the step the next epoch must carry.
    epochs : SequenceTracker
        Sequence numbers of the session's accepted epochs.
    last_epoch : tuple of int or None
        ``(step, seq, t_ns)`` of the last accepted epoch: a re-send of it is answered again.
    answer : tuple or None
        The last move's fields and the state that accompanied it (fields, confidence).
    answer_unheard : bool
        The session was resumed and its answer re-sent before its source could have
        reconnected: it is sent again before the next new epoch is taken (a source that
        saw the move but not its state before the kill needs the state).
    extractor : ErrPFeatures or None
        Fitted on the first raw epoch (``signal`` "epochs").
    shape : tuple of int or None
        Payload shape of the session's first accepted epoch.
    update_ns : list of int
        The learner's time per epoch, ns: ``observe`` of the epoch plus ``propose`` of the
        next move (:data:`time.perf_counter_ns` differences; none for the last epoch).
    queued_ms : list of float
        Per epoch with a next move, as ``update_ns``: its queueing delay in ms, from its
        arrival (the intake's pump) to the start of its computation.
    """

    id: str
    config: dict[str, Any]
    config_t_ns: int
    world: World | None
    draws: TransitionDraws | None
    learner: CalibrationFreeLearner | PlaneStepper
    state: int | None
    recorder: SessionRecorder | None
    active_ns: int
    action: int = 0
    step: int = 0
    epochs: SequenceTracker = field(default_factory=SequenceTracker)
    last_epoch: tuple[int, int, int] | None = None
    answer: tuple[dict[str, Any], dict[str, Any], np.ndarray] | None = None
    answer_unheard: bool = False
    extractor: ErrPFeatures | None = None
    shape: tuple[int, ...] | None = None
    update_ns: list[int] = field(default_factory=list)
    queued_ms: list[float] = field(default_factory=list)


class _PuddleTables:
    """Builds the puddle world's policy tables (:func:`session.plane.puddle_world`) on a
    daemon thread, once per process, so that the service's loop never waits for them."""

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def ready(self) -> bool:
        """Whether the tables are built; starts building them if nobody has.

        Raises
        ------
        RuntimeError
            If the build failed (e.g. out of memory).
        """
        if puddle_world_built():
            return True
        if self._error is not None:
            raise RuntimeError(f"the puddle world's tables could not be built: {self._error!r}")
        if self._thread is None:
            self._thread = threading.Thread(target=self._build, name="puddle-tables",
                                            daemon=True)
            self._thread.start()
            log.info("building the puddle world's policy tables (once per process)")
        return False

    def _build(self) -> None:
        try:
            puddle_world()
        except BaseException as error:  # reported by ready(), on the loop
            self._error = error


#: Called with a session's id, its :attr:`_Session.update_ns` and its
#: :attr:`_Session.queued_ms` when the session ends.
SessionEndHook = Callable[[str, list[int], list[float]], None]


class _ErrorBudget:
    """At most :data:`ERRORS_PER_SECOND` error and rejection events per session id per
    second, and :data:`EVENTS_PER_SECOND` in all; the others are only counted (and the
    count logged)."""

    def __init__(self) -> None:
        self._window = 0
        self._counts: Counter[str] = Counter()
        self._total = self._suppressed = 0

    def allows(self, session: str) -> bool:
        window = int(time.monotonic())
        if window != self._window:
            if self._suppressed:
                log.warning("%d error events suppressed in the last second", self._suppressed)
            self._window, self._total, self._suppressed = window, 0, 0
            self._counts.clear()
        self._counts[session] += 1
        self._total += 1
        allowed = self._counts[session] <= ERRORS_PER_SECOND and self._total <= EVENTS_PER_SECOND
        self._suppressed += not allowed
        return allowed


class PipelineService:
    """Runs sessions for any number of sources; see the module docstring.

    Parameters
    ----------
    session : zenoh.Session
        An open Zenoh session (the caller closes it, after :meth:`close`).
    record_dir : Path or None
        Directory of the recordings, ``<session>.mcap``; None: no recording. The
        unfinished sessions recorded there are resumed (:meth:`resume`).
    limits : ServiceLimits
    on_end : callable or None
        Called with ``(session id, update_ns, queued_ms)`` when a session ends normally:
        the learner's time per epoch in ns and each epoch's queueing delay in ms, as
        :attr:`_Session.update_ns` and :attr:`_Session.queued_ms` (``cfbci bench latency``).
    resume : bool
        Resume the unfinished sessions of ``record_dir`` (:meth:`resume`).
    service_id : str or None
        This service's id among several (:mod:`wire.services`; default ``<host>-<pid>``):
        it answers the offers query and runs the configs that name it or no service.

    Use :meth:`run` to serve until :meth:`stop`; :meth:`handle` processes one message.
    """

    def __init__(
        self,
        session: zenoh.Session,
        record_dir: Path | None = None,
        limits: ServiceLimits | None = None,
        on_end: SessionEndHook | None = None,
        resume: bool = True,
        service_id: str | None = None,
    ) -> None:
        self.limits = limits or ServiceLimits()
        self.intake = Intake(self.limits.rate, self.limits.max_message_bytes)
        self.recordings = Recordings(record_dir)
        self.on_end = on_end
        self._outbox = Outbox(session)
        self._sessions: dict[str, _Session] = {}
        self._pending: dict[str, _Pending] = {}
        # Sessions whose last epoch was recorded before a kill and which ended at the
        # resumption, before their source could hear the end: a re-send of that epoch is
        # answered with the last state and session_ended again (at most max_sessions).
        self._ended_at_resume: dict[str, _EndedAtResume] = {}
        self._errors = _ErrorBudget()
        self._puddle_tables = _PuddleTables()
        self._stopped = False
        self.registration = ServiceRegistration(
            session, service_id or default_service_id(),
            lambda: (len(self._sessions) + len(self._pending), self.limits.max_sessions),
        )
        if record_dir is not None and resume:
            self.resume(record_dir)
        prefix = protocol.PREFIX
        self._pumps = [
            Pump(session, f"{prefix}/*/{kind}", kind, self.intake, self.intake.accepts_size)
            # Recorder-only: truth goes to self.recordings, never to a _Session. Truth is
            # declared before epoch, so that a source (re)discovering this service knows the
            # truth subscriber before its epochs are delivered: the truth re-sent with an
            # epoch after a restart is then not lost while the epoch gets through.
            for kind in ("config", "truth", "epoch")
        ]

    @property
    def sessions(self) -> tuple[str, ...]:
        """Ids of the running sessions."""
        return tuple(self._sessions)

    def stop(self) -> None:
        """Make :meth:`run` return (safe to call from a signal handler)."""
        self._stopped = True
        self.intake.stop()

    def run(self) -> None:
        """Handle messages fairly (:class:`wire.intake.Intake`) until :meth:`stop`; start
        the sessions whose source has subscribed, end idle ones; then :meth:`close`."""
        try:
            while not self._stopped:
                received = self.intake.get(TICK if self._pending else IDLE_TICK)
                if received is not None:
                    self.handle(received)
                self.housekeeping()
        finally:
            self.close()

    def close(self) -> None:
        """Stop receiving, record the truths already received (a source's last truth may
        still be queued when a stop comes right after its session ended), close every
        recording and undeclare the publishers."""
        for pump in self._pumps:
            pump.close()
        for received in self.intake.drain():
            if received.tag == "truth":
                self.handle(received)
        self.recordings.close()
        self.registration.close()
        self._outbox.close()

    def handle(self, received: Received) -> None:
        """Process one received message; a bad one yields an ``error`` event, nothing else."""
        try:
            if received.tag == "truth":
                running = self._sessions.get(session_of(received.key_expr) or "")
                self.recordings.truth(received, running.step if running is not None else 0)
            elif received.tag == "config":
                self._on_config(received)
            else:
                self._on_epoch(received, (time.monotonic_ns() - received.t_ns) / 1e6)
        except ProtocolError as error:
            self._reject(error)
        except Exception as exc:  # a bug must not stop the other sessions: report it
            log.exception("internal error on a message of %s", received.key_expr)
            session = session_of(received.key_expr)
            session = session if protocol.TYPES["session"][1](session) else None
            self._reject(ProtocolError(f"internal error: {exc!r}", session))

    def housekeeping(self) -> None:
        """Start the pending sessions whose source has subscribed, reject those that waited
        too long, end the idle sessions, and log the messages the intake dropped."""
        now = time.monotonic_ns()
        for sid, pending in list(self._pending.items()):
            if pending.publisher.matching_status.matching:
                try:
                    if not self._world_ready(pending.message.fields):
                        continue  # its world's tables are being built: no deadline for that
                except RuntimeError as error:
                    del self._pending[sid]
                    self._outbox.forget(sid)
                    self._reject(Rejection(str(error), sid, pending.message.seq,
                                           pending.message.t_ns))
                    continue
                del self._pending[sid]
                self._guarded(sid, lambda p=pending: self._start(p.message, p.publisher))
            elif now >= pending.deadline_ns:
                del self._pending[sid]
                self._outbox.forget(sid)
                self._reject(Rejection(
                    f"no subscriber to the session's events within "
                    f"{self.limits.subscriber_timeout:g} s", sid, pending.message.seq,
                    pending.message.t_ns,
                ))
        for sid, keeper in self.registration.take_conflicts().items():
            self._give_up(sid, f"session {sid!r} is also claimed by service {keeper!r}, which "
                          "keeps it (the smaller id)")
        idle_ns = int(self.limits.idle_timeout * 1e9)
        for session in [s for s in self._sessions.values() if now - s.active_ns > idle_ns]:
            self._abort(session, f"no epoch for {self.limits.idle_timeout:g} s: session ended")
        self.recordings.close_overdue()
        drops = self.intake.take_drops()
        if drops:
            log.warning("intake dropped %s", dict(drops))

    def _give_up(self, sid: str, problem: str) -> None:
        """End a running or waiting session with ``problem``; its claim is withdrawn first,
        before the rejection is published."""
        self.registration.release(sid)
        running, pending = self._sessions.get(sid), self._pending.pop(sid, None)
        if running is not None:
            self._abort(running, problem)
        elif pending is not None:
            self._reject(Rejection(problem, sid, pending.message.seq, pending.message.t_ns))

    def _guarded(self, session: str, action: Callable[[], None]) -> None:
        """Run ``action``; a rejection or a bug is reported on ``session``."""
        try:
            action()
        except ProtocolError as error:
            self._reject(error)
        except Exception as exc:
            log.exception("internal error on session %r", session)
            self._reject(ProtocolError(f"internal error: {exc!r}", session))

    # -- sessions ---------------------------------------------------------------------

    def _on_config(self, received: Received) -> None:
        message = protocol.decode(
            received.data, key_expr=received.key_expr, max_bytes=self.limits.max_message_bytes
        )
        sid, config = message.session, message.fields
        chosen = config.get("service")
        if chosen is not None and chosen != self.registration.service:
            return  # the source chose another service

        def reject(problem: str) -> Rejection:
            return Rejection(problem, sid, message.seq, message.t_ns)

        running = self._sessions.get(sid)
        if running is not None:
            if running.config_t_ns == message.t_ns and running.config == _resolved(config):
                self._event(sid, "session_started", "session already started (config re-sent)",
                            message.t_ns)
                return
            raise reject("a session with this id is already running")
        if sid in self._pending:
            if self._pending[sid].message.t_ns == message.t_ns:
                return  # a re-send: the pending session starts once its source subscribes
            raise reject("a session with this id is already waiting for its source")
        limits = self.limits
        if "grid" in config and not 2 <= config["grid"] <= limits.max_grid:
            raise reject(f"field 'grid' must be in 2..{limits.max_grid}; got {config['grid']}")
        if not 1 <= config["steps"] <= limits.max_steps:
            raise reject(f"field 'steps' must be in 1..{limits.max_steps}; got {config['steps']}")
        if len(config.get("ch_names", ())) > limits.max_epoch_values:
            raise reject(f"more than {limits.max_epoch_values} ch_names")
        try:
            resolved_config(config)
        except (ValueError, TypeError) as exc:
            raise reject(f"bad config: {exc}") from None
        if is_plane(config):
            self._check_plane_memory(config, 0, reject)
        else:
            self._check_memory(sid, config, 0, lambda problem: reject(problem))
        if len(self._sessions) >= limits.max_sessions:
            raise reject(f"the service runs its maximum of {limits.max_sessions} sessions")
        if len(self._pending) >= PENDING_PER_SESSION * limits.max_sessions:
            raise reject(f"{len(self._pending)} sessions already wait for their source")
        try:
            ready = self._world_ready(config)
        except RuntimeError as error:
            raise reject(str(error)) from None
        holder = self.registration.claim(sid) if chosen is not None else None
        if holder is not None:
            raise reject(f"session {sid!r} is already served by service {holder!r}")
        publisher = self._outbox.publisher(protocol.key(sid, "event"))
        if publisher.matching_status.matching and ready:
            self._start(message, publisher)
        else:  # never wait here: the loop starts it once its source subscribes (and its
            # world's tables are built)
            deadline = time.monotonic_ns() + int(limits.subscriber_timeout * 1e9)
            self._pending[sid] = _Pending(message, publisher, deadline)

    def _world_ready(self, config: dict[str, Any]) -> bool:
        """Whether a config's world can start now: always, but for the puddle world while
        its tables are being built (see :class:`_PuddleTables`)."""
        return config.get("world") != "puddle" or self._puddle_tables.ready()

    def _check_memory(
        self,
        sid: str,
        config: dict[str, Any],
        n_features: int,
        reject: Callable[[str], Rejection],
    ) -> None:
        """Reject a session whose :func:`world_memory_bytes` is over the limit."""
        world = config_world(config)
        learner = learner_settings(config["learner"], config["frame"])
        needed = world_memory_bytes(world, learner, config["steps"], n_features)
        if needed > self.limits.max_session_mb * 2**20:
            what = f"{n_features} features, " if n_features else ""
            raise reject(
                f"the session would commit about {needed / 2**20:.0f} MiB ({what}"
                f"{world_text(world)}, {config['steps']} steps, {learner.decoder} decoder), "
                "more than the limit of "
                f"{self.limits.max_session_mb:g} MiB"
            )

    def _check_plane_memory(
        self, config: dict[str, Any], n_features: int, reject: Callable[[str], Rejection]
    ) -> None:
        """Reject a plane-world session whose :func:`session.plane.plane_memory_bytes` is over
        the limit."""
        needed = plane_memory_bytes(config, n_features)
        if needed > self.limits.max_session_mb * 2**20:
            what = f"{n_features} features, " if n_features else ""
            raise reject(
                f"the session would commit about {needed / 2**20:.0f} MiB ({what}"
                f"{config['world']} world, {config['steps']} steps), more than the limit of "
                f"{self.limits.max_session_mb:g} MiB"
            )

    def _start(self, message: protocol.Message, publisher: zenoh.Publisher) -> None:
        """Create the learner and the recording of a config; publish the first move."""
        sid, config = message.session, resolved_config(message.fields)
        if len(self._sessions) >= self.limits.max_sessions:
            raise Rejection(
                f"the service runs its maximum of {self.limits.max_sessions} sessions", sid,
                message.seq, message.t_ns,
            )
        # Recorded with every learner setting it runs with (defaults included).
        recorder = self.recordings.open(sid, {"seq": message.seq, "t_ns": message.t_ns, **config})
        if is_plane(config):
            session = _Session(
                sid, config, message.t_ns, None, None, plane_stepper(config), None,
                recorder, time.monotonic_ns(),
            )
        else:
            world = config_world(config)
            learner_config = learner_settings(config["learner"], config["frame"])
            learner = CalibrationFreeLearner(
                world, learner_config, session_streams(config["seed"])[2]
            )
            session = _Session(
                sid, config, message.t_ns, world, transition_draws(config["seed"]), learner,
                start_state(config["seed"], world), recorder, time.monotonic_ns(),
            )
        self._sessions[sid] = session
        self._ended_at_resume.pop(sid, None)  # the id is reused: its old end is over
        self.intake.open(sid)
        self._event(
            sid,
            "session_started",
            f"session {sid!r}: {config['steps']} steps, {_world_text(session)}, "
            f"{config['frame']} frame, {config['signal']}",
            message.t_ns,
        )
        self._next_move(session)

    def resume(self, record_dir: Path) -> None:
        """Resume every unfinished session recorded in ``record_dir`` (see the module
        docstring); a recording that cannot be resumed is named in the log and left as is."""
        for path in sorted(record_dir.glob("*.mcap")):
            if len(self._sessions) >= self.limits.max_sessions:
                log.warning("not resuming %s: the service runs its maximum of sessions", path)
                continue
            try:
                recording = read_recording(path)
                if path.name == f"{recording.session}.mcap" and unfinished(recording):
                    self._resume(recording)
            except (ValueError, KeyError, TypeError) as exc:
                log.warning("cannot resume %s: %s", path, exc)

    def _resume(self, recording: Recording) -> None:
        """Rebuild a session's learner by re-running it over its recording, and go on."""
        # A recording of an older version may hold only the settings its source sent: it
        # resumes (as it replays) with today's defaults for the others.
        config = resolved_config(
            {k: v for k, v in recording.config.items() if k not in ("seq", "t_ns")}
        )
        rerun = rerun_of(config)
        epochs = recording.accepted_epochs()
        inputs = zip(recorded_signals(recording), recorded_resets(recording), strict=True)
        for signal_, reset in list(inputs)[: rerun.steps]:
            rerun.observe(signal_, reset=reset)
        recorded_moves = [m for _, m in recording.messages.get("/move", [])]
        divergence = move_divergence(recorded_moves, rerun.moves[: len(recorded_moves)])
        if divergence is not None or len(recorded_moves) < len(rerun.moves) - 1:
            raise ValueError(f"the re-run does not reproduce the recording: {divergence}")
        sid = recording.session
        if config.get("service") is not None and (
            holder := self.registration.claim(sid, ask=True)  # just started: ask the network
        ):
            raise ValueError(f"session {sid!r} is already served by service {holder!r}")
        recorder = self.recordings.resume(recording)
        session = _Session(
            sid, config, recording.config["t_ns"], rerun.world, rerun.draws, rerun.learner,
            None if rerun.world is None else rerun.moves[-1]["from_state"], recorder,
            time.monotonic_ns(),
            action=rerun.action, step=len(rerun.moves),
        )
        if epochs:
            last = epochs[-1]
            session.last_epoch = (last["step"], last["seq"], last["t_ns"])
            session.epochs.expected = last["seq"] + 1  # later epochs continue its numbering
            first = decode_array(epochs[0])
            session.shape = first.shape
            session.extractor = signal_extractor(config, first)
        self._sessions[sid] = session
        self.intake.open(sid)
        recorded_states = len(recording.messages.get("/state", []))
        self._event(sid, "info", f"session {sid!r} resumed at step {session.step} after a "
                    f"restart, from its recording")
        if rerun.finished:
            state = rerun.states[-1]
            beliefs = ({k: state[k] for k in STATE_MESSAGE_FIELDS}, state["confidence"])
            self._send_state(session, record=recorded_states < len(rerun.states),
                             beliefs=beliefs)
            self._finish(session)
            self._ended_at_resume[sid] = _EndedAtResume(
                sid, session.step, session.last_epoch, beliefs
            )
            return
        fields, state = rerun.moves[-1], rerun.states[len(rerun.moves) - 1]
        confidence = np.asarray(state["confidence"], dtype=np.float32)
        session.answer = (fields, {k: state[k] for k in STATE_MESSAGE_FIELDS}, confidence)
        record_move = len(recorded_moves) < len(rerun.moves)
        sent = self._send(session, "move", fields, record=record_move)
        if record_move and recorder is not None and isinstance(rerun.learner, PuddleStepper):
            recorder.record_position(
                fields["from_state"], fields["to_state"], fields["step"], sent.t_ns
            )
        self._send_state(session, record=recorded_states < len(rerun.moves),
                         beliefs=session.answer[1:])
        session.answer_unheard = True

    def _on_epoch(self, received: Received, queued_ms: float) -> None:
        message = protocol.decode(
            received.data, key_expr=received.key_expr, max_bytes=self.limits.max_message_bytes
        )
        where = {"session": message.session, "seq": message.seq}
        session = self._sessions.get(message.session)
        identity = (message.fields["step"], message.seq, message.t_ns)
        ended = self._ended_at_resume.get(message.session)
        if session is None and ended is not None and ended.last_epoch == identity:
            self._end_again(ended)
            return
        if session is None:
            problem = "before session_started" if message.session in self._pending else (
                "for an unknown session (no running session has this id)")
            raise ProtocolError(f"epoch {problem}", **where)
        if session.last_epoch == identity:
            self._answer_again(session)
            return
        if session.answer_unheard:
            self._answer_again(session)
        signal_ = self._check_epoch(session, message, where)
        gap = self._check_seq(session.epochs, where)
        if gap is not None:
            self._event(session.id, "info", gap)
        if session.shape is None:
            def reject(problem: str) -> Rejection:
                return Rejection(problem, session.id, message.seq, session.config_t_ns)

            if session.world is None:
                self._check_plane_memory(session.config, signal_.shape[0], reject)
            else:
                self._check_memory(session.id, session.config, signal_.shape[0], reject)
        assert message.payload is not None  # decode guarantees an epoch's payload
        session.shape = message.payload.shape
        session.last_epoch = (message.fields["step"], message.seq, message.t_ns)
        session.active_ns = time.monotonic_ns()
        if session.recorder is not None:
            header = {"seq": message.seq, "t_ns": message.t_ns, "units": "uV", **message.fields}
            session.recorder.record_array("/epoch", header, message.payload, received.t_ns)
            header = {"seq": message.seq, "t_ns": message.t_ns, "step": session.step}
            session.recorder.record_array("/features", header, signal_, received.t_ns)
        started_ns = time.perf_counter_ns()
        if isinstance(session.learner, PlaneStepper):
            session.learner.observe(signal_, message.fields.get("reset", False))
        else:
            assert session.world is not None and session.draws is not None
            session.learner.observe(session.state, session.action, signal_)
            session.state = session.world.step(
                session.state, session.action, session.draws.uniform(session.step)
            )
        if session.step < session.config["steps"]:
            self._next_move(session, started_ns, queued_ms)
            return
        self._send_state(session)
        self._finish(session)

    def _answer_again(self, session: _Session) -> None:
        """A re-sent epoch already answered: publish its move and state again (unrecorded)."""
        assert session.answer is not None
        session.answer_unheard = False
        fields, state, confidence = session.answer
        self._send(session, "move", fields, record=False)
        self._send(session, "state", state, confidence, record=False)

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
        if "reset" in fields and session.config["world"] != "puddle":
            raise ProtocolError(
                f"field 'reset' is allowed only in the puddle world; this session's world is "
                f"{session.config['world']!r}",
                **where,
            )
        if session.shape is not None and payload.shape != session.shape:
            raise ProtocolError(
                f"epoch shape {list(payload.shape)} differs from the session's first epoch's "
                f"{list(session.shape)}",
                **where,
            )
        limit = self.limits.max_epoch_values if fields["signal"] == "epochs" else (
            self.limits.max_features)
        if payload.size > limit:
            raise ProtocolError(
                f"epoch of {payload.size} values, more than the limit of {limit}", **where
            )
        if fields["signal"] == "features":
            return payload
        try:
            extractor = session.extractor or ErrPFeatures(
                session.config["sfreq"], session.config["tmin"], session.config["ch_names"]
            ).fit(payload[None])
            signal_ = extractor.transform(payload[None])[0].astype(np.float32)
        except ValueError as exc:
            raise ProtocolError(f"cannot extract ErrP features: {exc}", **where) from None
        session.extractor = extractor
        return signal_

    def _next_move(
        self, session: _Session, started_ns: int | None = None, queued_ms: float | None = None
    ) -> None:
        """Choose, publish and record the move of the next step, then its state.

        ``started_ns``: :func:`time.perf_counter_ns` before the learner observed the epoch
        that led here (None for the first move); the learner's time is then appended to
        :attr:`_Session.update_ns`. ``queued_ms``: how long that epoch waited in the
        intake. Both are recorded with the move (``update_ms``, ``queued_ms``).
        """
        if isinstance(session.learner, PlaneStepper):
            self._next_plane_move(session, started_ns, queued_ms)
            return
        proposal = session.learner.propose(session.state)
        timing = self._timing(session, started_ns, queued_ms)
        session.step += 1
        session.action = proposal.action
        fields = move_fields(session.world, session.step, session.state, proposal, session.draws)
        self._send(session, "move", fields, recorded_only=timing)
        state, confidence = self._send_state(session)
        session.answer = (fields, state, confidence)
        if proposal.declares_target:
            self._event(
                session.id,
                "target_reached",
                target_text(session.world, session.step, session.state),
            )

    @staticmethod
    def _timing(
        session: _Session, started_ns: int | None, queued_ms: float | None
    ) -> dict[str, float]:
        """The recorded-only timing fields of a move (see :meth:`_next_move`); appends the
        learner's time to :attr:`_Session.update_ns`."""
        timing = {}
        if started_ns is not None:
            session.update_ns.append(time.perf_counter_ns() - started_ns)
            timing["update_ms"] = session.update_ns[-1] / 1e6
        if queued_ms is not None:
            session.queued_ms.append(queued_ms)
            timing["queued_ms"] = queued_ms
        return timing

    def _next_plane_move(
        self, session: _Session, started_ns: int | None, queued_ms: float | None
    ) -> None:
        """:meth:`_next_move` in a plane world: the next probe point (continuous) or move
        (puddle), then the beliefs as the latest epoch left them (the continuous world's
        particles as that epoch scored them)."""
        assert isinstance(session.learner, PlaneStepper)
        fields = session.learner.move()
        timing = self._timing(session, started_ns, queued_ms)
        session.step = fields["step"]
        message = self._send(session, "move", fields, recorded_only=timing)
        if session.recorder is not None and isinstance(session.learner, PuddleStepper):
            session.recorder.record_position(
                fields["from_state"], fields["to_state"], fields["step"], message.t_ns
            )
        state, confidence = self._send_state(session)
        session.answer = (fields, state, confidence)

    def _send_state(
        self,
        session: _Session,
        record: bool = True,
        beliefs: tuple[dict[str, Any], Any] | None = None,
    ) -> tuple[dict[str, Any], np.ndarray]:
        """Publish (and record) the state: the learner's, or ``beliefs`` (fields,
        confidence) when given; return what was sent."""
        if beliefs is None:
            learner = session.learner
            beliefs = learner.state if isinstance(learner, PlaneStepper) else (
                state_fields(learner))
        fields, confidence = beliefs
        confidence = np.asarray(confidence, dtype=np.float32)
        message = self._send(session, "state", fields, confidence, record=record)
        if session.recorder is not None and record:
            if session.config.get("world") == "puddle":
                session.recorder.record_grid(
                    goal_probabilities(confidence), TASK_CELLS, 1.0 / TASK_CELLS, "plane",
                    message.t_ns,
                )
            elif session.world is None:
                session.recorder.record_particles(fields["points"], confidence, message.t_ns)
            else:
                session.recorder.record_belief(confidence, session.world, message.t_ns)
        return fields, confidence

    def _send(
        self,
        session: _Session,
        kind: str,
        fields: dict[str, Any],
        payload: Any = None,
        recorded_only: dict[str, Any] | None = None,
        record: bool = True,
    ) -> protocol.Message:
        """Publish a message of the session; record it (unless not ``record``) with
        ``recorded_only`` fields added."""
        message = self._outbox.send(kind, session.id, fields, payload)
        if session.recorder is not None and record:
            record_ = {"seq": message.seq, "t_ns": message.t_ns, **fields, **(recorded_only or {})}
            if payload is not None:
                record_["confidence"] = [float(x) for x in payload]
            session.recorder.record(f"/{kind}", record_, message.t_ns)
        return message

    def _end_again(self, ended: _EndedAtResume) -> None:
        """The re-sent last epoch of a session that ended at its resumption: publish its
        last state and ``session_ended`` again (unrecorded: its recording is closed)."""
        fields, confidence = ended.beliefs
        self._outbox.send("state", ended.id, fields, np.asarray(confidence, dtype=np.float32))
        self._event(
            ended.id, "session_ended", f"session {ended.id!r} ended after {ended.step} "
            "steps (sent again: it ended when the service resumed it)"
        )
        self._outbox.forget(ended.id)

    def _finish(self, session: _Session) -> None:
        """The session's last epoch is in: ``session_ended``, and forget it."""
        self._event(
            session.id, "session_ended", f"session {session.id!r} ended after {session.step} steps"
        )
        if self.on_end is not None:
            self.on_end(session.id, session.update_ns, session.queued_ms)
        self._end(session, session.step)

    def _abort(self, session: _Session, problem: str) -> None:
        """End a session before its last step, with a ``session_rejected`` event."""
        self._reject(Rejection(problem, session.id, None, session.config_t_ns))

    def _end(self, session: _Session, last_epoch_step: int) -> None:
        del self._sessions[session.id]
        self.registration.release(session.id)
        self.intake.close(session.id)
        self.recordings.end(session.id, last_epoch_step)
        self._outbox.forget(session.id)

    # -- events -----------------------------------------------------------------------

    def _event(
        self, session: str, event: str, text: str, config_t_ns: int | None = None
    ) -> None:
        """Publish an event on ``cfbci/<session>/event``; record and log it."""
        fields = {"event": event, "message": text, "config_t_ns": config_t_ns}
        message = self._outbox.send("event", session, fields)
        (log.warning if event in ("error", "session_rejected") else log.info)(
            "%s: %s", event, text
        )
        recorder = self.recordings.get(session)
        if recorder is not None:
            recorder.record("/event", {"seq": message.seq, "t_ns": message.t_ns, **fields},
                            message.t_ns)
            recorder.record_log(_LOG_LEVELS.get(event, 2), f"{event}: {text}", message.t_ns)

    def _reject(self, error: ProtocolError) -> None:
        """Report a rejected message where the protocol says (its session, else ``_``);
        a :class:`Rejection` of a running session (the one its ``config_t_ns`` names) ends
        it. A session that neither runs nor waits for its source holds no claim (say its
        start failed): the claim is withdrawn before the rejection is published, so that a
        source told of it may pick another service at once."""
        session = error.session if error.session is not None else NO_SESSION
        running = self._sessions.get(session)
        if running is None and session not in self._pending:
            self.registration.release(session)
        ends = running is not None and running.config_t_ns == getattr(error, "config_t_ns", -1)
        if isinstance(error, Rejection) and (ends or self._errors.allows(session)):
            self._event(session, "session_rejected", str(error), error.config_t_ns)
            if ends:
                assert running is not None
                self._end(running, running.step - 1)
        elif self._errors.allows(session):
            self._event(session, "error", str(error))
        if session not in self._sessions and session not in self._pending:
            never_ran = session != NO_SESSION and self.recordings.get(session) is None
            self._outbox.forget(session, numbering=never_ran)


def _resolved(config: dict[str, Any]) -> dict[str, Any] | None:
    """:func:`resolved_config`, or None for a config whose learner settings are bad."""
    try:
        return resolved_config(config)
    except (ValueError, TypeError):
        return None


def _world_text(session: _Session) -> str:
    if session.world is None:
        return f"{session.config['world']} world"
    return world_text(session.world)


def unfinished(recording: Recording) -> bool:
    """Whether a recorded session started and neither ended nor was rejected (for its own
    config): a session to resume."""
    if not recording.config or not recording.messages.get("/move"):
        return False
    t_ns = recording.config.get("t_ns")
    for _, event in recording.messages.get("/event", []):
        if event["event"] == "session_ended" or (
            event["event"] == "session_rejected" and event.get("config_t_ns") == t_ns
        ):
            return False
    return True


def serve(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    record_dir: Path | None = None,
    on_end: SessionEndHook | None = None,
    limits: ServiceLimits | None = None,
    zenoh_config: Path | None = None,
    resume: bool = True,
    service_id: str | None = None,
) -> None:
    """Run a :class:`PipelineService` until SIGINT or SIGTERM, then shut down cleanly.

    Recordings are closed and the Zenoh session is closed before returning. Meant as the
    main function of ``cfbci serve`` or of a spawned process.

    Parameters
    ----------
    listen, connect : sequence of str
        Zenoh endpoints (see :func:`wire.zenoh_config.peer_config`).
    record_dir : Path or None
        Directory of the recordings (``<session>.mcap``); None records nothing. Unfinished
        sessions recorded there are resumed.
    on_end : callable or None
        See :class:`PipelineService`.
    limits : ServiceLimits or None
        Default :class:`cfbci.limits.ServiceLimits`.
    zenoh_config : Path or None
        Zenoh JSON5 configuration merged over the defaults (``--zenoh-config``).
    resume : bool
        Resume the unfinished sessions recorded in ``record_dir``.
    service_id : str or None
        See :class:`PipelineService`.
    """
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    keep_freed_memory()
    with zenoh.open(peer_config(listen, connect, zenoh_config)) as session:
        service = PipelineService(
            session, record_dir, limits, on_end=on_end, resume=resume, service_id=service_id
        )
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, lambda *_: service.stop())
        log.info("service %s serving on listen=%s connect=%s", service.registration.service,
                 list(listen), list(connect))
        service.run()
    log.info("stopped")
