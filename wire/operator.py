"""The operator's side of the ``control`` messages (docs/protocol.md, "Operator controls").

`send_command` publishes one command on ``cfbci/<session>/control`` and waits for the
service's answer on the session's events: the event the command gives (`ANSWERS`), or an
``error`` naming the command. ``cfbci control`` and the browser view's operator page
(through its server) both send commands with `control_fields`.
"""

from __future__ import annotations

import queue
import time
from typing import Any

import zenoh

from wire import protocol
from wire.transport import Outbox, Pump, Received, wait_for_subscribers

#: The event that answers each command.
ANSWERS: dict[str, str] = {
    "pause": "session_paused", "resume": "session_resumed", "end": "session_ended",
    "target": "target_marked",
}


def control_fields(command: str, target: Any = None) -> dict[str, Any]:
    """The ``control`` message's fields of a command (``target`` only for ``"target"``).

    Raises
    ------
    ValueError
        On an unknown command, a target without the ``target`` command or the reverse.
    """
    if command not in protocol.COMMANDS:
        raise ValueError(f"unknown command {command!r}; the commands are "
                         f"{', '.join(protocol.COMMANDS)}")
    if (command == "target") != (target is not None):
        raise ValueError("a target goes with the command 'target', and only with it")
    return {"command": command, **({"target": target} if target is not None else {})}


def send_command(
    session: zenoh.Session, sid: str, command: str, target: Any = None, timeout: float = 10.0
) -> dict[str, Any]:
    """Send one command to the service running ``sid`` and return its answer's fields.

    Parameters
    ----------
    session : zenoh.Session
    sid : str
        The session id.
    command : str
        One of `wire.protocol.COMMANDS`.
    target : int, list of float or None
        The target of the command ``"target"``: a task index (the continuous world's: a
        point ``[x, y]``).
    timeout : float
        Seconds to wait for a service to subscribe to the commands, then for its answer.

    Returns
    -------
    dict
        The answering ``event``'s fields (``event``, ``message``, ``step``, ...).

    Raises
    ------
    ValueError
        On a bad command or session id; an ``error`` event answering it (its message).
    TimeoutError
        If no service subscribes, or none answers within ``timeout``.
    """
    fields = control_fields(command, target)
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    pump = Pump(session, protocol.key(sid, "event"), "event", inbox)
    outbox = Outbox(session)
    try:
        key_expr = protocol.key(sid, "control")
        if not wait_for_subscribers(outbox.publisher(key_expr), timeout):
            raise TimeoutError(f"no service subscribed to {key_expr} within {timeout:g} s")
        sent = outbox.send("control", sid, fields)
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                received = inbox.get(timeout=left)
            except queue.Empty:
                break
            event = protocol.decode(received.data, key_expr=received.key_expr).fields
            if event["event"] == ANSWERS[command]:
                return event
            if event["event"] == "error" and f"seq {sent.seq}: control" in event["message"]:
                raise ValueError(f"the service refused {command!r}: {event['message']}")
        raise TimeoutError(f"session {sid!r}: no answer to {command!r} within {timeout:g} s")
    finally:
        pump.close()
        outbox.close()
