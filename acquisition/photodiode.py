"""Onsets from a photodiode: what the screen showed, when, in the amplifier's own samples.

Software can time the frame a move is drawn in (``cfbci bench timing``), not when the
display lights it nor how late the amplifier stamps its samples. A photodiode taped to a
corner of the screen that the stimulus brightens with every move, wired into an auxiliary
channel of the amplifier, records the onset as the brain sees it, in the EEG's clock.

``cfbci lsl-bridge --photodiode CHANNEL`` (`PhotodiodeRule`) takes each onset from that
channel; the stimulus program's marker still says which step it is and roughly when:

* around the marker (its nearest sample, as without a photodiode) the bridge takes the
  channel's samples from ``baseline`` s before it to ``window`` s after it (from one
  segment of the buffer: not across a gap), once they have all arrived;
* the baseline is the median of the samples before the marker's sample; the pulse level
  the sample after it farthest from that baseline (either sign: a pulse may rise or fall);
* the threshold is half-way between the two, unless given (``--photodiode-threshold``,
  in the unit the bridge converts the stream to, µV for a stream in volts); with no
  threshold given, a pulse no farther from the baseline than 10 times the baseline's
  robust spread (1.4826 times its median absolute deviation) is no pulse;
* a crossing is a sample at or beyond the threshold (towards the pulse) whose previous
  sample is not, from the marker's sample on; the onset is the first sample of the one
  crossing in the window;
* no crossing, or more than one (a pulse that flickers, two shows), and the bridge
  refuses the window as it refuses a broken one: it reports why and sends the move again
  (``repeat`` + 1), so that no epoch is ever cut at a marker's guess when the photodiode
  says otherwise. A photodiode that fell off makes every move repeat: the bridge's
  warnings say so at the first one.

The channel is kept out of the epochs and of the session's channel names. The epoch is cut
around the crossing's sample by the usual window (MNE's rule), so an epoch's samples are
those around the light's onset, a display's delay later than the frame's.

``cfbci lsl-simulator --photodiode SECONDS`` writes such a channel (`pulse_column`): a
rectangular pulse of `PULSE_LEVEL` µV and `PULSE_SECONDS` from each epoch's onset sample,
which it places that delay (rounded to samples) after the marker's; the user's epoch is
written around it, as a brain would answer the screen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acquisition.lsl_epochs import Refusal, SampleBuffer

#: The simulator's photodiode channel: its name, pulse height (µV) and length (s).
PHOTODIODE_CHANNEL = "Photodiode"
PULSE_LEVEL = 1000.0
PULSE_SECONDS = 0.05
#: Without a threshold: the least pulse height, in robust spreads of the baseline.
CONTRAST = 10.0


@dataclass(frozen=True)
class PhotodiodeRule:
    """How the bridge takes onsets from a photodiode channel (see the module).

    Attributes
    ----------
    channel : str
        The channel's label in the EEG stream.
    threshold : float or None
        The crossing level, in the bridge's unit (µV); None: half-way between the
        baseline and the pulse level.
    window : float
        Seconds after the marker in which one crossing pairs with it.
    baseline : float
        Seconds before the marker whose median is the baseline.
    """

    channel: str
    threshold: float | None = None
    window: float = 0.1
    baseline: float = 0.1

    def __post_init__(self) -> None:
        if not 0 < self.window <= 1:
            raise ValueError(f"--photodiode-window must be in (0, 1] s; got {self.window}")
        if not 0 < self.baseline <= 1:
            raise ValueError(f"the photodiode baseline must be in (0, 1] s; got {self.baseline}")
        if self.threshold is not None and not np.isfinite(self.threshold):
            raise ValueError(f"--photodiode-threshold must be finite; got {self.threshold}")

    def bind(self, ch_names: list[str], sfreq: float) -> Photodiode:
        """The rule for a stream with these channel labels and rate (Hz).

        Raises
        ------
        ValueError
            If the stream has no such channel, or no other.
        """
        if self.channel not in ch_names:
            raise ValueError(f"--photodiode {self.channel!r}: the EEG stream has no such "
                             f"channel (it has {', '.join(ch_names)})")
        if len(ch_names) < 2:
            raise ValueError(f"--photodiode {self.channel!r} is the stream's only channel")
        return Photodiode(self, ch_names.index(self.channel), sfreq)


@dataclass(frozen=True)
class Photodiode:
    """A `PhotodiodeRule` bound to a stream: the channel's index and the rate (Hz)."""

    rule: PhotodiodeRule
    index: int
    sfreq: float

    def eeg_names(self, ch_names: list[str]) -> list[str]:
        """The channel labels without the photodiode's."""
        return [name for i, name in enumerate(ch_names) if i != self.index]

    def strip(self, data: np.ndarray) -> np.ndarray:
        """An epoch's samples (n_channels, n_times) without the photodiode's row."""
        return np.delete(data, self.index, axis=0)

    def locate(self, buffer: SampleBuffer, marker: float) -> float | Refusal | None:
        """The onset paired with a marker at ``marker`` (s, the EEG's clock): the crossing
        sample's time, a `Refusal` (no crossing, several, a gap), or None while the
        window's samples have not all arrived."""
        before = round(self.rule.baseline * self.sfreq)
        around = buffer.cut(marker, -before, round(self.rule.window * self.sfreq))
        if around is None or isinstance(around, Refusal):
            return around
        trace = around.data[self.index].astype(float)
        crossings = crossings_after(trace, before, self.rule.threshold)
        where = f"on {self.rule.channel!r} within {self.rule.window:g} s after the marker"
        if len(crossings) != 1:
            return Refusal(f"{'no' if not crossings else len(crossings)} photodiode "
                           f"crossing{'s' * (len(crossings) != 1)} {where}")
        return around.onset_time + (crossings[0] - before) / self.sfreq


def crossings_after(trace: np.ndarray, start: int, threshold: float | None) -> list[int]:
    """Indices ``i >= start`` of ``trace`` where it reaches the threshold (towards the
    pulse) and ``i - 1`` does not; the baseline is the median of ``trace[:start]``.

    Parameters
    ----------
    trace : ndarray, shape (n_times,)
        The photodiode's samples, µV, from the baseline's first to the window's last.
    start : int
        Index of the marker's sample (at least 1).
    threshold : float or None
        The level; None: half-way between the baseline and the pulse level, and no
        crossing when the pulse is within `CONTRAST` robust spreads of the baseline.
    """
    base = float(np.median(trace[:start]))
    after = trace[start:] - base
    peak = float(after[np.argmax(np.abs(after))])
    if threshold is None:
        spread = 1.4826 * float(np.median(np.abs(trace[:start] - base)))
        if abs(peak) <= CONTRAST * spread:
            return []
        level = peak / 2
    else:
        level = threshold - base
        if level == 0:
            return []
    beyond = (trace - base) * np.sign(level) >= abs(level)
    return [int(i) for i in np.flatnonzero(beyond[1:] & ~beyond[:-1]) + 1 if i >= start]


def pulse_column(indices: np.ndarray, onsets: list[int], width: int) -> np.ndarray:
    """The simulator's photodiode samples at ``indices``: `PULSE_LEVEL` µV for ``width``
    samples from each of ``onsets`` (sample indices), 0 elsewhere; shape (n, 1),
    float32."""
    lit = np.zeros(len(indices), dtype=bool)
    for onset in onsets:
        lit |= (indices >= onset) & (indices < onset + width)
    return (lit * PULSE_LEVEL).astype(np.float32)[:, None]
