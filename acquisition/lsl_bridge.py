"""The LSL bridge: a Zenoh source whose epochs are cut from an amplifier's LSL stream.

``cfbci lsl-bridge`` stands where the simulated source stands in ``cfbci session``: it
sends the session's ``config`` to the pipeline service, forwards every ``move`` of the
service to the stimulus program (the LSL move stream,
`acquisition.lsl_streams.move_marker`) and answers it with the ``epoch`` cut from the
continuous EEG around the stimulus program's onset marker of that step (docs/protocol.md).
It publishes no ``truth``: in the lab nobody knows it; ``cfbci lsl-simulator`` publishes
its own. The loop is every client's, `wire.client.Client`: the config is re-sent
until the session starts and each epoch until the next move arrives (a service that
dropped one, or was restarted, still gets it), a move sent again is the one the bridge
has (the stimulus program sees it once), and the session ends only on ``session_ended``
or on a ``session_rejected`` answering the bridge's own config.

Timing. Samples are placed by their LSL timestamps, markers by theirs; both are mapped to
this machine's clock with the inlets' ``time_correction()`` (the marker time is then
expressed in the EEG stream's clock), except that a stream from a program on this machine
(its ``hostname``) shares this machine's clock and is taken as it is: a measured offset
would only add some microseconds of noise, enough to move an onset that falls half-way
between two samples to the other one. The onset is the EEG sample nearest the marker
(``acquisition.lsl_epochs.nearest_sample``, the later of two equally near) and
the epoch the samples ``round(tmin * sfreq)`` to ``round(tmax * sfreq)`` around it (MNE's
rule), corrected by ``baseline`` if one is given (none by default: the service's feature
extraction band-passes every epoch, and the raw window stays identical to the samples
the amplifier sent).

Streams the project did not write. The EEG stream's channel labels, units and nominal
rate are its own metadata; units may be named (microvolts, millivolts, volts) or, as
mne-lsl writes them, a power of ten of volts (``"0"``: volts). The markers must be
strings. mne-lsl's ``PlayerLSL`` (``annotations=True, annotations_encoding="string"``)
plays a raw ``.fif`` as an amplifier and its annotations ``onset <step>`` as the
stimulus program's markers (stream ``<name>-annotations``), but stamps every annotation
one sample period early (the chunk's start against the data's last-sample stamps); the
bridge recognises that stream by its metadata and adds the period back
(``marker_shift``; `acquisition.lsl_streams.marker_stream_shift`).

Faults. A discontinuity of the EEG timestamps (samples dropped, a restarted stream) is
reported and splits the buffer (`acquisition.lsl_epochs.SampleBuffer`); an epoch
is never cut across one. When the window of the awaited step is broken (by a gap, or by a
marker so late that its samples have left the buffer) the bridge reports it and sends the
move again with ``repeat`` incremented, and the stimulus program presents it again. An
onset marker that arrives more than ``late_marker`` seconds after its own timestamp is
reported (and used if its window is whole); one that names another step, precedes the
move or comes when no move awaits an onset is reported and ignored. A stream that is lost
is resolved again by name (a restarted source is found with its new uid).

Photodiode. With ``photodiode`` the onset is a photodiode channel's crossing paired with
the marker, the channel kept out of the epochs (the rule: ``acquisition.photodiode``).
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
import zenoh

from acquisition.lsl_epochs import Epoch, Gap, Refusal, SampleBuffer, apply_baseline
from acquisition.lsl_input import StreamInput, StreamReader
from acquisition.lsl_streams import (
    StreamMeta,
    as_float32,
    eeg_stream_meta,
    let_consumers_leave,
    marker_outlet,
    marker_stream_shift,
    move_marker,
    parse_onset_marker,
)
from acquisition.photodiode import Photodiode, PhotodiodeRule
from wire import protocol
from wire.client import RESEND_INTERVAL, Client
from wire.prior_upload import upload_priors
from wire.zenoh_config import peer_config

log = logging.getLogger("cfbci.lsl_bridge")

#: Name of the bridge's move stream (the stimulus program's input).
DEFAULT_MOVES = "cfbci-moves"
#: Seconds of EEG the bridge keeps.
DEFAULT_BUFFER_SECONDS = 30.0
#: Seconds the loop waits for the service or the streams before its checks.
_IDLE_SECONDS = 0.1
#: Seconds without EEG after which the silence is reported.
_SILENCE_SECONDS = 1.0


@dataclass(frozen=True)
class BridgeSettings:
    """One session bridged from LSL.

    Attributes
    ----------
    session : str
        Session id.
    eeg, markers : str
        Names of the EEG stream and of the stimulus program's marker stream.
    moves : str
        Name of the move stream the bridge creates.
    seed, steps, grid, frame, learner
        The session's config (see `acquisition.simulated_source.SourceSettings`).
    tmin, tmax : float
        Epoch limits around the onset, s (rounded to samples as MNE does).
    baseline : (float or None, float or None) or None
        MNE-style baseline interval, s; None: no correction.
    onset_marker : str
        The marker word of an action onset (``"<word>"`` or ``"<word> <step>"``).
    marker_shift : int or None
        EEG sample periods added to every marker timestamp; None: from the marker stream's
        metadata (1 for an mne-lsl ``PlayerLSL`` annotation stream, else 0).
    gap_tolerance : float
        Deviation of a timestamp interval from the sample period, in periods, beyond
        which it is a discontinuity.
    buffer_seconds : float
        EEG kept for markers that come late, s.
    late_marker : float
        An onset marker arriving more than this many seconds after its timestamp is
        reported as late.
    timeout : float
        Seconds to find a stream, or that the service or the stimulus program may keep the
        bridge waiting, before giving up.
    photodiode : PhotodiodeRule or None
        Take the onsets from this photodiode channel (``acquisition.photodiode``).
    prior : tuple of Path
        Earlier recordings of the user the learner starts from (``cfbci source --prior``).
    """

    session: str
    eeg: str
    markers: str
    moves: str = DEFAULT_MOVES
    seed: int = 0
    steps: int = 500
    grid: int = 5
    frame: str = "feedback"
    learner: dict[str, Any] = field(default_factory=dict)
    tmin: float = -0.2
    tmax: float = 1.0
    baseline: tuple[float | None, float | None] | None = None
    onset_marker: str = "onset"
    marker_shift: int | None = None
    gap_tolerance: float = 0.5
    buffer_seconds: float = DEFAULT_BUFFER_SECONDS
    late_marker: float = 0.5
    timeout: float = 30.0
    photodiode: PhotodiodeRule | None = None
    prior: tuple[Path, ...] = ()

    def window(self, sfreq: float) -> tuple[int, int]:
        """First and last sample of an epoch relative to its onset sample."""
        first, last = round(self.tmin * sfreq), round(self.tmax * sfreq)
        if last <= first:
            raise ValueError(f"--tmax ({self.tmax} s) must be after --tmin ({self.tmin} s) by "
                             f"at least a sample at {sfreq:g} Hz")
        if (last - first + 1) / sfreq >= self.buffer_seconds / 2:
            raise ValueError(f"the buffer ({self.buffer_seconds:g} s) must hold at least two "
                             "epoch windows")
        return first, last

    def config(self, meta: StreamMeta) -> dict[str, Any]:
        """The fields of the session's ``config`` message for an EEG stream of ``meta``
        (its epochs' channels without the photodiode's), the prior left out."""
        first, _ = self.window(meta.sfreq)
        names = list(meta.ch_names)
        if self.photodiode is not None:
            names = self.photodiode.bind(names, meta.sfreq).eeg_names(names)
        return {
            "seed": self.seed, "world": "grid", "grid": self.grid, "frame": self.frame,
            "steps": self.steps, "learner": self.learner,
            "dataset": {"description": f"LSL streams {self.eeg!r} (EEG) and "
                                       f"{self.markers!r} (markers)"},
            "signal": "epochs", "sfreq": meta.sfreq, "tmin": first / meta.sfreq,
            "ch_names": names,
        }


@dataclass
class BridgeSummary:
    """What the bridge did.

    Attributes
    ----------
    session : str
    epochs : list of dict
        Every published epoch: ``step``, ``onset`` (its onset sample's timestamp, s),
        ``repeat`` (how often its move had been sent again), ``arrived`` (when its
        window's last sample arrived, s of the monotonic clock: ``pylsl.local_clock``'s on
        Linux); with a photodiode, ``marker`` (the marker's time in the EEG's clock, s).
    gaps : list of Gap
        Discontinuities of the EEG, in order.
    refused : list of dict
        Windows that could not be cut: ``step``, ``reason``.
    late_markers : list of dict
        ``step`` and ``delay`` (s from the marker's timestamp to its arrival).
    ignored_markers : list of str
        Why each ignored onset marker was ignored.
    reconnects : list of str
        The streams resolved again after being lost, in order.
    latency_ns : list of int
        Per published epoch, from the arrival of its window's last sample to its
        publication, ns of the monotonic clock.
    age_s : list of float
        Per published epoch, from its last sample's timestamp (mapped to this machine's
        clock) to its publication, s: the latency above plus the amplifier's chunking and
        LSL's transport.
    """

    session: str
    epochs: list[dict[str, Any]] = field(default_factory=list)
    gaps: list[Gap] = field(default_factory=list)
    refused: list[dict[str, Any]] = field(default_factory=list)
    late_markers: list[dict[str, Any]] = field(default_factory=list)
    ignored_markers: list[str] = field(default_factory=list)
    reconnects: list[str] = field(default_factory=list)
    latency_ns: list[int] = field(default_factory=list)
    age_s: list[float] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dictionary, with the latencies' median, p99 and max in ms."""
        return {
            "session": self.session, "epochs": self.epochs,
            "gaps": [vars(gap) for gap in self.gaps], "refused": self.refused,
            "late_markers": self.late_markers, "ignored_markers": self.ignored_markers,
            "reconnects": self.reconnects,
            "latency_ms": _figures(np.asarray(self.latency_ns, dtype=float) / 1e6),
            "age_ms": _figures(np.asarray(self.age_s) * 1e3),
            "latency_ns": self.latency_ns, "age_s": self.age_s,
        }


def _figures(values_ms: np.ndarray) -> dict[str, float]:
    """Median, p99 and max of some milliseconds ({} for none)."""
    if not len(values_ms):
        return {}
    return {"median": float(np.median(values_ms)), "p99": float(np.percentile(values_ms, 99)),
            "max": float(values_ms.max())}


def run_bridge(
    settings: BridgeSettings, listen: Sequence[str] = (), connect: Sequence[str] = (),
    keep_running: Callable[[], bool] = lambda: True, zenoh_config: Path | None = None,
) -> BridgeSummary:
    """Open a Zenoh session (`wire.zenoh_config.peer_config`: a peer, or what
    ``zenoh_config``, a JSON5 file, says, e.g. a router's client with its user's
    credentials) and bridge one session (see `bridge_session`)."""
    with zenoh.open(peer_config(listen, connect, zenoh_config)) as session:
        return bridge_session(session, settings, keep_running)


@dataclass
class _Awaited:
    """The step whose epoch the bridge waits for."""

    move: dict[str, Any]
    sent_at: float  # this machine's LSL clock when its move was pushed, s
    repeat: int = 0
    onset: float | None = None  # onset in the EEG stream's clock, s

    @property
    def step(self) -> int:
        return int(self.move["step"])


def bridge_session(
    session: zenoh.Session, settings: BridgeSettings,
    keep_running: Callable[[], bool] = lambda: True,
) -> BridgeSummary:
    """Bridge one session between LSL and the service reachable through ``session``.

    Raises
    ------
    TimeoutError
        If a stream is not found, no stimulus program subscribes to the move stream, no
        service subscribes to the config, or the service or the stimulus program keeps the
        bridge waiting for ``settings.timeout`` s.
    RuntimeError
        If the service rejects the session (a ``session_rejected`` event answering its
        config) or a prior's upload; ``error`` events about single messages are logged.
    ValueError
        If the EEG stream's metadata do not describe EEG (see
        `acquisition.lsl_streams.eeg_stream_meta`) or the marker stream does not
        carry strings.
    """
    summary = BridgeSummary(settings.session)
    stop = threading.Event()  # the reader's

    def reading() -> bool:
        return keep_running() and not stop.is_set()

    eeg = StreamInput(settings.eeg, settings.timeout, summary.reconnects, reading)
    meta = eeg_stream_meta(eeg.inlet.info())
    first, last = settings.window(meta.sfreq)
    photodiode = settings.photodiode and settings.photodiode.bind(list(meta.ch_names), meta.sfreq)
    names = photodiode.eeg_names(list(meta.ch_names)) if photodiode else list(meta.ch_names)
    markers = StreamInput(settings.markers, settings.timeout, summary.reconnects, reading)
    shift = settings.marker_shift
    if shift is None:
        shift = marker_stream_shift(markers.inlet.info())
        if shift:
            log.info("marker stream %r is mne-lsl's PlayerLSL annotations: timestamps "
                     "moved %d sample later", settings.markers, shift)
    for stream in (eeg, markers):  # the first estimate takes a while: get it now
        stream.clock_offset()
    moves = marker_outlet(settings.moves, f"cfbci-bridge-{settings.session}-moves")
    if not moves.wait_for_consumers(settings.timeout):
        raise TimeoutError(f"no stimulus program subscribed to the move stream "
                           f"{settings.moves!r} within {settings.timeout:g} s")
    config = settings.config(meta)
    if settings.prior:  # uploaded first: the config names the bytes uploaded
        config["prior"] = upload_priors(session, settings.session, settings.prior,
                                        settings.timeout, RESEND_INTERVAL)
    with Client(session, settings.session, log, settings.timeout) as client:
        reader = StreamReader(eeg, markers, client.wake, stop)
        bridge = _Bridge(settings, meta, (first, last), shift / meta.sfreq, reader, moves,
                         client, summary, photodiode or None, names)
        reader.start()
        try:
            client.run(config, bridge, keep_running)
        finally:
            stop.set()
            reader.join()
    for stream in (eeg, markers):  # before their outlets close: no broken stream
        stream.inlet.close_stream()
    let_consumers_leave(moves)
    return summary


class _Bridge:
    """The bridge's side of the session (a `wire.client.Answerer`): EEG in, markers
    in, moves out to the stimulus program, epochs out to the client."""

    def __init__(
        self, settings: BridgeSettings, meta: StreamMeta, window: tuple[int, int],
        marker_shift: float, reader: StreamReader, moves: pylsl.StreamOutlet, client: Client,
        summary: BridgeSummary, photodiode: Photodiode | None, names: list[str],
    ) -> None:
        self.settings, self.meta, self.window = settings, meta, window
        self.marker_shift = marker_shift  # s added to every marker timestamp
        self.reader, self.eeg, self.markers = reader, reader.eeg, reader.markers
        self.moves, self.client = moves, client
        self.summary, self.photodiode, self.names = summary, photodiode, names
        self.buffer = SampleBuffer(len(meta.ch_names), meta.sfreq, settings.buffer_seconds,
                                   settings.gap_tolerance)
        self.times = np.arange(window[0], window[1] + 1) / meta.sfreq
        self.awaited: _Awaited | None = None
        # Last EEG sample, and last progress on the awaited step (its move, its onset), ns.
        self.eeg_ns = self.progress_ns = time.monotonic_ns()
        self.silent = False

    def poll(self) -> float:
        """Take the reader's polls in order, each a round: its EEG, its markers, then cut
        what is due; wait for the service at most `_IDLE_SECONDS` (the reader wakes the
        loop when a stream brings something)."""
        while True:
            try:
                samples, times, eeg_ns, values, stamps, arrived = self.reader.taken.get_nowait()
            except queue.Empty:
                break
            self._take_eeg(samples, times, eeg_ns)
            self._take_markers(values, stamps, arrived)
            if self.awaited is not None and self.awaited.onset is not None:
                self._try_cut(self.awaited)
        if self.reader.error is not None:
            raise self.reader.error
        self._check_silence()
        return _IDLE_SECONDS

    def _take_eeg(self, samples: Any, times: Any, now: int) -> None:
        if not len(times):
            return
        self.eeg_ns = now
        if self.silent:
            log.warning("EEG stream %r: samples again", self.settings.eeg)
            self.silent = False
        for gap in self.buffer.append(as_float32(samples, self.meta.scale), times, now):
            log.warning("EEG stream %r: %s", self.settings.eeg, gap.describe())
            self.summary.gaps.append(gap)

    def _take_markers(self, values: Any, times: Any, arrived: float) -> None:
        for value, stamp in zip(values, times, strict=True):
            is_onset, step = parse_onset_marker(value[0], self.settings.onset_marker)
            if is_onset:
                self._on_onset(float(stamp), step, arrived)
            else:
                log.debug("marker %r is no onset; ignored", value[0])

    def _ignore(self, why: str) -> None:
        log.warning("onset marker ignored: %s", why)
        self.summary.ignored_markers.append(why)

    def _on_onset(self, stamp: float, named_step: int | None, arrived: float) -> None:
        """Take an onset marker (its timestamp, the step it names, when it was pulled in
        this machine's LSL clock, s)."""
        local = stamp + self.marker_shift + self.markers.clock_offset()
        awaited = self.awaited
        if awaited is None or awaited.onset is not None:
            self._ignore(f"onset at t={local:.4f} s while no move awaits one")
            return
        if named_step is not None and named_step != awaited.step:
            self._ignore(f"onset of step {named_step} while step {awaited.step} is awaited")
            return
        if local < awaited.sent_at:
            self._ignore(f"onset at t={local:.4f} s precedes the move of step {awaited.step} "
                         f"(sent at t={awaited.sent_at:.4f} s)")
            return
        delay = arrived - local
        if delay > self.settings.late_marker:
            log.warning("late marker: the onset of step %d arrived %.3f s after its timestamp",
                        awaited.step, delay)
            self.summary.late_markers.append({"step": awaited.step, "delay": delay})
        awaited.onset = local - self.eeg.clock_offset()
        self.progress_ns = time.monotonic_ns()

    def _try_cut(self, awaited: _Awaited) -> None:
        assert awaited.onset is not None
        onset = awaited.onset if self.photodiode is None else self.photodiode.locate(
            self.buffer, awaited.onset)
        result = onset if not isinstance(onset, float) else self.buffer.cut(onset, *self.window)
        if result is None:
            return
        if isinstance(result, Refusal):
            log.warning("step %d: no epoch: %s; asking for the action again", awaited.step,
                        result.reason)
            self.summary.refused.append({"step": awaited.step, "reason": result.reason})
            awaited.repeat += 1
            self._send_move(awaited)
            return
        self._publish(awaited, result)

    def _publish(self, awaited: _Awaited, epoch: Epoch) -> None:
        data = epoch.data if self.photodiode is None else self.photodiode.strip(epoch.data)
        data = apply_baseline(data, self.times, self.settings.baseline)
        fields = {"step": awaited.step, "signal": "epochs", "ch_names": self.names}
        self.client.send_epoch(fields, data)
        self.summary.latency_ns.append(time.monotonic_ns() - epoch.last_arrival_ns)
        self.summary.age_s.append(pylsl.local_clock() - epoch.last_time - self.eeg.offset)
        self.summary.epochs.append(
            {"step": awaited.step, "onset": epoch.onset_time, "repeat": awaited.repeat,
             "arrived": epoch.last_arrival_ns / 1e9}
            | ({"marker": awaited.onset} if self.photodiode else {})
        )
        self.awaited = None

    def _send_move(self, awaited: _Awaited) -> None:
        awaited.onset = None
        awaited.sent_at = pylsl.local_clock()
        self.moves.push_sample([move_marker(awaited.move, awaited.repeat)])

    def on_move(self, move: protocol.Message) -> None:
        """Forward the move to the stimulus program; its epoch is cut once its onset marker
        and window have come (`poll`)."""
        if self.awaited is not None:
            log.warning("move of step %d while step %d awaits its epoch; following the service",
                        move.fields["step"], self.awaited.step)
        self.progress_ns = time.monotonic_ns()
        self.awaited = _Awaited(move.fields, 0.0)
        self._send_move(self.awaited)

    def _check_silence(self) -> None:
        """Report a silent EEG stream; give up on a step whose onset or window does not
        come (the client gives up on a silent service)."""
        now = time.monotonic_ns()
        if not self.silent and now - self.eeg_ns > _SILENCE_SECONDS * 1e9:
            log.warning("EEG stream %r: no sample for %.1f s", self.settings.eeg,
                        (now - self.eeg_ns) / 1e9)
            self.silent = True
        awaited = self.awaited
        if awaited is not None and now - self.progress_ns > self.settings.timeout * 1e9:
            what = (
                f"the onset marker of step {awaited.step}" if awaited.onset is None
                else f"the samples of step {awaited.step}'s window"
            )
            raise TimeoutError(f"session {self.settings.session!r}: waited "
                               f"{self.settings.timeout:g} s for {what}")
