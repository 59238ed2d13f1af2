"""Zenoh plumbing shared by the service, the sources and the displays.

Publications are RELIABLE with congestion control BLOCK: a slow receiver slows the
sender down instead of losing messages. Subscriptions use a bounded FIFO channel that a
thread of ours (a `Pump`) empties into a Python queue; no Zenoh callback ever calls
back into Zenoh or into the application.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import zenoh

from wire import protocol

#: Capacity of a subscriber's FIFO channel, in messages.
CHANNEL_CAPACITY = 1024


@dataclass(frozen=True)
class Received:
    """One sample as taken off a subscriber's channel.

    Attributes
    ----------
    tag : str
        Which subscription it came from (the `Pump`'s tag).
    key_expr : str
        The key expression it was published on.
    data : bytes
        The payload.
    t_ns : int
        Receiver's ``time.monotonic_ns()`` when it was taken off the channel, ns.
    """

    tag: str
    key_expr: str
    data: bytes
    t_ns: int


def decode_from_service(
    received: Received, trackers: dict[str, protocol.SequenceTracker], log: logging.Logger
) -> protocol.Message | None:
    """Decode a message of the service and check its sequence number, as a client does.

    A message that does not decode is logged and dropped (None). A sequence problem is
    logged and the message kept: a gap at INFO (normal when a session id is reused, since
    the service numbers a key expression's messages for its whole life), anything else
    (duplicate, out of order) at WARNING. ``trackers``: one per kind received.
    """
    try:
        message = protocol.decode(received.data, key_expr=received.key_expr)
    except protocol.ProtocolError as error:
        log.warning("dropped a message of the service: %s", error)
        return None
    problem = trackers[message.kind].check(message.seq)
    if problem is not None:
        (log.info if problem.startswith("gap") else log.warning)("%s %s", message.kind, problem)
    return message


def reliable_publisher(session: zenoh.Session, key_expr: str) -> zenoh.Publisher:
    """A publisher with reliability RELIABLE and congestion control BLOCK (nothing dropped)."""
    return session.declare_publisher(
        key_expr,
        reliability=zenoh.Reliability.RELIABLE,
        congestion_control=zenoh.CongestionControl.BLOCK,
    )


def wait_for_subscribers(publisher: zenoh.Publisher, timeout: float) -> bool:
    """Wait until some subscriber matches ``publisher``; False after ``timeout`` seconds.

    The matching listener's callback only sets a `threading.Event`.
    """
    matched = threading.Event()
    listener = publisher.declare_matching_listener(
        lambda status: matched.set() if status.matching else None
    )
    try:
        return bool(publisher.matching_status.matching) or matched.wait(timeout)
    finally:
        listener.undeclare()


class Sink(Protocol):
    """Where a `Pump` puts what it receives (a ``queue.SimpleQueue``, an intake)."""

    def put(self, item: Received, /) -> Any: ...


class Pump:
    """A subscriber whose samples a thread of ours moves into a queue, as `Received`.

    Parameters
    ----------
    session : zenoh.Session
    key_expr : str
        What to subscribe to (wildcards allowed).
    tag : str
        Put in every `Received`, to tell subscriptions apart in a shared queue.
    queue : Sink
        Where samples go, in the order the subscriber received them.
    admit : callable, optional
        ``admit(n_bytes)``: whether to take a sample of that many payload bytes; a sample
        refused is dropped before its payload is copied.

    The thread ends when the subscriber is undeclared or the session closed
    (`close`).
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        tag: str,
        queue: Sink,
        admit: Callable[[int], bool] | None = None,
    ) -> None:
        self._subscriber = session.declare_subscriber(
            key_expr, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY)
        )
        self._handler = self._subscriber.handler
        self._tag, self._queue, self._admit = tag, queue, admit
        self._thread = threading.Thread(target=self._run, name=f"pump {key_expr}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                sample = self._handler.recv()
            except zenoh.ZError:  # the channel is closed: undeclared or session closed
                return
            if self._admit is not None and not self._admit(len(sample.payload)):
                continue
            self._queue.put(
                Received(
                    self._tag, str(sample.key_expr), sample.payload.to_bytes(), time.monotonic_ns()
                )
            )

    def close(self) -> None:
        """Undeclare the subscriber and wait for the thread to end."""
        self._subscriber.undeclare()
        self._thread.join()


class Outbox:
    """Publishes protocol messages, numbering them per key expression from 0.

    Publishers are declared on first use and kept until `forget` or `close`;
    sequence numbers are kept for the life of the outbox, so a key expression's ``seq``
    never restarts.
    """

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._seq: dict[str, int] = {}

    def publisher(self, key_expr: str) -> zenoh.Publisher:
        """The (reliable, blocking) publisher of ``key_expr``, declared if needed."""
        if key_expr not in self._publishers:
            self._publishers[key_expr] = reliable_publisher(self.session, key_expr)
        return self._publishers[key_expr]

    def send(
        self,
        kind: str,
        session: str,
        fields: dict[str, Any],
        payload: Any = None,
        before: Callable[[protocol.Message], None] | None = None,
    ) -> protocol.Message:
        """Encode and publish one message on ``cfbci/<session>/<kind>``; return it.

        Parameters
        ----------
        kind, session : str
            See `wire.protocol.key`.
        fields : dict
            The kind's header fields.
        payload : ndarray or None
            float32 payload (epoch ``(n_channels, n_times)`` or ``(n_features,)`` uV;
            state ``(n_tasks,)``).
        before : callable, optional
            Called with the message once it is encoded, before it is published (e.g. to
            record it first, so that whatever a receiver saw is on disk).

        Raises
        ------
        ProtocolError
            If the message breaks the protocol (nothing is published).
        """
        key_expr = protocol.key(session, kind)
        seq = self._seq.get(key_expr, 0)
        message = protocol.Message(kind, session, seq, time.monotonic_ns(), fields, payload)
        data = protocol.encode(message)
        if before is not None:
            before(message)
        self.publisher(key_expr).put(data)
        self._seq[key_expr] = seq + 1
        return message

    def repeat(self, message: protocol.Message) -> None:
        """Publish a message sent before once more, unchanged (same ``seq`` and ``t_ns``)."""
        self.publisher(protocol.key(message.session, message.kind)).put(protocol.encode(message))

    def forget(self, session: str, numbering: bool = False) -> None:
        """Undeclare the publishers of a session's key expressions; with ``numbering``,
        forget their sequence numbers too (they restart from 0: for ids that never ran,
        so that the outbox does not grow with every id a client makes up)."""
        prefix = f"{protocol.PREFIX}/{session}/"
        for key_expr in [k for k in self._publishers if k.startswith(prefix)]:
            self._publishers.pop(key_expr).undeclare()
        if numbering:
            for key_expr in [k for k in self._seq if k.startswith(prefix)]:
                del self._seq[key_expr]

    def close(self) -> None:
        """Undeclare every publisher."""
        for publisher in self._publishers.values():
            publisher.undeclare()
        self._publishers.clear()


class Resender:
    """A client's unanswered message, re-sent unchanged until its answer arrives.

    The service may drop a message (over a limit) or restart; a client therefore re-sends
    its config until the session starts, and an epoch (with the step's truth) until the
    next move arrives (docs/protocol.md, "Re-sending"). The service answers a re-sent
    message idempotently.

    Parameters
    ----------
    outbox : Outbox
    interval : float
        Seconds between two sendings of the same messages.
    """

    def __init__(self, outbox: Outbox, interval: float) -> None:
        self.outbox, self.interval = outbox, interval
        self.pending: protocol.Message | None = None
        self._group: list[protocol.Message] = []
        self._due_ns = 0

    def send(
        self,
        kind: str,
        session: str,
        fields: dict[str, Any],
        payload: Any = None,
        companion: bool = False,
    ) -> protocol.Message:
        """Send a message (see `Outbox.send`) and await its answer; a ``companion``
        is re-sent with the pending message and needs no answer of its own."""
        message = self.outbox.send(kind, session, fields, payload)
        if companion:
            self._group.append(message)
        else:
            self.pending, self._group = message, [message]
            self._due_ns = time.monotonic_ns() + int(self.interval * 1e9)
        return message

    def also(self, message: protocol.Message) -> None:
        """Re-send ``message``, sent before, with the pending one until it is answered."""
        self._group.append(message)

    def answered(self) -> None:
        """The pending message is answered: stop re-sending it and its companions."""
        self.pending, self._group = None, []

    def wait(self, longest: float) -> float:
        """Seconds to wait for a message before `poll` is due (at most ``longest``)."""
        if self.pending is None:
            return longest
        return min(longest, max(0.0, (self._due_ns - time.monotonic_ns()) / 1e9))

    def poll(self) -> None:
        """Re-send the pending message and its companions if they are due."""
        if self.pending is not None and time.monotonic_ns() >= self._due_ns:
            for message in self._group:
                self.outbox.repeat(message)
            self._due_ns = time.monotonic_ns() + int(self.interval * 1e9)
