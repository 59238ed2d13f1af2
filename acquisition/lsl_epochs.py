"""Epochs cut from continuous, timestamped EEG: the bridge's sample buffer.

`SampleBuffer` keeps the last seconds of a regularly sampled stream with each
sample's timestamp and arrival time, and splits it into *segments* at every
discontinuity: consecutive timestamps more than ``1 + tolerance`` sample periods apart
(samples dropped, a stream restarted) or less than ``1 - tolerance`` apart (duplicated or
backwards timestamps). `SampleBuffer.cut` takes the samples around an onset in
MNE's way: the onset is the sample nearest the onset time, the epoch runs from
``round(tmin * sfreq)`` to ``round(tmax * sfreq)`` samples after it, both included. An
epoch is only ever cut from one segment: a window that reaches across a discontinuity,
or whose onset falls into one, is refused; a window whose last sample has not arrived
yet is waited for.

`nearest_sample` is the onset rule the bridge and the LSL simulator share. Two
descriptions shared by the live bridge and the XDF reader: `microvolts_per_unit`
(a channel unit as LSL streams and XDF files declare it) and
`player_annotation_shift` (the marker offset of mne-lsl's ``PlayerLSL``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Microvolts per unit of the channel units streams declare by name (case-insensitive).
_MICROVOLTS_PER_NAMED_UNIT = {
    "microvolts": 1.0, "microvolt": 1.0, "uv": 1.0, "µv": 1.0, "μv": 1.0,
    "millivolts": 1e3, "millivolt": 1e3, "mv": 1e3,
    "volts": 1e6, "volt": 1e6, "v": 1e6,
}  # fmt: skip
#: What a stream with no unit carries (XDF's EEG convention).
DEFAULT_UNIT = "microvolts"


def microvolts_per_unit(unit: str | None) -> float | None:
    """Microvolts per unit of an EEG channel's declared unit; None if it is no voltage.

    ``unit`` is a name (``microvolts``, ``mV``, ``volts``, ...; none or empty: microvolts)
    or, as mne-lsl writes it, the FIFF unit multiplier: a decimal integer exponent ``e``
    of the channel's SI unit, volts for EEG, so the values are ``10**e`` V (``"0"``
    volts, ``"-3"`` millivolts, ``"-6"`` microvolts).
    """
    text = (unit or DEFAULT_UNIT).strip().lower()
    if text in _MICROVOLTS_PER_NAMED_UNIT:
        return _MICROVOLTS_PER_NAMED_UNIT[text]
    digits = text.removeprefix("-").removeprefix("+")
    if digits.isdigit() and int(digits) <= 24:  # FIFF's multipliers span 1e-24 .. 1e24
        return 10.0 ** (int(text) + 6)
    return None


def parse_onset_marker(text: str, word: str) -> tuple[bool, int | None]:
    """Whether a marker is an action onset, and the step it names (None if it names none).

    ``"<word>"`` and ``"<word> <step>"`` are onsets; anything else is not.
    """
    head, _, rest = text.strip().partition(" ")
    if head != word:
        return False, None
    rest = rest.strip()
    return True, int(rest) if rest.isdigit() else None


def player_annotation_shift(
    stream_type: str, channel_format: str, labels: list[str] | None, types: list[str] | None
) -> int:
    """Samples to add to a marker stream's timestamps: 1 for the annotations of mne-lsl's
    ``PlayerLSL`` (string encoding), 0 for any other stream.

    The player stamps an annotation at ``chunk start + (onset - chunk's first sample
    time)``, where the chunk's start is the previous chunk's last-sample stamp, while its
    data's samples are stamped from the chunk's last sample back: every annotation is one
    sample period before the sample it annotates (mne-lsl 1.14). Its annotation stream
    is recognised by what the player declares: type ``annotations``, one string channel
    labelled ``description`` of type ``annotations``.

    Parameters
    ----------
    stream_type, channel_format : str
        The stream's ``type`` and ``channel_format`` (``"string"``).
    labels, types : list of str or None
        Its channels' ``label`` and ``type`` (``desc/channels/channel``), if declared.
    """
    is_player = (
        stream_type.lower() == "annotations" and channel_format == "string"
        and labels == ["description"] and types is not None
        and [kind.lower() for kind in types] == ["annotations"]
    )
    return int(is_player)


def nearest_sample(times: np.ndarray, onset: float) -> int:
    """The onset sample: the index of the timestamp nearest ``onset``, the later one of two
    equally near.

    The bridge cuts every epoch around this sample, and ``cfbci lsl-simulator`` writes
    every epoch it is told to write at a marker's time around it: both call this function
    on the same float64 timestamps, so that they choose the same sample.

    Parameters
    ----------
    times : ndarray, shape (n_samples,)
        Increasing timestamps, s (at least one).
    onset : float
        The onset's time, s, in the same clock.
    """
    nearest = int(np.clip(np.searchsorted(times, onset), 1, max(len(times) - 1, 1)))
    if len(times) > 1 and onset - times[nearest - 1] < times[nearest] - onset:
        nearest -= 1
    return min(nearest, len(times) - 1)


@dataclass(frozen=True)
class Gap:
    """A discontinuity between two consecutive samples.

    Attributes
    ----------
    index : int
        Index of the first sample after it (samples are counted from 0 in arrival order).
    before, after : float
        Timestamps of the samples on either side, s (the stream's clock).
    missing : int
        Sample periods missing between them, ``round((after - before) * sfreq) - 1``
        (0 or negative when the timestamps went backwards or repeated).
    """

    index: int
    before: float
    after: float
    missing: int

    def describe(self) -> str:
        if self.missing > 0:
            return (f"{self.missing} samples missing between t={self.before:.4f} s and "
                    f"t={self.after:.4f} s (before sample {self.index})")
        return (f"timestamps out of order at sample {self.index}: t={self.before:.4f} s then "
                f"t={self.after:.4f} s")


@dataclass(frozen=True)
class Epoch:
    """A window of samples around an onset.

    Attributes
    ----------
    data : ndarray, shape (n_channels, n_times), float32
        Microvolts.
    onset_index : int
        Index of the onset sample.
    onset_time : float
        Timestamp of the onset sample, s.
    last_time : float
        Timestamp of the window's last sample, s.
    last_arrival_ns : int
        ``time.monotonic_ns()`` when the window's last sample arrived.
    """

    data: np.ndarray
    onset_index: int
    onset_time: float
    last_time: float
    last_arrival_ns: int


@dataclass(frozen=True)
class Refusal:
    """Why no epoch can be cut around an onset (it never will be)."""

    reason: str


class SampleBuffer:
    """The last ``seconds`` of a regularly sampled stream, split at discontinuities.

    Parameters
    ----------
    n_channels : int
    sfreq : float
        Nominal sampling rate, Hz.
    seconds : float
        How much to keep, s.
    tolerance : float, default 0.5
        Allowed deviation of the interval between consecutive timestamps from the sample
        period, in sample periods; beyond it the interval is a discontinuity.
    """

    def __init__(
        self, n_channels: int, sfreq: float, seconds: float, tolerance: float = 0.5
    ) -> None:
        if not 0 < tolerance < 1:
            raise ValueError(
                f"the gap tolerance must be in (0, 1) sample periods; got {tolerance}"
            )
        self.sfreq, self.tolerance = sfreq, tolerance
        self.capacity = max(round(seconds * sfreq), 1)
        self._data = np.zeros((self.capacity, n_channels), dtype=np.float32)
        self._times = np.zeros(self.capacity)
        self._arrivals = np.zeros(self.capacity, dtype=np.int64)
        self.end = 0  # samples received so far: the next sample's index
        self._starts: list[int] = [0]  # index of the first sample of every segment

    @property
    def oldest(self) -> int:
        """Index of the oldest sample still buffered."""
        return max(0, self.end - self.capacity)

    def append(self, samples: np.ndarray, times: np.ndarray, arrival_ns: int) -> list[Gap]:
        """Add samples (shape (n, n_channels), float32 µV) with their timestamps (s).

        Returns the discontinuities found before and between them.
        """
        n = len(times)
        if n == 0:
            return []
        previous = self._times[(self.end - 1) % self.capacity] if self.end else times[0]
        steps = np.diff(np.concatenate([[previous], times])) * self.sfreq
        jumps = np.flatnonzero(np.abs(steps - 1) > self.tolerance)
        if self.end == 0:
            jumps = jumps[jumps > 0]
        gaps = [
            Gap(self.end + int(j), float(times[j - 1]) if j else float(previous),
                float(times[j]), round(float(steps[j])) - 1)
            for j in jumps
        ]
        self._starts += [gap.index for gap in gaps]
        for chunk in range(0, n, self.capacity):  # more than the capacity: keep the newest
            part = slice(chunk, min(chunk + self.capacity, n))
            positions = np.arange(self.end + part.start, self.end + part.stop) % self.capacity
            self._data[positions] = samples[part]
            self._times[positions] = times[part]
            self._arrivals[positions] = arrival_ns
        self.end += n
        oldest = self.oldest
        self._starts = [oldest] + [s for s in self._starts if s > oldest]
        return gaps

    def _segment(self, time: float) -> tuple[int, int] | str | None:
        """The (start, stop) indices of the segment holding ``time`` within half a period,
        None if ``time`` is after every sample, or why no segment holds it."""
        half = 0.5 / self.sfreq
        if self.end == 0 or time > self._times[(self.end - 1) % self.capacity] + half:
            return None
        stops = [*self._starts[1:], self.end]
        for start, stop in zip(reversed(self._starts), reversed(stops), strict=True):
            if time >= self._times[start % self.capacity] - half:
                if time <= self._times[(stop - 1) % self.capacity] + half:
                    return start, stop
                return f"the onset t={time:.4f} s falls in a gap before sample {stop}"
        return (f"the onset t={time:.4f} s is before the oldest buffered sample "
                f"(t={self._times[self.oldest % self.capacity]:.4f} s)")

    def cut(self, onset: float, first: int, last: int) -> Epoch | Refusal | None:
        """The epoch of samples ``first`` to ``last`` (included) after the onset sample.

        Parameters
        ----------
        onset : float
            Onset time in the stream's clock, s.
        first, last : int
            Window limits in samples relative to the onset sample (``first <= last``).

        Returns
        -------
        Epoch, Refusal or None
            None while the window's last sample has not arrived (and no discontinuity has
            broken the window yet).
        """
        found = self._segment(onset)
        if found is None or isinstance(found, str):
            return found if found is None else Refusal(found)
        start, stop = found
        positions = np.arange(start, stop) % self.capacity
        onset_index = start + nearest_sample(self._times[positions], onset)
        begin, finish = onset_index + first, onset_index + last
        if begin < start:
            where = (
                "the oldest buffered sample" if start == self.oldest
                else f"the gap before sample {start}"
            )
            return Refusal(f"the window (samples {begin}..{finish}) starts before {where}")
        if finish >= stop:
            if stop == self.end:
                return None
            return Refusal(
                f"the window (samples {begin}..{finish}) spans the gap before sample {stop}"
            )
        window = np.arange(begin, finish + 1) % self.capacity
        return Epoch(
            np.ascontiguousarray(self._data[window].T), onset_index,
            float(self._times[onset_index % self.capacity]),
            float(self._times[finish % self.capacity]),
            int(self._arrivals[finish % self.capacity]),
        )


def apply_baseline(
    epoch: np.ndarray, times: np.ndarray, baseline: tuple[float | None, float | None] | None
) -> np.ndarray:
    """Subtract each channel's mean over the baseline interval, as MNE does.

    Parameters
    ----------
    epoch : ndarray, shape (n_channels, n_times), float32
    times : ndarray, shape (n_times,)
        Sample times relative to the onset, s.
    baseline : (float or None, float or None) or None
        Interval in s, ends included; None for an end means the epoch's first (last)
        sample; None: no correction (``epoch`` returned unchanged).

    Returns
    -------
    ndarray, float32, the shape of ``epoch``.
    """
    if baseline is None:
        return epoch
    low = times[0] if baseline[0] is None else baseline[0]
    high = times[-1] if baseline[1] is None else baseline[1]
    mask = (times >= low - 1e-9) & (times <= high + 1e-9)
    if not mask.any():
        raise ValueError(f"baseline {baseline} s holds no sample of the epoch "
                         f"({times[0]:.3f} to {times[-1]:.3f} s)")
    mean = epoch[:, mask].astype(np.float64).mean(axis=1, keepdims=True)
    return (epoch.astype(np.float64) - mean).astype(np.float32)
