"""``cfbci bench update``: the learner's per-step cost against a naive scikit-learn reference.

A step is timed from a new signal to the next action chosen: the likelihood update with
every task's cross-validated confusion, the decoders refitted for the grown history, the
confidence, and the default ``uncertainty`` planner. Histories are built by running the
learner (default settings) on synthetic data with the simulated user; each history size
is measured over the steps that follow it (the history grows by one per measured step).

The naive reference, for the smallest grid only (T = 25 by default), does per task
what a straightforward implementation would: ``LinearDiscriminantAnalysis(
solver="lsqr", shrinkage=<default>, priors=<equal>)`` refitted on the history for the
new signal's probabilities, plus ``cross_val_predict(..., cv=KFold(10),
method="predict_proba")`` for its confusion matrix.
It leaves out planning, so the speed-up it gives is a lower bound.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from rich.console import Console
from rich.progress import Progress
from rich.table import Table
from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
from sklearn.model_selection import KFold, cross_val_predict

from acquisition.sources import synthetic_features
from acquisition.user import SimulatedUser
from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.session import session_streams
from calibration_free.world import GridWorld


@dataclass(frozen=True)
class BenchRow:
    """Figures for one (tasks, history size)."""

    tasks: int
    history: int
    median_ms: float
    p99_ms: float
    naive_median_ms: float | None
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


def bench_grid(
    grid: int,
    histories: tuple[int, ...],
    *,
    measured_steps: int,
    naive_repeats: int,
    seed: int,
    with_naive: bool,
    progress: Progress,
) -> list[BenchRow]:
    """Run the learner on one grid and time it at each history size (and the naive
    reference too, if ``with_naive``)."""
    world = GridWorld(grid)
    config = LearnerConfig()
    data_rng, user_rng, learner_rng = session_streams(seed)
    data = synthetic_features(0.78, data_rng)
    signals = data.features.astype(np.float32)
    user = SimulatedUser(world, config.frame, data.labels, user_rng)
    learner = CalibrationFreeLearner(world, config, learner_rng)
    total = max(histories) + measured_steps
    task = progress.add_task(f"T = {world.n_tasks}", total=total)
    state = user.start_state
    proposal = learner.propose(state)
    timings: dict[int, list[float]] = {h: [] for h in histories}
    naive: dict[int, list[float]] = {h: [] for h in histories}
    for n_seen in range(total):
        index, _ = user.answer(state, proposal.action)
        if proposal.declares_target:
            user.new_target()
        measuring = [h for h in histories if h <= n_seen < h + measured_steps]
        if measuring and with_naive and len(naive[measuring[0]]) < naive_repeats:
            naive[measuring[0]].append(_time_naive(learner, signals[index], config.shrinkage))
        start = time.perf_counter()
        learner.observe(state, proposal.action, signals[index])
        next_state = world.step(state, proposal.action)
        proposal = learner.propose(next_state)
        elapsed = time.perf_counter() - start
        for h in measuring:
            timings[h].append(elapsed)
        state = next_state
        progress.advance(task)
    rows = []
    for h in histories:
        ms = 1000 * np.asarray(timings[h])
        naive_ms = float(np.median(naive[h]) * 1000) if naive[h] else None
        median = float(np.median(ms))
        rows.append(
            BenchRow(
                world.n_tasks, h, median, float(np.percentile(ms, 99)), naive_ms,
                naive_ms / median if naive_ms else None,
            )
        )
    return rows


def _time_naive(learner: CalibrationFreeLearner, signal: np.ndarray, shrinkage: float) -> float:
    history = learner.history
    labels = np.argmax(history.label_weights, axis=-1)
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
    """All rows, with a progress bar."""
    with Progress(console=console, transient=True) as progress:
        rows = [
            row
            for grid in grids
            for row in bench_grid(
                grid, histories, measured_steps=measured_steps,
                naive_repeats=naive_repeats, seed=seed, with_naive=grid == min(grids),
                progress=progress,
            )
        ]
    return rows


def print_rows(rows: list[BenchRow], console: Console) -> None:
    table = Table(title="cfbci bench update - per-step cost (new signal -> next action)")
    for column in ("tasks", "history", "median ms", "p99 ms", "naive median ms", "speed-up"):
        table.add_column(column, justify="right")
    for row in rows:
        table.add_row(
            str(row.tasks), str(row.history), f"{row.median_ms:.2f}", f"{row.p99_ms:.2f}",
            "-" if row.naive_median_ms is None else f"{row.naive_median_ms:.1f}",
            "-" if row.speedup is None else f"{row.speedup:.0f}x",
        )
    console.print(table)
