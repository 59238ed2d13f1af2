"""The confidence calibration curve: bins, pooling, and its figures from real sessions."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from calibration_free.config import DEFAULT_BETA
from cfbci.cli import main
from replay.calibration import (
    N_BINS,
    bin_of,
    calibration_counts,
    calibration_curve,
    counts_by_rule,
    pool_counts,
    pool_counts_by_rule,
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


def test_counts_by_rule_split_the_steps_and_pool_per_rule() -> None:
    confidence = [0.95, 0.3, 0.999, 0.97, 0.5, 0.91]
    right = [True, False, True, False, True, True]
    rules = [("pairwise", 0.9), ("normalised", 0.995), ("normalised", 0.995),
             ("normalised", 0.995), ("pairwise", 0.9), ("pairwise", 0.9)]
    pairwise, normalised = counts_by_rule(confidence, right, rules)
    assert (pairwise.rule, pairwise.threshold, normalised.rule) == ("pairwise", 0.9, "normalised")
    assert pairwise.counts[9] == [2, 2] and pairwise.counts[5] == [1, 1]
    assert normalised.counts[9] == [2, 1] and normalised.counts[3] == [1, 0]
    # Above the threshold: the pairwise rule's 0.95 and 0.91, the normalised rule's 0.999.
    assert pairwise.above_threshold == [2, 2] and normalised.above_threshold == [1, 1]
    # Pooled over sessions, a rule met in one session only keeps its own counts.
    [only_pairwise] = counts_by_rule([0.92], [False], [("pairwise", 0.9)])
    pooled = pool_counts_by_rule([[pairwise, normalised], [only_pairwise]])
    assert [(p.rule, p.counts[9], p.above_threshold) for p in pooled] == [
        ("pairwise", [3, 2], [3, 2]), ("normalised", [2, 1], [1, 1])]
    with pytest.raises(ValueError, match="2 confidences but 1 rules"):
        counts_by_rule([0.1, 0.2], [True, False], [("pairwise", 0.9)])


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
    # Per rule: the pairwise W against its threshold before the evidence is calibrated, the
    # normalised likelihood against 0.995 in the segments after a target on 100 signals or
    # more; together they are every step, and the pairwise W of the best task is never
    # below 0.5 (the normalised likelihood often is).
    by_rule = {(r["rule"], r["threshold"]): r for r in
               report["summary"]["confidence_calibration_by_rule"]}
    pairwise_rule = ("pairwise", DEFAULT_BETA["feedback"])
    assert set(by_rule) == {pairwise_rule, ("normalised", 0.995)}
    assert [b["steps"] for b in curve] == [
        sum(r["curve"][k]["steps"] for r in by_rule.values()) for k in range(N_BINS)]
    pairwise, normalised = by_rule[pairwise_rule], by_rule[("normalised", 0.995)]
    assert all(b["steps"] == 0 for b in pairwise["curve"][:5])
    assert sum(b["steps"] for b in normalised["curve"][:5]) > 0
    for rule in by_rule.values():
        above = rule["above_threshold"]
        assert 0 < above["steps"] <= rule["curve"][-1]["steps"]
