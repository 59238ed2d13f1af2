"""How well the confidence means what it says: a reliability (calibration) curve.

Over all steps of many sessions, the best hypothesis's confidence is binned and, per bin,
the fraction of steps at which that hypothesis was the user's target is counted. A
calibrated confidence of 0.9 is right 90 % of the time. Bins are :data:`N_BINS` equal
intervals of [0, 1], ``[k/10, (k+1)/10)``, the last one closed (a confidence of 1.0 and the
default threshold 0.9 fall in the last bin).

Counts are kept per session (:func:`calibration_counts`) so that sessions run apart (Dask
workers, recordings) pool by summing (:func:`pool_counts`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

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

