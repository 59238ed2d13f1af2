"""The LSL bridge's input: its inlets, resolved again when lost, read in a thread of their
own (``acquisition.lsl_bridge``).

`StreamReader` polls the EEG inlet (waiting up to `POLL_SECONDS` for a sample), then
the marker inlet, queues what came with when it came and wakes the bridge's loop
(`wire.client.Client.wake`). The loop thus waits for the service and the streams at
once: a move of the service is forwarded to the stimulus program as soon as it comes, not
after the EEG's poll has waited its time out.
"""

from __future__ import annotations

import logging
import queue
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import pylsl
from pylsl.util import LostError

from acquisition.lsl_streams import resolve_inlet

log = logging.getLogger("cfbci.lsl_bridge")

#: Seconds one poll of the EEG inlet may wait for a sample.
POLL_SECONDS = 0.005


def on_this_host(inlet: pylsl.StreamInlet) -> bool:
    """Whether the inlet's stream comes from a program on this machine (its host name):
    then it shares this machine's clock and its timestamps need no correction."""
    return bool(inlet.info().hostname() == socket.gethostname())


class StreamInput:
    """An LSL inlet resolved by name, resolved again when its stream is lost.

    Parameters
    ----------
    name : str
        The stream's name.
    timeout : float
        Seconds to find the stream, at first and after a loss (`TimeoutError`).
    reconnects : list of str
        Where its name is appended at every reconnection.
    keep_running : callable
        Resolving stops when it returns False.
    """

    def __init__(self, name: str, timeout: float, reconnects: list[str],
                 keep_running: Callable[[], bool]) -> None:
        self.name, self.timeout, self.reconnects = name, timeout, reconnects
        self.keep_running = keep_running
        self.inlet = resolve_inlet(name, timeout, keep_running=keep_running)
        self.offset = 0.0
        self.local = on_this_host(self.inlet)

    def pull(self, timeout: float, as_numpy: bool) -> tuple[Any, Any]:
        """(samples, timestamps) available now or within ``timeout``; ([], []) after a
        reconnection."""
        try:
            return self.inlet.pull_chunk(timeout=timeout, max_samples=1024, min_samples=1,
                                         as_numpy=as_numpy)
        except LostError:
            log.warning("LSL stream %r lost; resolving it again", self.name)
            self.inlet = resolve_inlet(self.name, self.timeout, keep_running=self.keep_running)
            self.local = on_this_host(self.inlet)
            self.reconnects.append(self.name)
            log.warning("LSL stream %r reconnected", self.name)
            return [], []

    def clock_offset(self) -> float:
        """Seconds to add to the stream's timestamps to get this machine's LSL clock: 0 for
        a stream of this machine (the same clock; a measured offset would only add its
        noise of some microseconds)."""
        if self.local:
            return 0.0
        try:
            self.offset = self.inlet.time_correction(timeout=2.0)
        except (pylsl.util.TimeoutError, LostError) as error:
            log.warning("no time correction for %r (%s); using the last one", self.name, error)
        return self.offset


#: One poll of `StreamReader`: EEG samples (n_samples, n_channels), their timestamps (s),
#: when they were taken (ns of the monotonic clock), marker values, their timestamps (s),
#: when they were taken (s of this machine's LSL clock).
Poll = tuple[Any, Any, int, Any, Any, float]


class StreamReader(threading.Thread):
    """Polls the EEG and the markers in a thread of its own until ``stop`` is set: every
    poll that brought something is queued on `taken` and ``wake`` called; a stream lost
    and not found again is kept in `error` (and ``wake`` called)."""

    def __init__(self, eeg: StreamInput, markers: StreamInput, wake: Callable[[], None],
                 stop: threading.Event) -> None:
        super().__init__(name="lsl-bridge-streams", daemon=True)
        self.eeg, self.markers, self.wake, self.stop = eeg, markers, wake, stop
        self.taken: queue.SimpleQueue[Poll] = queue.SimpleQueue()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            while not self.stop.is_set():
                samples, times = self.eeg.pull(POLL_SECONDS, as_numpy=True)
                eeg_ns = time.monotonic_ns()
                values, stamps = self.markers.pull(0.0, as_numpy=False)
                if len(times) or len(stamps):
                    self.taken.put((samples, times, eeg_ns, values, stamps, pylsl.local_clock()))
                    self.wake()
        except BaseException as error:  # the bridge's loop raises it
            self.error = error
            self.wake()
