"""The pieces the stimulus loop's timing rests on: the page clock's offset from round trips
(`acquisition.clock_sync`), and the onset sample the bridge and the listening simulator
both choose (`acquisition.lsl_epochs.nearest_sample`)."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.clock_sync import ClockSync
from acquisition.lsl_epochs import nearest_sample


def _trip(sync: ClockSync, sent: float, out: float, back: float, offset: float) -> None:
    """A round trip leaving at ``sent`` (this clock), ``out`` s to the other side, which
    answers at once, and ``back`` s back; the other clock is this one minus ``offset``."""
    sync.add(sent, sent + out - offset, sent + out + back)


def test_the_offset_comes_from_the_fastest_round_trips_within_their_bound() -> None:
    rng = np.random.default_rng(0)
    sync, offset = ClockSync(window=64, best=8), 1234.5678
    assert not sync.ready and sync.estimate() is None
    for k in range(200):
        # Mostly slow and lopsided trips (a busy page answers late), some fast ones.
        fast = k % 5 == 0
        out, back = (rng.uniform(1e-4, 2e-4, 2) if fast
                     else (rng.uniform(1e-4, 2e-4), rng.uniform(5e-3, 40e-3)))
        _trip(sync, 10.0 + k * 0.25, out, back, offset)
    estimate = sync.estimate()
    assert estimate is not None and estimate.round_trips == 64
    # The window's fastest trips give it: its error within their half round trip, far
    # below the slow trips' lopsidedness (milliseconds).
    assert estimate.uncertainty <= 2e-4
    assert abs(estimate.offset - offset) <= estimate.uncertainty
    naive = np.median([t[1] for t in sync._trips])
    assert abs(naive - offset) > 1e-3  # what all the trips alike would have given


def test_the_window_follows_a_clock_that_jumps() -> None:
    sync = ClockSync(window=16, best=4)
    for k in range(16):
        _trip(sync, k * 0.1, 1e-4, 1e-4, offset=5.0)
    assert sync.estimate().offset == pytest.approx(5.0, abs=1e-9)
    for k in range(16, 32):
        _trip(sync, k * 0.1, 1e-4, 1e-4, offset=7.0)
    assert sync.estimate().offset == pytest.approx(7.0, abs=1e-9)


def test_bad_round_trips_are_refused() -> None:
    sync = ClockSync()
    with pytest.raises(ValueError, match="before its ping was sent"):
        sync.add(2.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="finite"):
        sync.add(1.0, float("nan"), 2.0)
    with pytest.raises(ValueError, match="best"):
        ClockSync(window=4, best=5)


def test_the_onset_is_the_nearest_sample_the_later_of_two_equally_near() -> None:
    sfreq, t0 = 256.0, 1000.123
    times = t0 + np.arange(0, 20) / sfreq
    assert nearest_sample(times, times[7]) == 7
    assert nearest_sample(times, times[7] + 0.4 / sfreq) == 7
    assert nearest_sample(times, times[7] + 0.6 / sfreq) == 8
    middle = (times[7] + times[8]) / 2
    assert times[8] - middle == middle - times[7]  # exactly half-way in float64
    assert nearest_sample(times, middle) == 8
    assert nearest_sample(times, times[0] - 1.0) == 0
    assert nearest_sample(times, times[-1] + 1.0) == 19
    # A window of three stamps around an onset gives the sample the whole stream gives
    # (the listening simulator looks at three, the bridge at its whole buffer).
    for onset in np.random.default_rng(1).uniform(times[1], times[-2], 200):
        first = int((onset - t0) * sfreq) - 1
        window = t0 + np.arange(first, first + 3) / sfreq
        assert first + nearest_sample(window, onset) == nearest_sample(times, onset)
