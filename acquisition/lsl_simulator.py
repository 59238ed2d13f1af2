"""The LSL simulator: an amplifier, a stimulus program and a user, for tests and demos.

``cfbci lsl-simulator`` plays the lab's side of ``cfbci lsl-bridge``:

* an **EEG outlet** streaming continuous synthetic EEG in real time (float32 µV, one
  timestamp per sample: ``t0 + n / sfreq`` on this machine's LSL clock, as an amplifier
  driver stamps samples from its sample clock), at the rate of the user's epochs (256 Hz
  for the synthetic generator);
* a **stimulus loop**: it takes each move from the bridge's move stream, waits the onset
  delay, sends the onset marker ``"onset <step>"`` (stamped with the onset sample's time)
  on its **marker outlet**, and writes the simulated user's epoch for that move into the
  continuous signal at that time: the epoch's samples *replace* the background from
  ``onset + tmin`` to ``onset + tmax``, so the bridge's epoch can be compared sample for
  sample with what was written (``acquisition.lsl_written.check_recording``);
* the **truth** of every step (the user's target and the epoch's label) on Zenoh, as the
  replay source publishes it, so that the service's recording has ``/truth``.

**Listening** (``onsets``: a stimulus program's marker stream, e.g. ``cfbci view
--stimulus``'s): no onsets of its own; the moves come from the service (Zenoh), the onsets
from the ``onset <step>`` markers, each epoch written around the sample the bridge cuts it
around (``acquisition.lsl_epochs.nearest_sample`` on the same float64 sample stamps; a
marker stream of this machine taken as it is, another's mapped with ``time_correction()``,
as the bridge does). A marker arrives after its timestamp and the epoch starts ``|tmin|``
before it, so a sample stamped ``t`` is pushed at ``t + |tmin| + marker_latency``; a marker
later than ``marker_latency`` finds the epoch's first samples sent: it is reported
(``Simulation.late``) and nothing is written. The simulator opens its EEG outlet only once
it listens to the onset markers (the bridge starts a session only once it has found the EEG
stream: no onset can come before), and stamps sample 0 ``|tmin|`` before, as from an
amplifier already running: an onset shown as soon as the bridge has found the stream has
its whole window.

The user is `acquisition.user.SimulatedUser` with the random streams of
`calibration_free.streams.session_streams`, and synthetic epochs come from the data
stream as in `acquisition.simulated_source`: with the bridge's ``--seed`` equal to the
simulator's, a session over LSL makes the decisions of ``cfbci session`` with that seed.
A move sent again (``repeat`` > 0, the bridge could not cut its epoch) is answered with
the same epoch, and its truth is not sent again.

Between epochs the signal is a simple continuous background (`Background`).
With ``photodiode`` (s), a display's delay: every epoch's onset sample is that delay after
its marker's, and a photodiode channel (``acquisition.photodiode``) pulses from it.
For tests, `Drop` leaves samples of an epoch out of the stream (a gap in the
timestamps) and ``restart_after`` closes the EEG outlet for ``outage`` seconds and opens
it again (the stream vanishes and comes back with a new uid).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pylsl
import scipy.signal
import zenoh
from pylsl.util import LostError

from acquisition.labelled import LabelledEpochs
from acquisition.loaders import load_epochs
from acquisition.lsl_bridge import DEFAULT_MOVES
from acquisition.lsl_epochs import nearest_sample
from acquisition.lsl_input import on_this_host
from acquisition.lsl_streams import (
    eeg_outlet,
    let_consumers_leave,
    marker_outlet,
    parse_move_marker,
    parse_onset_marker,
    resolve_inlet,
)
from acquisition.lsl_written import check_recording as check_recording  # for older imports
from acquisition.photodiode import PHOTODIODE_CHANNEL, PULSE_SECONDS, pulse_column
from acquisition.sources import DataSpec, synthetic_epochs
from acquisition.user import SimulatedUser
from calibration_free.streams import session_streams
from calibration_free.world import ACTIONS, GridWorld
from wire import protocol
from wire.transport import Outbox, Pump, Received, wait_for_subscribers
from wire.zenoh_config import peer_config

log = logging.getLogger("cfbci.lsl_simulator")

DEFAULT_EEG = "cfbci-sim-eeg"
DEFAULT_MARKERS = "cfbci-sim-markers"
#: Samples pushed per chunk (8 at 256 Hz: a chunk every 31 ms).
CHUNK = 8


@dataclass(frozen=True)
class Drop:
    """Samples of an epoch the simulator leaves out of the stream (a test of gaps).

    Attributes
    ----------
    step : int
        The step whose first epoch loses samples.
    offset : int
        First lost sample, in samples after the onset.
    count : int
        Samples lost.
    """

    step: int
    offset: int
    count: int


@dataclass(frozen=True)
class SimulatorSettings:
    """One simulated session on LSL.

    Attributes
    ----------
    session : str
        Session id of the truth messages (the bridge's ``--session``).
    data : DataSpec
        Synthetic epochs, or a dataset of raw epochs (an epochs ``.npz``, a recording of
        raw epochs).
    seed, grid, frame, user_error_rate
        As for the replay source; ``seed`` and ``grid`` must be the bridge's.
    eeg, markers, moves : str
        Names of the EEG and marker outlets, and of the bridge's move stream.
    onset_delay : float
        Seconds from a move's arrival to its onset; at least the epoch's pre-onset span.
    drops : tuple of Drop
    late_markers : tuple of (int, float)
        ``(step, seconds)``: the onset marker of that step's first epoch is sent this many
        seconds after its onset (still stamped with the onset's time).
    restart_after : int or None
        After the epoch of this step has been streamed, close the EEG outlet for
        ``outage`` seconds, then open a new one.
    outage : float
        Seconds the EEG outlet stays closed.
    timeout : float
        Seconds to wait for the bridge's move stream.
    onsets : str or None
        Listen to this marker stream's onsets instead of making them (see the module).
    marker_latency : float
        Listening: how late an onset marker may arrive, s (the EEG's lag beyond |tmin|).
    photodiode : float or None
        A display's delay, s: a photodiode channel pulses that long after each marker.
    """

    session: str
    data: DataSpec = field(default_factory=DataSpec)
    seed: int = 0
    grid: int = 5
    frame: str = "feedback"
    user_error_rate: float = 0.0
    eeg: str = DEFAULT_EEG
    markers: str = DEFAULT_MARKERS
    moves: str = DEFAULT_MOVES
    onset_delay: float = 1.0
    drops: tuple[Drop, ...] = ()
    late_markers: tuple[tuple[int, float], ...] = ()
    restart_after: int | None = None
    outage: float = 1.0
    timeout: float = 30.0
    onsets: str | None = None
    marker_latency: float = 0.3
    photodiode: float | None = None


@dataclass
class Written:
    """One epoch written into the stream.

    Attributes
    ----------
    step, repeat : int
        The move it answers and how often that move had been sent again.
    onset : int
        Index of the onset sample (samples counted from the stream's start).
    start : int
        Index of the epoch's first sample.
    epoch : ndarray, shape (n_channels, n_times), float32
        The samples written, µV.
    marked : int
        Index of the sample after which its onset marker is sent (the onset, or later).
    dropped : list of (int, int)
        ``(first index, count)`` of the samples of this epoch left out of the stream.
    """

    step: int
    repeat: int
    onset: int
    start: int
    epoch: np.ndarray
    marked: int
    dropped: list[tuple[int, int]] = field(default_factory=list)

    @property
    def stop(self) -> int:
        return self.start + self.epoch.shape[1]


class Background:
    """Continuous background EEG between the epochs, about 10 µV RMS per channel.

    Low-pass noise (a first-order recursive filter with a 2 Hz corner on white noise),
    60 % of its variance shared by all channels, plus a 10 Hz rhythm of 5 µV amplitude;
    filter states and phase carry over from one call to the next.
    """

    def __init__(self, n_channels: int, sfreq: float, rng: np.random.Generator) -> None:
        self.n_channels, self.sfreq, self.rng = n_channels, sfreq, rng
        self.pole = np.exp(-2 * np.pi * 2.0 / sfreq)
        self.state = np.zeros((1, n_channels + 1))
        self.phase = rng.uniform(0, 2 * np.pi)

    def next(self, n: int) -> np.ndarray:
        """The next ``n`` samples, shape (n, n_channels), float32 µV."""
        white = self.rng.standard_normal((n, self.n_channels + 1)) * 10 * np.sqrt(
            1 - self.pole**2
        )
        noise, self.state = scipy.signal.lfilter([1.0], [1.0, -self.pole], white, axis=0,
                                                 zi=self.state)
        mixed = np.sqrt(0.6) * noise[:, :1] + np.sqrt(0.4) * noise[:, 1:]
        phases = self.phase + 2 * np.pi * 10.0 * np.arange(n) / self.sfreq
        self.phase = (phases[-1] + 2 * np.pi * 10.0 / self.sfreq) % (2 * np.pi)
        return (mixed + 5.0 * np.sin(phases)[:, None]).astype(np.float32)


def raw_epochs(data: DataSpec, frame: str, rng: np.random.Generator) -> LabelledEpochs:
    """The user's epochs as float32 µV: synthetic (from ``rng``, the session's data
    stream) or a dataset of raw epochs.

    Raises
    ------
    ValueError
        If the dataset holds feature vectors (nothing to write into an EEG stream).
    """
    if data.path is None:
        data.resolve(frame)  # rejects synthetic guidance data
        return synthetic_epochs(data.synthetic_accuracy, rng)
    epochs = load_epochs(data.path, frame=frame)
    return LabelledEpochs(
        np.asarray(epochs.epochs, dtype=np.float32), epochs.sfreq, epochs.tmin,
        epochs.ch_names, epochs.labels, epochs.n_classes, epochs.source,
    )


@dataclass(frozen=True)
class Simulation:
    """What the simulator streamed.

    Attributes
    ----------
    written : list of Written
        The epochs written into the stream, in order.
    t0 : float
        Timestamp of sample 0, s (sample n is stamped ``t0 + n / sfreq``).
    targets : list of (int, bool)
        Every declared target: its step and whether it was the user's target.
    late : list of (int, float)
        Listening: step and lateness (s) of the onsets that came too late to be written.
    """

    written: list[Written]
    t0: float
    targets: list[tuple[int, bool]]
    late: list[tuple[int, float]] = field(default_factory=list)


def run_simulator(
    settings: SimulatorSettings, listen: Sequence[str] = (), connect: Sequence[str] = (),
    keep_running: Callable[[], bool] = lambda: True, zenoh_config: Path | None = None,
) -> Simulation:
    """Open a Zenoh session for the truth (`wire.zenoh_config.peer_config`: a peer, or
    what ``zenoh_config`` says) and simulate until the bridge's move stream ends or
    ``keep_running()`` turns False."""
    with zenoh.open(peer_config(listen, connect, zenoh_config)) as session:
        return _Simulator(session, settings).run(keep_running)


class _Simulator:
    def __init__(self, session: zenoh.Session, settings: SimulatorSettings) -> None:
        self.settings = settings
        data_rng, user_rng, _ = session_streams(settings.seed)
        self.signals = raw_epochs(settings.data, settings.frame, data_rng)
        self.sfreq = self.signals.sfreq
        self.first = round(self.signals.tmin * self.sfreq)
        self.delay = round(settings.onset_delay * self.sfreq)
        self.display = round((settings.photodiode or 0.0) * self.sfreq)  # samples
        if self.delay + self.first < CHUNK:
            raise ValueError(
                f"--onset-delay {settings.onset_delay:g} s is too short: the epoch starts "
                f"{-self.signals.tmin:g} s before its onset, which must still be ahead"
            )
        self.world = GridWorld(settings.grid)
        self.user = SimulatedUser(self.world, settings.frame, self.signals.labels, user_rng,
                                  settings.user_error_rate)
        background_seed = np.random.SeedSequence(settings.seed).spawn(4)[3]
        self.background = Background(len(self.signals.ch_names), self.sfreq,
                                     np.random.default_rng(background_seed))
        self.outbox = Outbox(session)
        self.truth_key = protocol.key(settings.session, "truth")
        self.answers: dict[int, int] = {}  # step -> index of its epoch in the dataset
        self.written: list[Written] = []
        self.targets: list[tuple[int, bool]] = []  # declared targets: (step, correct)
        self.pending: list[Written] = []  # written, not all streamed yet
        self.marks: list[Written] = []  # onset marker not sent yet
        self.next = 0  # index of the next sample to stream
        self.outage_until: int | None = None  # sample at which the EEG outlet reopens
        self.restart_after = settings.restart_after
        self.lag = 0.0  # s the EEG runs behind real time
        self.late: list[tuple[int, float]] = []
        self.session = session

    def _open_eeg(self) -> pylsl.StreamOutlet:
        pd = [PHOTODIODE_CHANNEL] if self.settings.photodiode is not None else []
        return eeg_outlet(self.settings.eeg, [*self.signals.ch_names, *pd], self.sfreq,
                          f"cfbci-sim-{self.settings.session}-eeg")

    def run(self, keep_running: Callable[[], bool]) -> Simulation:
        if self.settings.onsets is not None:
            return _Listener(self).listen(keep_running)
        settings = self.settings
        self.eeg: pylsl.StreamOutlet | None = self._open_eeg()
        self.markers = marker_outlet(settings.markers, f"cfbci-sim-{settings.session}-markers")
        moves = resolve_inlet(settings.moves, settings.timeout, keep_running=keep_running)
        events: queue.SimpleQueue[Received] = queue.SimpleQueue()
        pump = Pump(self.session, protocol.key(settings.session, "event"), "event", events)
        self._wait_for_truth_subscriber()
        self.t0 = pylsl.local_clock()  # sample 0: the onsets are ours, all ahead of it
        try:
            while keep_running() and not _ended(events):
                try:
                    values, _ = moves.pull_chunk(timeout=0.0, as_numpy=False)
                except LostError:
                    log.info("the bridge's move stream ended")
                    break
                for value in values:
                    self._on_move(parse_move_marker(value[0]))
                self._stream()
                self._wait_for_chunk()
        finally:
            moves.close_stream()  # before the bridge's outlet closes: no broken stream
            let_consumers_leave(*(o for o in (self.eeg, self.markers) if o is not None))
            pump.close()
            self.outbox.close()
        return Simulation(self.written, self.t0, self.targets)

    def _wait_for_truth_subscriber(self) -> None:
        if not wait_for_subscribers(self.outbox.publisher(self.truth_key), self.settings.timeout):
            log.warning("nobody subscribed to %s: the truth will not be recorded",
                        self.truth_key)

    def _wait_for_chunk(self) -> None:
        wake = self.t0 + self.lag + (self.next + CHUNK - 1) / self.sfreq  # the next chunk
        time.sleep(max(0.0, wake - pylsl.local_clock()))

    def _answer(self, move: dict[str, Any]) -> None:
        """The user's answer to a move, once per step (its truth sent)."""
        step = move["step"]
        if step not in self.answers:
            index, label = self.user.answer(move["from_state"], ACTIONS.index(move["action"]))
            self.answers[step] = index
            target = self.user.target
            self.outbox.send("truth", self.settings.session,
                             {"step": step, "target": target, "label": label})
            if move["target_reached"]:
                self.targets.append((step, move["from_state"] == target))
                self.user.new_target()

    def _on_move(self, move: dict[str, Any]) -> None:
        self._answer(move)
        step = move["step"]
        # the marker's sample: the display's delay before it, counted from now even when
        # the streaming lags (a stalled process): an onset never precedes its move
        onset = max(self.next, self._due()) + self.delay + self.display
        epoch = self.signals.epochs[self.answers[step]]
        first_time = move["repeat"] == 0
        late = sum(s for k, s in self.settings.late_markers if k == step and first_time)
        written = Written(step, move["repeat"], onset, onset + self.first, epoch,
                          onset - self.display + round(late * self.sfreq))
        for drop in self.settings.drops:
            if drop.step == step and first_time:
                written.dropped.append((onset + drop.offset, drop.count))
        self.written.append(written)
        self.pending.append(written)
        self.marks.append(written)

    def _due(self) -> int:
        """The first sample not due yet (the samples before it are due by now)."""
        return int((pylsl.local_clock() - self.lag - self.t0) * self.sfreq) + 1

    def _stream(self) -> None:
        """Stream the samples that are due; send the onset markers among them."""
        due = self._due()
        if due <= self.next:
            return
        indices = np.arange(self.next, due)
        block = self.background.next(len(indices))
        keep = np.ones(len(indices), dtype=bool)
        for written in self.pending:
            inside = (indices >= written.start) & (indices < written.stop)
            block[inside] = written.epoch[:, indices[inside] - written.start].T
            for first, count in written.dropped:
                keep &= (indices < first) | (indices >= first + count)
        if self.settings.photodiode is not None:
            block = np.hstack([block, pulse_column(indices, [w.onset for w in self.pending],
                                                   round(PULSE_SECONDS * self.sfreq))])
        self._push(block[keep], indices[keep])
        for written in [w for w in self.marks if w.marked < due]:
            self.markers.push_sample([f"onset {written.step}"],
                                     self.t0 + (written.onset - self.display) / self.sfreq)
            self.marks.remove(written)
        finished = [w for w in self.pending if w.stop <= due]
        self.pending = [w for w in self.pending if w.stop > due]
        self.next = due
        if any(w.step == self.restart_after for w in finished):
            log.info("closing the EEG outlet for %.1f s", self.settings.outage)
            # pylsl destroys the outlet with its last reference; liblsl's teardown can block
            # while an inlet is connected, so it happens on a thread of its own.
            closing, self.eeg = self.eeg, None
            threading.Thread(target=_drop, args=(closing,), daemon=True).start()
            del closing
            self.outage_until = due + round(self.settings.outage * self.sfreq)
            self.restart_after = None  # once

    def _push(self, block: np.ndarray, indices: np.ndarray) -> None:
        if self.outage_until is not None and self.next >= self.outage_until:
            self.eeg, self.outage_until = self._open_eeg(), None
            log.info("EEG outlet open again")
        if self.eeg is not None and len(indices):
            self.eeg.push_chunk(block, list(self.t0 + indices / self.sfreq))


def _decoded(inbox: queue.SimpleQueue[Received]) -> list[protocol.Message]:
    """The messages that came (bad bytes dropped with a line)."""
    messages = []
    while not inbox.empty():
        received = inbox.get()
        try:
            messages.append(protocol.decode(received.data, key_expr=received.key_expr))
        except protocol.ProtocolError as error:
            log.warning("dropped a message: %s", error)
    return messages


def _ended(events: queue.SimpleQueue[Received]) -> bool:
    """Whether a ``session_ended`` event came (other events are skipped)."""
    return any(m.fields["event"] == "session_ended" for m in _decoded(events))


class _Listener:
    """A simulator's listening mode (see the module): moves from Zenoh, onsets from the
    stimulus program's markers, the EEG ``|tmin| + marker_latency`` behind real time."""

    def __init__(self, simulator: _Simulator) -> None:
        self.sim = simulator
        settings = simulator.settings
        self.inboxes: dict[str, queue.SimpleQueue[Received]] = {"move": queue.SimpleQueue(),
                                                                 "event": queue.SimpleQueue()}
        self.pumps = [Pump(simulator.session, protocol.key(settings.session, kind), kind, inbox)
                      for kind, inbox in self.inboxes.items()]
        self.onsets: list[tuple[int, float]] = []  # (step, marker time) not written yet
        simulator.lag = -simulator.signals.tmin + settings.marker_latency

    def listen(self, keep_running: Callable[[], bool]) -> Simulation:
        sim, settings = self.sim, self.sim.settings
        # Listening before the EEG stream exists: the bridge starts the session only once
        # it has found that stream, so no onset is shown before (an inlet gets only what
        # is pushed after it connected).
        markers = resolve_inlet(str(settings.onsets), settings.timeout, keep_running=keep_running)
        offset = 0.0 if on_this_host(markers) else markers.time_correction(timeout=5.0)
        sim._wait_for_truth_subscriber()
        # An amplifier already running: an onset shown as soon as the bridge has found the
        # stream has its window's |tmin| before it (the clock read before the stream exists).
        sim.t0 = pylsl.local_clock() + sim.signals.tmin
        sim.eeg = sim._open_eeg()
        try:
            while keep_running() and not _ended(self.inboxes["event"]):
                for move in _decoded(self.inboxes["move"]):
                    sim._answer(move.fields)
                try:
                    values, stamps = markers.pull_chunk(timeout=0.0, as_numpy=False)
                except LostError:
                    log.info("the stimulus program's onset stream ended")
                    break
                for value, stamp in zip(values, stamps, strict=True):
                    is_onset, step = parse_onset_marker(value[0], "onset")
                    if is_onset and step is not None:
                        self.onsets.append((step, stamp + offset))
                self._write()
                sim._stream()
                sim._wait_for_chunk()
        finally:
            markers.close_stream()  # before the stimulus program's outlet closes
            let_consumers_leave(sim.eeg)
            for pump in self.pumps:
                pump.close()
            sim.outbox.close()
        return Simulation(sim.written, sim.t0, sim.targets, sim.late)

    def _write(self) -> None:
        """Write the epochs of the onsets whose moves are known, or report them late."""
        sim, waiting = self.sim, []
        for step, when in self.onsets:
            if step not in sim.answers:  # its move has not come yet
                waiting.append((step, when))
                continue
            first = int((when - sim.t0) * sim.sfreq) - 1
            stamps = sim.t0 + np.arange(first, first + 3) / sim.sfreq  # as pushed
            onset = first + nearest_sample(stamps, when) + sim.display
            if onset + sim.first < sim.next:
                sim.late.append((step, late := pylsl.local_clock() - when))
                log.warning("onset of step %d came %.3f s late: its epoch's first samples "
                            "are sent already; nothing written", step, late)
                continue
            repeat = sum(w.step == step for w in sim.written)
            written = Written(step, repeat, onset, onset + sim.first,
                              sim.signals.epochs[sim.answers[step]], onset)
            sim.written.append(written)
            sim.pending.append(written)
        self.onsets = waiting


def _drop(outlet: object) -> None:
    """Hold the last reference to ``outlet`` until this thread ends (where it is destroyed)."""
    del outlet
