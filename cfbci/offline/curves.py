"""``cfbci curves``: the mean curve of a per-session series of several simulate runs.

A plane-world run's sessions each hold a series: the puddle world's ``taught_likelihood``
(after every update, at the steps of ``update_steps``), the continuous world's
``distance_every_10`` (the best particle's distance to the goal at steps 10, 20, ...).
Each run (one ``cfbci simulate --json`` file, labelled by its name without ``.json``) is
drawn as the mean over its sessions with a band of one standard error of the mean, or
the median with its interquartile band (``--statistic median``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from cfbci.offline.compare import simulate_sessions

#: The step of each element of a series, by series: a session field, or every 10th step.
STEP_AXES = {"taught_likelihood": "update_steps", "distance_every_10": None}
STATISTICS = ("mean", "median")


def run_series(path: Path, metric: str) -> tuple[np.ndarray, np.ndarray]:
    """The steps (n_points,) and every session's series (n_sessions, n_points) of a run.

    Raises
    ------
    ValueError
        Naming the file and session: not a simulate JSON, a session without the series,
        series of different lengths, a value that is not a finite number.
    """
    if metric not in STEP_AXES:
        raise ValueError(f"metric must be one of {sorted(STEP_AXES)}; got {metric!r}")
    sessions = simulate_sessions(path)
    rows = [_series(path, index, session, metric) for index, session in enumerate(sessions)]
    if len({len(row) for row in rows}) != 1:
        raise ValueError(f"{path}: the sessions' {metric!r} series differ in length")
    axis = STEP_AXES[metric]
    n_points = len(rows[0])
    steps = (
        np.asarray(sessions[0].get(axis, []), dtype=float) if axis
        else 10.0 * np.arange(1, n_points + 1)
    )
    if len(steps) != n_points:
        raise ValueError(f"{path}: {axis!r} and {metric!r} differ in length")
    return steps, np.array(rows)


def _series(path: Path, index: int, session: Any, metric: str) -> list[float]:
    values = session.get(metric) if isinstance(session, dict) else None
    if not isinstance(values, list) or not values or not all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        for v in values
    ):
        raise ValueError(f"{path}: session {index} has no series of finite numbers {metric!r}")
    return [float(v) for v in values]


def plot_curves(
    runs: dict[str, tuple[np.ndarray, np.ndarray]],
    metric: str,
    statistic: str,
    out: Path,
    log_y: bool = False,
) -> list[dict[str, Any]]:
    """Draw every run's curve and band (``log_y``: on a log scale); returns the rows that
    were drawn."""
    from matplotlib.figure import Figure  # only here: importing cfbci.cli stays light

    if statistic not in STATISTICS:
        raise ValueError(f"statistic must be one of {STATISTICS}; got {statistic!r}")
    figure = Figure(figsize=(6.4, 4.0), layout="constrained")
    axes = figure.add_subplot()
    rows = []
    for label, (steps, series) in runs.items():
        if statistic == "mean":
            centre = series.mean(axis=0)
            spread = series.std(axis=0, ddof=1) / np.sqrt(len(series)) if len(series) > 1 else 0
            low, high = centre - spread, centre + spread
        else:
            low, centre, high = np.percentile(series, [25, 50, 75], axis=0)
        axes.plot(steps, centre, label=f"{label} (n = {len(series)})")
        axes.fill_between(steps, low, high, alpha=0.2)
        rows.append({"run": label, "steps": steps.tolist(), statistic: centre.tolist()})
    band = "one standard error" if statistic == "mean" else "interquartile range"
    axes.set(xlabel="step", ylabel=f"{metric}\n({statistic}; band: {band})")
    if log_y:
        axes.set_yscale("log")
    axes.grid(alpha=0.3, which="both")
    axes.legend(fontsize="small")
    figure.savefig(out, dpi=150)
    return rows


