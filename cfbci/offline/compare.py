"""``cfbci compare``: a one-sided rank test between the sessions of two simulate runs.

Each ``cfbci simulate --json`` file holds one object per session under ``sessions``; a
per-session number (``final_distance`` of the continuous world, ``first_confident_step``
of the grid worlds, ...) of run A is tested against run B with the Mann-Whitney U test
(`scipy.stats.mannwhitneyu`, exact or asymptotic as scipy chooses for the sizes,
ties corrected). ``--alternative less`` tests whether A's values tend to be smaller than
B's (the thesis's "uncertainty + active beats uncertainty + random" on final distances).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import mannwhitneyu

ALTERNATIVES = ("less", "greater", "two-sided")


@dataclass(frozen=True)
class RankTest:
    """The test of one metric between two runs (``a`` against ``b``)."""

    metric: str
    alternative: str
    n_a: int
    n_b: int
    median_a: float
    median_b: float
    u_statistic: float
    p_value: float


def simulate_sessions(path: Path) -> list[Any]:
    """The ``sessions`` list of a simulate JSON file (not empty; its items unchecked).

    Raises
    ------
    ValueError
        Naming the file: not readable JSON, or no ``sessions`` list.
    """
    try:
        report = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: not a readable JSON file ({error})") from None
    sessions = report.get("sessions") if isinstance(report, dict) else None
    if not isinstance(sessions, list) or not sessions:
        raise ValueError(f"{path}: no 'sessions' list (write it with cfbci simulate --json)")
    return sessions


def session_values(path: Path, metric: str) -> np.ndarray:
    """The ``metric`` of every session of a simulate JSON file, shape (n_sessions,).

    Raises
    ------
    ValueError
        Naming the file (and the session): not a simulate JSON, no sessions, a session
        without the metric, or a value that is not a finite number.
    """
    values = []
    for index, session in enumerate(simulate_sessions(path)):
        if not isinstance(session, dict):
            raise ValueError(f"{path}: session {index} is not an object")
        value = session.get(metric)
        if not _is_number(value):
            known = sorted(k for k, v in session.items() if _is_number(v))
            raise ValueError(
                f"{path}: session {index} has no finite number {metric!r} (got {value!r}); "
                f"its numbers are {', '.join(known) or 'none'}"
            )
        values.append(float(value))
    return np.array(values)


def _is_number(value: object) -> bool:
    return (
        isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    )


def rank_test(a: Path, b: Path, metric: str, alternative: str) -> RankTest:
    """The Mann-Whitney test of ``metric`` between the sessions of runs ``a`` and ``b``."""
    if alternative not in ALTERNATIVES:
        raise ValueError(f"alternative must be one of {ALTERNATIVES}; got {alternative!r}")
    first, second = session_values(a, metric), session_values(b, metric)
    result = mannwhitneyu(first, second, alternative=alternative)
    return RankTest(
        metric, alternative, len(first), len(second), float(np.median(first)),
        float(np.median(second)), float(result.statistic), float(result.pvalue),
    )


