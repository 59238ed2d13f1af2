"""``cfbci bench update`` and ``cfbci bench simulate``: the learner's cost.

``bench update``: a step is timed from a new signal to the next action chosen: the
likelihood update with every task's cross-validated confusion, the decoders refitted for
the grown history, the confidence, and the default ``uncertainty`` planner. Histories are
built by running the learner (default settings) on synthetic data with the simulated
user; each history size is measured over the steps that follow it (the history grows by
one per measured step). Every grid runs in a fresh process, so that its peak resident
memory (interpreter and libraries included, the world's tables too) is its own.

The naive reference does per task what a straightforward implementation would:
``LinearDiscriminantAnalysis(solver="lsqr", shrinkage=0.5, priors=<equal>)``
refitted on the history for the new signal's probabilities, plus
``cross_val_predict(..., cv=KFold(10), method="predict_proba")`` for its confusion
matrix. It stays this whatever the project's own decoder is, so that speed-ups compare
across versions. It leaves out planning, so the speed-up it gives is a lower bound. Its
cost is exactly linear in the number of tasks (the same work per task): it is measured on
at most ``NAIVE_TASKS`` tasks (all of them at T = 25, an evenly spaced slice of the tasks
beyond) and, on larger grids, extrapolated linearly to T.

``bench simulate``: the wall time of whole offline sessions (``cfbci simulate``'s
`run_session`) in one process, process start and dataset loading
excluded, and how much faster than real time they run at ``SECONDS_PER_ACTION`` per
device action.
"""

from __future__ import annotations

import resource
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import Progress
from rich.table import Table
from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
from sklearn.model_selection import KFold, cross_val_predict

from acquisition.loaders import load_labelled
from acquisition.sources import synthetic_features
from acquisition.user import SimulatedUser
from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.streams import session_streams
from calibration_free.world import GridWorld
from cfbci.blas import single_threaded_blas
from cfbci.memory import keep_freed_memory
from cfbci.offline.simulation import SessionConfig, run_session
from decoding.lda import DEFAULT_SHRINKAGE
from session.tasks import TaskSession

#: Tasks the naive reference is measured on; beyond, it is extrapolated linearly in T.
NAIVE_TASKS = 25
#: The protocol's pace: one device action (and one epoch) every 3 s.
SECONDS_PER_ACTION = 3.0


@dataclass(frozen=True)
class BenchRow:
    """Figures for one (tasks, history size).

    ``peak_memory_mb``: the grid's process peak resident memory up to the end of this
    row's measurement. ``naive_median_ms``: the naive reference for all ``tasks``,
    measured on ``naive_measured_tasks`` of them (extrapolated when fewer than ``tasks``).
    """

    tasks: int
    history: int
    median_ms: float
    p99_ms: float
    peak_memory_mb: float
    naive_median_ms: float | None
    naive_measured_tasks: int | None
    speedup: float | None


def naive_lda(n_classes: int, shrinkage: float) -> LinearDiscriminantAnalysis:
    """scikit-learn's shrinkage LDA with equal priors."""
    return LinearDiscriminantAnalysis(
        solver="lsqr", shrinkage=shrinkage, priors=np.full(n_classes, 1 / n_classes)
    )


def naive_step(
    history: np.ndarray, labels: np.ndarray, signal: np.ndarray, shrinkage: float
) -> None:
    """The naive per-step work for every task: a refit plus a 10-fold cross_val_predict.

    ``history`` (n, d), ``labels`` (n_tasks, n) hard labels, ``signal`` (d,).
    """
    n_classes = int(labels.max()) + 1
    for task_labels in labels:
        naive_lda(n_classes, shrinkage).fit(history, task_labels).predict_proba(signal[None])
        cross_val_predict(
            naive_lda(n_classes, shrinkage), history, task_labels, cv=KFold(10),
            method="predict_proba",
        )


