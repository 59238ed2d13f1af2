"""``cfbci compare``: a one-sided rank test between the sessions of two simulate runs.

Each ``cfbci simulate --json`` file holds one object per session under ``sessions``; a
per-session number (``final_distance`` of the continuous world, ``first_confident_step``
of the grid worlds, ...) of run A is tested against run B with the Mann-Whitney U test
(:func:`scipy.stats.mannwhitneyu`, exact or asymptotic as scipy chooses for the sizes,
ties corrected). ``--alternative less`` tests whether A's values tend to be smaller than
B's (the thesis's "uncertainty + active beats uncertainty + random" on final distances).
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
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


def run_compare(args: argparse.Namespace, console: Console) -> int:
    """``cfbci compare``: print the test (and write it as JSON if asked)."""
    test = rank_test(args.a, args.b, args.metric, args.alternative)
    side = {"less": "one-sided, A < B", "greater": "one-sided, A > B"}.get(
        test.alternative, "two-sided"
    )
    console.print(
        f"{test.metric}: A median {test.median_a:.4g} (n = {test.n_a}), B median "
        f"{test.median_b:.4g} (n = {test.n_b}); Mann-Whitney U = {test.u_statistic:.1f}, "
        f"{side}: p = {test.p_value:.3g}", soft_wrap=True,
    )
    if args.json:
        args.json.write_text(json.dumps(asdict(test), indent=2) + "\n")
    return 0


def add_compare_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci compare``."""
    p = commands.add_parser(
        "compare",
        help="a Mann-Whitney rank test of a per-session number between two simulate runs",
        description="Tests whether the sessions of run A tend to have smaller (--alternative "
        "less), larger (greater) or different (two-sided) values of --metric than those of "
        "run B; both are cfbci simulate --json files.",
    )
    p.add_argument("a", type=Path, help="simulate JSON of run A")
    p.add_argument("b", type=Path, help="simulate JSON of run B")
    p.add_argument("--metric", required=True, help="a per-session number, e.g. final_distance")
    p.add_argument("--alternative", choices=ALTERNATIVES, default="less")
    p.add_argument("--json", type=Path, help="write the test as JSON")
    p.set_defaults(run=run_compare)
