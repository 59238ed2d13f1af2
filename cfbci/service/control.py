"""The operator's commands on running sessions: pause, resume, end, and the target marked.

A ``control`` message (docs/protocol.md, "Operator controls") names a running session
and a command. `Controls` keeps which sessions are paused and answers each command with
an event, which the service publishes and records in the session's event log (``/event``
and ``/log``): ``session_paused``, ``session_resumed``, ``session_ended`` (the operator's
end) and ``target_marked``, each with the last move's ``step``. A paused session's
timeouts do not run (`Controls.overdue`), and an epoch that arrives while it is paused is
held, the latest one, and handed back at the resumption: the learner takes it then, as
if it had come then. The learner never reads a command: a recording with a pause replays
as one without.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from typing import Any

from cfbci.service.limits import ServiceLimits
from cfbci.service.running import RunningSession
from replay.recording import Recording
from wire import protocol
from wire.intake import session_of
from wire.protocol import ProtocolError
from wire.transport import Received

#: ``publish(session, event, text, extra=...)``: publish, record and log an event.
Publish = Callable[..., None]


class Controls:
    """The paused sessions and the epochs they hold; see the module docstring.

    Parameters
    ----------
    publish : callable
        `cfbci.service.events.Events.publish`.
    running : callable
        The running session of an id, or None.
    end : callable
        Ends a running session (its recording closed) once its ``session_ended`` is out.
    limits : ServiceLimits
        The timeouts, and the message size limit.
    """

    def __init__(
        self,
        publish: Publish,
        running: Callable[[str], RunningSession | None],
        end: Callable[[RunningSession], None],
        limits: ServiceLimits,
    ) -> None:
        self._publish, self._running, self._end, self._limits = publish, running, end, limits
        self._held: dict[str, Received | None] = {}  # paused session -> its held epoch

    def paused(self, session: str) -> bool:
        """Whether ``session`` is paused."""
        return session in self._held

    def hold(self, received: Received) -> bool:
        """Keep an epoch of a paused session (replacing the one held); False for any
        other message, which the service handles as usual."""
        session = session_of(received.key_expr)
        if received.tag != "epoch" or session not in self._held:
            return False
        self._held[session] = received
        return True

    def forget(self, session: str) -> None:
        """The session ended: it is no longer paused, its held epoch dropped."""
        self._held.pop(session, None)

    def restore(self, session: RunningSession, recording: Recording) -> None:
        """Pause a session resumed after a restart if its recording ends paused (its
        last ``session_paused`` not followed by a ``session_resumed``), and say so again
        (``session_paused``) to its source."""
        answers = [m["event"] for _, m in recording.messages.get("/event", [])
                   if m.get("event") in ("session_paused", "session_resumed")]
        if answers and answers[-1] == "session_paused":
            self._held[session.id] = None
            self._publish(session.id, "session_paused", "still paused by the operator after "
                          f"a restart, at step {session.step}", extra={"step": session.step})

    def overdue(
        self, sessions: Iterable[RunningSession], now_ns: int
    ) -> list[tuple[RunningSession, str]]:
        """The running sessions to end, and why: no first epoch within the start timeout,
        or none for the idle timeout, counted from the start, the last epoch or the last
        resumption; a paused session never is."""
        ended, limits = [], self._limits
        for session in sessions:
            quiet_ns = now_ns - session.active_ns
            if self.paused(session.id):
                continue
            if session.last_epoch is None and quiet_ns > limits.start_timeout * 1e9:
                ended.append((session, f"no epoch within {limits.start_timeout:g} s of the "
                              "start: session ended"))
            elif quiet_ns > limits.idle_timeout * 1e9:
                ended.append((session, f"no epoch for {limits.idle_timeout:g} s: session ended"))
        return ended

    def command(self, received: Received) -> list[Received]:
        """Carry out a ``control`` message; return the epoch a resumption hands back (the
        one held during the pause, if any: the service handles it next).

        Raises
        ------
        ProtocolError
            On a message that breaks the protocol, a session that is not running, a
            pause of a paused session or a resumption of a running one, and a target
            that is no task of the session's world.
        """
        message = protocol.decode(
            received.data, key_expr=received.key_expr, max_bytes=self._limits.max_message_bytes
        )
        sid, command = message.session, message.fields["command"]
        where = {"session": sid, "seq": message.seq}
        session = self._running(sid)
        if session is None:
            raise ProtocolError(f"control {command!r} for a session that is not running", **where)
        session.settle()  # the last move's state comes before the operator's action
        step = session.step
        if command == "pause":
            if self.paused(sid):
                raise ProtocolError("control 'pause': the session is paused already", **where)
            self._held[sid] = None
            self._publish(sid, "session_paused", f"paused by the operator at step {step}",
                          extra={"step": step})
        elif command == "resume":
            if not self.paused(sid):
                raise ProtocolError("control 'resume': the session is not paused", **where)
            held = self._held.pop(sid)
            session.active_ns = time.monotonic_ns()  # its idle timeout starts again
            self._publish(sid, "session_resumed", f"resumed by the operator at step {step}",
                          extra={"step": step})
            return [held] if held is not None else []
        elif command == "end":
            self.forget(sid)
            self._publish(sid, "session_ended", f"session {sid!r} ended by the operator at "
                          f"step {step} ({step - 1} epochs)", extra={"step": step})
            self._end(session)
        else:
            target = message.fields["target"]
            problem = target_problem(session, target)
            if problem is not None:
                raise ProtocolError(f"control 'target': {problem}", **where)
            self._publish(sid, "target_marked", f"the operator marked target {target} at "
                          f"step {step}", extra={"step": step, "target": target})
        return []


def target_problem(session: RunningSession, target: Any) -> str | None:
    """Why ``target`` is no task of the session's world (None: it is one): a task index
    below the number of tasks, or in the continuous world a point of the unit square."""
    if session.config["world"] == "continuous":
        if isinstance(target, list) and all(0 <= v <= 1 for v in target):
            return None
        return f"the continuous world's target is a point [x, y] of [0, 1]^2; got {target!r}"
    n_tasks = len(session.answer[2]) if session.answer is not None else 0
    if isinstance(target, int) and target < n_tasks:
        return None
    return f"target {target!r} is no task of the session's world (tasks 0 to {n_tasks - 1})"
