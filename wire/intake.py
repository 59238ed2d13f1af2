"""The service's intake: a bounded, fair queue of received messages.

Every received message is filed under the session id of its key expression
(``cfbci/<session>/<kind>``). A session the service runs has a FIFO of its own
(`Intake.open`); every other message (configs of new sessions, messages for unknown
sessions, undecodable key expressions) shares one FIFO, ``other``. `Intake.get`
serves the non-empty FIFOs round-robin, one message at a time, so a flood on some keys
delays another session's next message by at most one message per FIFO.

Nothing grows without bound: a message longer than ``max_bytes`` is dropped before it is
copied out of Zenoh, a session id that has sent ``rate`` messages in the current second
gets its further messages of that second dropped, and a FIFO that holds
`QUEUE_MESSAGES` messages or `QUEUE_BYTES` bytes drops what comes next.
Dropped messages are counted per reason (`Intake.take_drops`). Pump threads call
`Intake.put`; one thread (the service's loop) calls `Intake.get`.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field

from wire.transport import Received

#: Most messages one FIFO holds.
QUEUE_MESSAGES = 256
#: Most payload bytes one FIFO holds.
QUEUE_BYTES = 16 * 2**20
#: FIFO of every message not filed under a running session.
OTHER = "/other"  # not a valid session id, so never a session's FIFO


def session_of(key_expr: str) -> str | None:
    """The session of ``cfbci/<session>/<kind>`` (its one or two middle segments,
    unchecked), or None."""
    parts = key_expr.split("/")
    return "/".join(parts[1:-1]) if len(parts) in (3, 4) else None


@dataclass
class _Fifo:
    messages: deque[Received] = field(default_factory=deque)
    bytes: int = 0


class Intake:
    """Bounded, fair queue of received messages; see the module docstring.

    Parameters
    ----------
    rate : int
        Most messages accepted per session id per second (a fixed one-second window).
    max_bytes : int
        Longest message accepted, bytes.
    """

    def __init__(self, rate: int, max_bytes: int) -> None:
        self.rate, self.max_bytes = rate, max_bytes
        self._fifos: dict[str, _Fifo] = {OTHER: _Fifo()}
        self._ready: deque[str] = deque()  # FIFOs holding messages, in serving order
        self._window = 0  # the current second of time.monotonic()
        self._counts: Counter[str] = Counter()  # messages per session id in the window
        self._drops: Counter[str] = Counter()
        self._stopped = False
        self._changed = threading.Condition()

    def accepts_size(self, size: int) -> bool:
        """Whether a message of ``size`` bytes may be copied in (else it is counted)."""
        if size <= self.max_bytes:
            return True
        with self._changed:
            self._drops["over the size limit"] += 1
        return False

    def put(self, received: Received) -> None:
        """File a message (pump threads); drop it if over a limit."""
        session = session_of(received.key_expr)
        with self._changed:
            window = int(time.monotonic())
            if window != self._window:
                self._window = window
                self._counts.clear()
            self._counts[session or OTHER] += 1
            if self._counts[session or OTHER] > self.rate:
                self._drops["over the rate limit"] += 1
                return
            name = session if session in self._fifos else OTHER
            fifo = self._fifos[name]
            size = len(received.data)
            if len(fifo.messages) >= QUEUE_MESSAGES or fifo.bytes + size > QUEUE_BYTES:
                self._drops["queue full"] += 1
                return
            fifo.messages.append(received)
            fifo.bytes += len(received.data)
            if len(fifo.messages) == 1:
                self._ready.append(name)
            self._changed.notify()

    def get(self, timeout: float) -> Received | None:
        """The next message round-robin; None after ``timeout`` seconds or once stopped."""
        with self._changed:
            if not self._changed.wait_for(lambda: self._ready or self._stopped, timeout):
                return None
            if self._stopped:
                return None
            name = self._ready.popleft()
            fifo = self._fifos[name]
            received = fifo.messages.popleft()
            fifo.bytes -= len(received.data)
            if fifo.messages:
                self._ready.append(name)
            return received

    def open(self, session: str) -> None:
        """Give a session a FIFO of its own, from now on."""
        with self._changed:
            self._fifos.setdefault(session, _Fifo())

    def close(self, session: str) -> None:
        """File a session's messages with the others again (its pending ones first)."""
        with self._changed:
            fifo = self._fifos.pop(session, None)
            if fifo is None:
                return
            if session in self._ready:
                self._ready.remove(session)
            other = self._fifos[OTHER]
            other.messages.extendleft(reversed(fifo.messages))
            other.bytes += fifo.bytes
            if other.messages and OTHER not in self._ready:
                self._ready.append(OTHER)

    def stop(self) -> None:
        """Make every `get` return None (safe from a signal handler's thread)."""
        with self._changed:
            self._stopped = True
            self._changed.notify_all()

    def drain(self) -> list[Received]:
        """Every message still queued, removed from the queues (for a clean shutdown)."""
        with self._changed:
            left = [m for fifo in self._fifos.values() for m in fifo.messages]
            for fifo in self._fifos.values():
                fifo.messages.clear()
                fifo.bytes = 0
            self._ready.clear()
            return left

    def take_drops(self) -> Counter[str]:
        """Messages dropped per reason since the last call."""
        with self._changed:
            drops, self._drops = self._drops, Counter()
            return drops
