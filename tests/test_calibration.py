"""The confidence calibration curve: bins, pooling, and its figures from real sessions."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cfbci.cli import main
from replay.calibration import (
    N_BINS,
    bin_of,
    calibration_counts,
    calibration_curve,
    pool_counts,
)


def test_counts_bin_each_step_and_the_last_bin_is_closed() -> None:
    counts = calibration_counts([0.0, 0.05, 0.95, 0.9, 1.0, 0.5], [False, True, True, False,
                                                                    True, True])
    assert counts[0] == [2, 1] and counts[5] == [1, 1] and counts[N_BINS - 1] == [3, 2]
    assert sum(n for n, _ in counts) == 6
    curve = calibration_curve(pool_counts([counts, counts]))
    top = curve[bin_of(0.9)]
    assert (top.low, top.high, top.steps, top.fraction_right) == (0.9, 1.0, 6, pytest.approx(2 / 3))
    assert curve[3].fraction_right is None and curve[3].steps == 0


def test_a_confidence_outside_the_unit_interval_is_named() -> None:
    with pytest.raises(ValueError, match=r"must be in \[0, 1\]; got 1\.5"):
        calibration_counts([1.5], [True])
    with pytest.raises(ValueError, match="2 confidences but 1 outcomes"):
        calibration_counts([0.1, 0.2], [True])


def test_simulate_reports_a_curve_where_confidence_grows_with_being_right(
    tmp_path: Path,
) -> None:
    # Synthetic default data, 4 seeds x 150 steps: every step is counted once, and the
    # confident bin is right far more often than the least confident one (a curve that
    # mixed up the best task and the user's target would not be).
    out = tmp_path / "sim.json"
    assert main(["simulate", "--seeds", "4", "--steps", "150", "--jobs", "1",
                 "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    curve = report["summary"]["confidence_calibration"]
    assert sum(b["steps"] for b in curve) == 4 * 150
    filled = [b for b in curve if b["steps"] >= 10]
    assert filled[-1]["low"] == 0.9
    assert filled[-1]["fraction_right"] >= 0.8 > filled[0]["fraction_right"] + 0.3
    for session in report["sessions"]:
        assert sum(n for n, _ in session["calibration_counts"]) == 150