def peak_memory_mb() -> float:
    """This process's peak resident memory so far, in MB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 2**10  # bytes / KiB


def naive_slice(n_tasks: int) -> np.ndarray:
    """The tasks the naive reference is measured on: all, or ``NAIVE_TASKS`` evenly spaced."""
    return np.unique(np.linspace(0, n_tasks - 1, min(n_tasks, NAIVE_TASKS)).round().astype(int))


def bench_grid(
    grid: int,
    histories: tuple[int, ...],
    measured_steps: int,
    naive_repeats: int,
    seed: int,
) -> list[BenchRow]:
    """Run the learner on one grid and time it, and the naive reference, at each history
    size (in a worker process: see the module docstring)."""
    keep_freed_memory()
    single_threaded_blas()
    world = GridWorld(grid)
    config = LearnerConfig()
    data_rng, user_rng, learner_rng = session_streams(seed)
    data = synthetic_features(0.78, data_rng)
    signals = data.features.astype(np.float32)
    user = SimulatedUser(world, config.frame, data.labels, user_rng)
    learner = CalibrationFreeLearner(world, config, learner_rng)
    tasks = naive_slice(world.n_tasks)
    signals_seen = max(histories) + measured_steps
    # A step is a signal observed and the next action chosen: one more step than signals.
    session = TaskSession(world, learner, seed, signals_seen + 1)
    move = session.start().move
    timings: dict[int, list[float]] = {h: [] for h in histories}
    naive: dict[int, list[float]] = {h: [] for h in histories}
    memory: dict[int, float] = {}
    for n_seen in range(signals_seen):
        assert move is not None
        index, _ = user.answer(session.agent, session.action)
        if move["target_reached"]:
            user.new_target()
        measuring = [h for h in histories if h <= n_seen < h + measured_steps]
        if measuring and len(naive[measuring[0]]) < naive_repeats:
            naive[measuring[0]].append(
                _time_naive(learner, tasks, signals[index], DEFAULT_SHRINKAGE)
            )
        start = time.perf_counter()
        move = session.observe(signals[index]).move
        elapsed = time.perf_counter() - start
        for h in measuring:
            timings[h].append(elapsed)
            if n_seen == h + measured_steps - 1:
                memory[h] = peak_memory_mb()
    rows = []
    for h in histories:
        ms = 1000 * np.asarray(timings[h])
        median = float(np.median(ms))
        naive_ms = float(np.median(naive[h]) * 1000 * world.n_tasks / len(tasks))
        rows.append(
            BenchRow(
                world.n_tasks, h, median, float(np.percentile(ms, 99)), memory[h],
                naive_ms, len(tasks), naive_ms / median,
            )
        )
    return rows


def _time_naive(
    learner: CalibrationFreeLearner, tasks: np.ndarray, signal: np.ndarray, shrinkage: float
) -> float:
    history = learner.history
    labels = np.stack([np.argmax(history.task_label_weights(t), axis=-1) for t in tasks])
    start = time.perf_counter()
    naive_step(history.signals, labels, signal.astype(np.float64), shrinkage)
    return time.perf_counter() - start


def bench_update(
    grids: tuple[int, ...],
    histories: tuple[int, ...],
    *,
    measured_steps: int,
    naive_repeats: int,
    seed: int,
    console: Console,
) -> list[BenchRow]:
    """All rows, one fresh worker process per grid, with a progress bar."""
    if min(histories) < 1 or measured_steps < 1 or naive_repeats < 1:
        raise ValueError("--histories, --measured-steps and --naive-repeats must be >= 1")
    rows: list[BenchRow] = []
    context = get_context("spawn")
    with Progress(console=console, transient=True) as progress:
        task = progress.add_task("grids", total=len(grids))
        for grid in grids:
            progress.update(task, description=f"{grid} x {grid} grid")
            with ProcessPoolExecutor(1, mp_context=context) as pool:
                rows += pool.submit(
                    bench_grid, grid, histories, measured_steps, naive_repeats, seed
                ).result()
            progress.advance(task)
    return rows


def print_rows(rows: list[BenchRow], console: Console) -> None:
    """The rows as a table, with how the naive figures were obtained."""
    table = Table(title="cfbci bench update - per-step cost (new signal -> next action)")
    for column in (
        "tasks", "history", "median ms", "p99 ms", "peak MB", "naive median ms", "speed-up"
    ):
        table.add_column(column, justify="right")
    for row in rows:
        extrapolated = row.naive_measured_tasks != row.tasks
        naive = f"{row.naive_median_ms:.1f}" + (" *" if extrapolated else "")
        table.add_row(
            str(row.tasks), str(row.history), f"{row.median_ms:.2f}", f"{row.p99_ms:.2f}",
            f"{row.peak_memory_mb:.0f}", naive, f"{row.speedup:.0f}x",
        )
    console.print(table)
    console.print(
        f"naive: per task, sklearn LDA refit + 10-fold cross_val_predict, measured on "
        f"{NAIVE_TASKS} tasks; * = extrapolated linearly to T from that slice (its cost is "
        f"exactly linear in T). Planning is not in it: the speed-up is a lower bound. "
        f"peak MB: the grid's process peak resident memory (interpreter and libraries "
        f"included). One BLAS thread (cfbci/blas.py)."
    )


def bench_simulate(
    dataset: Path, seeds: int, steps: int, frame: str, grid: int, console: Console
) -> dict[str, Any]:
    """Per-session wall time of ``seeds`` sessions (seeds 0..) in this process."""
    if seeds < 1 or steps < 1:
        raise ValueError("--seeds and --steps must be at least 1")
    keep_freed_memory()
    single_threaded_blas()
    data = load_labelled(dataset, frame=frame)
    config = SessionConfig(steps=steps, grid=grid, learner=LearnerConfig(frame=frame))
    sessions = []
    with Progress(console=console, transient=True) as progress:
        task = progress.add_task("sessions", total=seeds)
        for seed in range(seeds):
            start = time.perf_counter()
            run_session(seed, config, data)
            wall = time.perf_counter() - start
            sessions.append(
                {"seed": seed, "wall_s": wall,
                 "realtime_factor": steps * SECONDS_PER_ACTION / wall}
            )
            progress.advance(task)
    walls = [s["wall_s"] for s in sessions]
    return {
        "dataset": str(dataset), "frame": frame, "grid": grid, "steps": steps,
        "seconds_per_action": SECONDS_PER_ACTION,
        "realtime_factor": float(np.median([s["realtime_factor"] for s in sessions])),
        "wall_s": {"median": float(np.median(walls)), "min": min(walls), "max": max(walls)},
        "sessions": sessions,
    }


