"""The service's loop: intake, dispatch, housekeeping, events and rejections.

`PipelineService` subscribes to ``cfbci/**/config``, ``ready``, ``truth``, ``epoch``,
``prior`` (uploads to its prior store) and ``control`` (`cfbci.service.control`) and
keeps one `cfbci.service.running.RunningSession` per session id. Messages wait in a
`wire.intake.Intake` (bounded, one FIFO per running session served round-robin,
per-session rate limit); the loop never blocks on anything but the intake. A config is
admitted (`cfbci.service.admission`) and starts once its source answers the
``session_pending`` event's challenge with a ``ready`` message; an epoch goes down its
session's path (`RunningSession.epoch`); a truth goes to the recordings
(`cfbci.service.recordings.Recordings`), never to a session. Every message the
service cannot accept gets an ``error`` event; a session it cannot run, or stops running (a
limit exceeded, no answer to its challenge, no epoch), a ``session_rejected`` event.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from cfbci.service.admission import (
    Pending,
    PuddleTables,
    Rejection,
    check_config,
    check_quota,
    confirm,
    make_room,
    resolved_or_none,
    take_due,
)
from cfbci.service.control import Controls
from cfbci.service.events import ErrorBudget, Events
from cfbci.service.limits import ServiceLimits
from cfbci.service.priors import PriorStore, default_store
from cfbci.service.recordings import Recordings
from cfbci.service.resume import EndedAtResume, end_again, resume_recorded
from cfbci.service.running import RunningSession, next_due
from session.config import resolved_config
from wire import protocol
from wire.intake import Intake, session_of
from wire.protocol import NO_SESSION, ProtocolError
from wire.services import ServiceRegistration, default_service_id
from wire.transport import Outbox, Pump, Received

log = logging.getLogger("cfbci.service")

#: Seconds the loop waits for a message while a session waits for its source to subscribe.
TICK = 0.02
#: Seconds the loop waits for a message otherwise (between two idle checks).
IDLE_TICK = 0.5
#: Configs that may wait for their source to subscribe, per session of ``max_sessions``.
PENDING_PER_SESSION = 4


#: Called with a session's id, its `RunningSession.update_ns` and its
#: `RunningSession.queued_ms` when the session ends.
SessionEndHook = Callable[[str, list[int], list[float]], None]


class PipelineService:
    """Runs sessions for any number of sources; see the module docstring.

    Parameters
    ----------
    session : zenoh.Session
        An open Zenoh session (the caller closes it, after `close`).
    record_dir : Path or None
        Directory of the recordings, ``<session>.mcap``; None: no recording. The
        unfinished sessions recorded there are resumed
        (`cfbci.service.resume.resume_recorded`).
    limits : ServiceLimits
    on_end : callable or None
        Called with ``(session id, update_ns, queued_ms)`` when a session ends normally:
        the learner's time per epoch in ns and each epoch's queueing delay in ms, as
        `RunningSession.update_ns` and `RunningSession.queued_ms`
        (``cfbci bench latency``).
    resume : bool
        Resume the unfinished sessions of ``record_dir``.
    service_id : str or None
        This service's id among several (`wire.services`; default ``<host>-<pid>``):
        it answers the offers query and runs the configs that name it or no service.
    prior_dir : Path or None
        The prior store (`cfbci.service.priors`); default ``<record_dir>/priors``.

    Use `run` to serve until `stop`; `handle` processes one message.
    """

    def __init__(
        self,
        session: zenoh.Session,
        record_dir: Path | None = None,
        limits: ServiceLimits | None = None,
        on_end: SessionEndHook | None = None,
        resume: bool = True,
        service_id: str | None = None,
        prior_dir: Path | None = None,
    ) -> None:
        self.limits = limits or ServiceLimits()
        self.intake = Intake(self.limits.rate, self.limits.max_message_bytes)
        self.recordings = Recordings(record_dir)
        self.priors = PriorStore(prior_dir or default_store(record_dir), self.limits)
        self.on_end = on_end
        self._outbox = Outbox(session)
        self._sessions: dict[str, RunningSession] = {}
        self._pending: dict[str, Pending] = {}
        # Sessions whose last epoch was recorded before a kill and which ended at the resumption,
        # unheard: a re-send of that epoch gets the last state and session_ended again.
        self._ended_at_resume: dict[str, EndedAtResume] = {}
        self._errors = ErrorBudget()
        self._puddle_tables = PuddleTables()
        self._stopped = False
        self.events = Events(self._outbox, self.recordings)
        self.controls = Controls(self.events.publish, self._sessions.get,
                                 lambda s: self._end(s, s.step - 1), self.limits)
        self.registration = ServiceRegistration(
            session, service_id or default_service_id(),
            lambda: (len(self._sessions) + len(self._pending), self.limits.max_sessions),
        )
        if record_dir is not None and resume:
            resume_recorded(self, record_dir)
        prefix = protocol.PREFIX
        self._pumps = [
            Pump(session, f"{prefix}/**/{kind}", kind, self.intake, self.intake.accepts_size)
            # Recorder-only: truth goes to self.recordings, never to a session. Truth is
            # declared before epoch, so that a source (re)discovering this service knows the
            # truth subscriber before its epochs are delivered: the truth re-sent with an
            # epoch after a restart is then not lost while the epoch gets through.
            for kind in ("config", "ready", "truth", "epoch", "prior", "control")
        ]

    @property
    def sessions(self) -> tuple[str, ...]:
        """Ids of the running sessions."""
        return tuple(self._sessions)

    def stop(self) -> None:
        """Make `run` return (safe to call from a signal handler)."""
        self._stopped = True
        self.intake.stop()

    def run(self) -> None:
        """Handle messages fairly (`wire.intake.Intake`) until `stop`; publish the states
        due, start the sessions whose source has subscribed, end idle ones; then `close`."""
        try:
            while not self._stopped:
                for due in [s for s in self._sessions.values() if s.following is not None]:
                    self._guarded(due.id, lambda s=due: s.settle(time.monotonic_ns()))
                tick = next_due(self._sessions.values(), TICK if self._pending else IDLE_TICK)
                received = self.intake.get(tick)
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
        for session in list(self._sessions.values()):
            self._guarded(session.id, session.settle)  # a failure leaves the rest to close
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
            elif received.tag == "ready":
                self._on_ready(received)
            elif received.tag == "prior":
                self._forget_idle(self.priors.receive(received, self.events.publish))
            elif received.tag == "control":  # a resumption hands back the epoch held
                for held in self.controls.command(received):
                    self.handle(held)
            elif not self.controls.hold(received):
                self._on_epoch(received, (time.monotonic_ns() - received.t_ns) / 1e6)
        except ProtocolError as error:
            self._reject(error)
        except Exception as exc:  # a bug must not stop the other sessions: report it
            log.exception("internal error on a message of %s", received.key_expr)
            session = session_of(received.key_expr)
            session = session if protocol.TYPES["session"][1](session) else None
            self._reject(ProtocolError(f"internal error: {exc!r}", session))

    def housekeeping(self) -> None:
        """Start the pending sessions whose source has answered their challenge, reject
        those that waited too long, end the idle sessions and those that never received an
        epoch, and log the messages the intake dropped."""
        now = time.monotonic_ns()
        for sid, pending, problem in take_due(self._pending, now, self._world_ready):
            if problem is None:
                self._guarded(sid, lambda p=pending: self._start(p.message, p.publisher))
                continue
            self._outbox.forget(sid)
            problem = problem or (
                "no subscriber to the session's events answered its challenge within "
                f"{self.limits.subscriber_timeout:g} s")
            self._reject(Rejection(problem, sid, pending.message.seq, pending.message.t_ns))
        for sid, keeper in self.registration.take_conflicts().items():
            self._give_up(sid, f"session {sid!r} is also claimed by service {keeper!r}, which "
                          "keeps it (the smaller id)")
        for session, problem in self.controls.overdue(self._sessions.values(), now):
            self._abort(session, problem)
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
            if running.config_t_ns == message.t_ns and running.config == resolved_or_none(config):
                self.events.publish(sid, "session_started",
                                    "session already started (config re-sent)", message.t_ns)
                return
            raise reject("a session with this id is already running")
        if sid in self._pending:
            if self._pending[sid].message.t_ns == message.t_ns:  # a re-send: challenge again
                self._challenge(sid, self._pending[sid])
                return
            raise reject("a session with this id is already waiting for its source")
        limits = self.limits
        check_config(config, limits, reject)
        check_quota(sid, self._sessions, self._pending, limits, reject)
        self.priors.check(sid, config, reject)
        if len(self._sessions) >= limits.max_sessions:
            raise reject(f"the service runs its maximum of {limits.max_sessions} sessions")
        if len(self._pending) >= PENDING_PER_SESSION * limits.max_sessions:
            oldest, dropped = make_room(self._pending, reject)  # its source never answered
            self._outbox.forget(oldest)
            self._reject(Rejection(
                f"{len(self._pending) + 1} sessions wait for their source: the oldest that "
                "has not answered its challenge makes room for a newer config", oldest,
                dropped.message.seq, dropped.message.t_ns,
            ))
        try:
            self._world_ready(config)  # starts building a puddle world's tables
        except RuntimeError as error:
            raise reject(str(error)) from None
        holder = self.registration.claim(sid) if chosen is not None else None
        if holder is not None:
            raise reject(f"session {sid!r} is already served by service {holder!r}")
        # Never wait here: the loop starts it once its source answers (and its world is built).
        publisher = self._outbox.publisher(protocol.key(sid, "event"))
        deadline = time.monotonic_ns() + int(limits.subscriber_timeout * 1e9)
        self._pending[sid] = Pending(message, publisher, deadline)
        self._challenge(sid, self._pending[sid])

    def _challenge(self, sid: str, pending: Pending) -> None:
        """Publish the ``session_pending`` event whose challenge the source answers."""
        self.events.publish(
            sid, "session_pending", f"session {sid!r} waits for its source to answer "
            "(a ready message with this event's challenge)", pending.message.t_ns,
            challenge=pending.challenge,
        )

    def _on_ready(self, received: Received) -> None:
        """A source's answer to its session's challenge: the session starts (at once, or
        once its world's tables are built)."""
        message = protocol.decode(
            received.data, key_expr=received.key_expr, max_bytes=self.limits.max_message_bytes
        )
        sid, fields = message.session, message.fields
        running = self._sessions.get(sid)
        if running is not None and running.config_t_ns == fields["config_t_ns"]:
            return  # a re-send after the start
        confirm(self._pending.get(sid), message)
        self.housekeeping()  # starts it now if its world is ready

    def _world_ready(self, config: dict[str, Any]) -> bool:
        """Whether a config's world can start now: always, but for the puddle world while
        its tables are being built (see `cfbci.service.admission.PuddleTables`)."""
        return config.get("world") != "puddle" or self._puddle_tables.ready()

    def _start(self, message: protocol.Message, publisher: zenoh.Publisher) -> None:
        """Open the session and the recording of a config; publish the first move."""
        sid, config = message.session, resolved_config(message.fields)
        if len(self._sessions) >= self.limits.max_sessions:
            raise Rejection(f"the service runs its maximum of {self.limits.max_sessions} "
                            "sessions", sid, message.seq, message.t_ns)
        # Recorded with every learner setting it runs with (defaults included), prior read first.
        core, recorder = self.priors.open(message, config, self.recordings.open)
        session = RunningSession(sid, config, message.t_ns, core, recorder, self._outbox,
                                 self.events.publish, time.monotonic_ns())
        self._sessions[sid] = session
        self._ended_at_resume.pop(sid, None)  # the id is reused: its old end is over
        self.intake.open(sid)
        self.events.publish(
            sid, "session_started", f"session {sid!r}: {config['steps']} steps, "
            f"{session.world_text()}, {config['frame']} frame, {config['signal']}", message.t_ns,
        )
        session.start()

    def _on_epoch(self, received: Received, queued_ms: float) -> None:
        message = protocol.decode(
            received.data, key_expr=received.key_expr, max_bytes=self.limits.max_message_bytes
        )
        where = {"session": message.session, "seq": message.seq}
        session = self._sessions.get(message.session)
        identity = (message.fields["step"], message.seq, message.t_ns)
        ended = self._ended_at_resume.get(message.session)
        if session is None and ended is not None and ended.last_epoch == identity:
            end_again(ended, self._outbox, self.events.publish)
            return
        if session is None:
            problem = "before session_started" if message.session in self._pending else (
                "for an unknown session (no running session has this id)")
            raise ProtocolError(f"epoch {problem}", **where)
        if session.epoch(message, received.t_ns, queued_ms, self.limits):
            self._finish(session)

    def _finish(self, session: RunningSession) -> None:
        """The session's last epoch is in: ``session_ended``, and forget it."""
        self.events.publish(
            session.id, "session_ended", f"session {session.id!r} ended after {session.step} steps"
        )
        if self.on_end is not None:
            self.on_end(session.id, session.update_ns, session.queued_ms)
        self._end(session, session.step)

    def _abort(self, session: RunningSession, problem: str) -> None:
        """End a session before its last step, with a ``session_rejected`` event."""
        self._reject(Rejection(problem, session.id, None, session.config_t_ns))

    def _end(self, session: RunningSession, last_epoch_step: int) -> None:
        session.settle()
        del self._sessions[session.id]
        self.controls.forget(session.id)
        self.registration.release(session.id)
        self.intake.close(session.id)
        self.recordings.end(session.id, last_epoch_step)
        self._outbox.forget(session.id)

    def _reject(self, error: ProtocolError) -> None:
        """Report a rejected message where the protocol says (its session, else ``_``);
        a `Rejection` of a running session (the one its ``config_t_ns`` names) ends
        it. A session that neither runs nor waits for its source holds no claim (say its
        start failed): the claim is withdrawn before the rejection is published, so that a
        source told of it may pick another service at once."""
        session = error.session if error.session is not None else NO_SESSION
        running = self._sessions.get(session)
        if running is None and session not in self._pending:
            self.registration.release(session)
        ends = running is not None and running.config_t_ns == getattr(error, "config_t_ns", -1)
        if isinstance(error, Rejection) and (ends or self._errors.allows(session)):
            self.events.publish(session, "session_rejected", str(error), error.config_t_ns)
            if ends:
                assert running is not None
                self._end(running, running.step - 1)
        elif self._errors.allows(session):
            self.events.publish(session, "error", str(error))
        self._forget_idle(session)

    def _forget_idle(self, session: str) -> None:
        """Forget an idle id's publishers (and numbering, if it never ran a session here)."""
        if session not in self._sessions and session not in self._pending:
            never_ran = session != NO_SESSION and self.recordings.get(session) is None
            self._outbox.forget(session, numbering=never_ran)
