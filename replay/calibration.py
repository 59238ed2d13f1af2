"""How well the confidence means what it says: a reliability (calibration) curve.

Over all steps of many sessions, the best hypothesis's confidence is binned and, per bin,
the fraction of steps at which that hypothesis was the user's target is counted. A
calibrated confidence of 0.8 is right 80 % of the time. Bins are `N_BINS` equal
intervals of [0, 1], ``[k/10, (k+1)/10)``, the last one closed (a confidence of 1.0 falls
in the last bin).

Counts are kept per session (`calibration_counts`) so that sessions run apart (Dask
workers, recordings) pool by summing (`pool_counts`). A learner may decide by more
than one rule in a session (the pairwise W against ``beta``, the normalised likelihood
against ``calibrated_beta`` while its evidence is calibrated: see
`calibration_free.config.LearnerConfig`): `counts_by_rule` keeps one set of
counts per rule and threshold, so that each threshold can be read against its own rule's
curve.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

#: Equal-width confidence bins over [0, 1].
N_BINS = 10
#: Rounding tolerated outside [0, 1] (a confidence computed in floating point).
_ROUNDING = 1e-9


def bin_of(confidence: float) -> int:
    """The bin index of a confidence in [0, 1] (the last bin is closed)."""
    return min(int(confidence * N_BINS), N_BINS - 1)


def calibration_counts(
    best_confidence: Sequence[float], best_is_target: Sequence[bool]
) -> list[list[int]]:
    """Per bin ``[steps, steps where the best hypothesis was the user's target]``.

    ``best_confidence``: per step, the best hypothesis's confidence in [0, 1];
    ``best_is_target``: per step, whether that hypothesis was the user's target.
    """
    if len(best_confidence) != len(best_is_target):
        raise ValueError(
            f"{len(best_confidence)} confidences but {len(best_is_target)} outcomes"
        )
    counts = [[0, 0] for _ in range(N_BINS)]
    for confidence, right in zip(best_confidence, best_is_target, strict=True):
        if not -_ROUNDING <= confidence <= 1.0 + _ROUNDING:
            raise ValueError(f"a confidence must be in [0, 1]; got {confidence}")
        bin_ = counts[bin_of(min(max(confidence, 0.0), 1.0))]
        bin_[0] += 1
        bin_[1] += bool(right)
    return counts


@dataclass(frozen=True)
class RuleCounts:
    """The counts (`calibration_counts`) of the steps decided by one rule: the
    confidence rule (a key of `calibration_free.likelihood.CONFIDENCES`) compared
    with ``threshold``; and ``above_threshold``, ``[steps, right]`` of the steps whose best
    task's confidence exceeded the threshold (the confident ones)."""

    rule: str
    threshold: float
    counts: list[list[int]]
    above_threshold: list[int]


def counts_by_rule(
    best_confidence: Sequence[float],
    best_is_target: Sequence[bool],
    rules: Sequence[tuple[str, float]],
) -> list[RuleCounts]:
    """`calibration_counts` of each rule's steps; ``rules`` holds the ``(rule,
    threshold)`` in force at each step. Rules in the order they first occur."""
    if len(rules) != len(best_confidence):
        raise ValueError(f"{len(best_confidence)} confidences but {len(rules)} rules")
    steps: dict[tuple[str, float], list[int]] = {}
    for i, rule in enumerate(rules):
        steps.setdefault(rule, []).append(i)
    return [
        RuleCounts(
            rule, threshold,
            calibration_counts([best_confidence[i] for i in chosen],
                               [best_is_target[i] for i in chosen]),
            [sum(best_confidence[i] > threshold for i in chosen),
             sum(best_confidence[i] > threshold and best_is_target[i] for i in chosen)],
        )
        for (rule, threshold), chosen in steps.items()
    ]


def pool_counts_by_rule(per_session: Iterable[Sequence[RuleCounts]]) -> list[RuleCounts]:
    """The per-rule counts of several sessions, each rule's summed (in the order the
    rules first occur)."""
    by_rule: dict[tuple[str, float], list[RuleCounts]] = {}
    for session in per_session:
        for counts in session:
            by_rule.setdefault((counts.rule, counts.threshold), []).append(counts)
    return [
        RuleCounts(
            rule, threshold, pool_counts(c.counts for c in counts),
            np.sum([c.above_threshold for c in counts], axis=0).tolist(),
        )
        for (rule, threshold), counts in by_rule.items()
    ]


def pool_counts(per_session: Iterable[Sequence[Sequence[int]]]) -> list[list[int]]:
    """The bin counts of several sessions summed."""
    total = np.zeros((N_BINS, 2), dtype=int)
    for counts in per_session:
        if len(counts):  # a session without counts (none recorded) adds nothing
            total += np.asarray(counts, dtype=int).reshape(N_BINS, 2)
    return total.tolist()


@dataclass(frozen=True)
class CalibrationBin:
    """One bin of the curve: ``[low, high)`` (the last closed), its steps, and the
    fraction of them where the best hypothesis was the user's target (None if empty)."""

    low: float
    high: float
    steps: int
    fraction_right: float | None


def calibration_curve(counts: Sequence[Sequence[int]]) -> list[CalibrationBin]:
    """The curve of pooled bin counts."""
    return [
        CalibrationBin(k / N_BINS, (k + 1) / N_BINS, int(n), right / n if n else None)
        for k, (n, right) in enumerate(counts)
    ]


def rule_summary(counts: RuleCounts) -> dict[str, Any]:
    """A rule's pooled counts as JSON: ``rule``, ``threshold``, ``curve`` (the
    `CalibrationBin` fields per bin) and ``above_threshold`` (``steps``, ``right``)."""
    steps, right = counts.above_threshold
    return {
        "rule": counts.rule,
        "threshold": counts.threshold,
        "curve": [asdict(b) for b in calibration_curve(counts.counts)],
        "above_threshold": {"steps": steps, "right": right},
    }


@dataclass(frozen=True)
class CalibrationPanel:
    """One curve of a calibration figure: all steps pooled (``rule`` None), or the steps one
    rule decided, with its threshold and ``above_threshold`` (``[steps, right]`` of those
    whose best task's confidence exceeded it). ``threshold`` without ``rule``: the one
    threshold of every pooled step (drawn, not counted)."""

    curve: list[CalibrationBin]
    rule: str | None = None
    threshold: float | None = None
    above_threshold: list[int] | None = None

    @property
    def steps(self) -> int:
        """The steps the panel counts."""
        return sum(b.steps for b in self.curve)

    @property
    def title(self) -> str:
        """What the panel counts, e.g. ``steps decided by the pairwise rule (threshold
        0.93): 255`` or ``all steps: 400``."""
        if self.rule is None:
            return f"all steps: {self.steps}"
        return f"steps decided by the {self.rule} rule (threshold {self.threshold:g}): {self.steps}"

    @classmethod
    def of_rule_summary(cls, summary: dict[str, Any]) -> CalibrationPanel:
        """The panel of one rule's `rule_summary`."""
        above = summary["above_threshold"]
        return cls([CalibrationBin(**b) for b in summary["curve"]], summary["rule"],
                   summary["threshold"], [above["steps"], above["right"]])
