"""``cfbci sweep``: the cross product of learner settings, datasets and seeds, on Dask.

A *cell* is one combination of the ``--grid`` settings with one dataset; it runs one session
per seed. Every session of every cell is one job of `cfbci.offline.parallel.run_parallel` (the
same job as ``cfbci simulate``'s, so a cell's sessions equal those of ``cfbci simulate
--dataset D --set K=V ...`` with the same seeds). Written to ``--out DIR``:

* ``<dataset>_<key>=<value>_....json`` per cell, in ``cfbci simulate --json``'s format;
* ``summary.json`` (the sweep, its wall time and one row per cell) and ``summary.csv``
  (the rows);
* ``summary.png``: per cell, the distribution of the steps to the first target and of the
  correct targets over the seeds, and the wrong-target rate.
"""

from __future__ import annotations

import csv
import itertools
import json
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rich import box
from rich.console import Console
from rich.table import Table

from acquisition.sources import DataSpec
from cfbci.offline.parallel import Scheduler, run_parallel
from cfbci.offline.simulate import SimulationJob, run_job, simulation_report
from cfbci.offline.simulation import SessionConfig, SessionResult
from session.config import learner_settings

#: ``--datasets`` entry that stands for the synthetic generator (at ``--synthetic-accuracy``).
SYNTHETIC = "synthetic"
#: Resolution of ``summary.png``, dots per inch.
DPI = 150

Grid = tuple[tuple[str, tuple[Any, ...]], ...]


@dataclass(frozen=True)
class SweepCell:
    """One combination of grid settings with one dataset.

    Attributes
    ----------
    name : str
        File-name-safe, unique name (``<dataset>_<key>=<value>_...``).
    dataset : str
        Short name of the dataset (its file stem, or "synthetic").
    settings : dict
        The grid's setting of each grid key in this cell.
    data : DataSpec
    config : SessionConfig
        The sessions' configuration (fixed ``--set`` settings and the cell's).
    """

    name: str
    dataset: str
    settings: dict[str, Any]
    data: DataSpec
    config: SessionConfig


@dataclass
class CellResult:
    """A cell's sessions, in seed order, and its ``simulate``-format report."""

    cell: SweepCell
    results: list[SessionResult]
    report: dict[str, Any] = field(repr=False)

    def first_targets(self) -> np.ndarray:
        """Steps to the first target per session, float, shape (n_seeds,); a session with
        none counts as steps + 1 (as `cfbci.offline.simulation.summarise`)."""
        return np.array([r.first_target_step or r.steps + 1 for r in self.results], float)

    def row(self) -> dict[str, Any]:
        """The cell's summary row (``summary.json``, ``summary.csv``)."""
        q1, q3 = np.percentile(self.first_targets(), [25, 75])
        return {
            "file": f"{self.cell.name}.json",
            "dataset": self.cell.dataset,
            **self.cell.settings,
            "sessions": len(self.results),
            "first_target_q1": float(q1),
            "first_target_q3": float(q3),
            "sessions_without_target": sum(r.first_target_step is None for r in self.results),
            **self.report["summary"],
        }


def parse_grid(spec: str, parse_value: Any) -> Grid:
    """``'key=v1,v2 key2=v3,v4'`` into ``(("key", (v1, v2)), ("key2", (v3, v4)))``.

    Parameters
    ----------
    spec : str
        Space-separated ``KEY=V1,V2,...`` items, one per learner setting.
    parse_value : callable
        ``parse_value(key, raw) -> value`` (the command's ``--set`` value parsing).

    Raises
    ------
    ValueError
        If an item is not ``KEY=V1,...``, a value is empty, or a key repeats.
    """
    grid: list[tuple[str, tuple[Any, ...]]] = []
    for item in spec.split():
        key, sep, raw = item.partition("=")
        values = raw.split(",")
        if not sep or not key or not all(values):
            raise ValueError(f"--grid expects KEY=V1,V2,... items; got {item!r}")
        if key in dict(grid):
            raise ValueError(f"--grid gives {key!r} twice")
        grid.append((key, tuple(parse_value(key, value) for value in values)))
    if not grid:
        raise ValueError("--grid is empty; give KEY=V1,V2,... items")
    return tuple(grid)


def _text(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(value)


def sweep_cells(
    grid: Grid, datasets: list[DataSpec], *, fixed: dict[str, Any], steps: int, side: int,
    frame: str, user_error_rate: float,
) -> list[SweepCell]:
    """Every (dataset, grid setting) cell, datasets outermost, the grid's first key slowest.

    Raises
    ------
    ValueError
        If a grid key is also a fixed (``--set``) setting, two datasets have the same name
        (file stem), or a setting is invalid (unknown key, value out of range), before
        anything runs.
    """
    clash = sorted(set(dict(grid)) & set(fixed))
    if clash:
        raise ValueError(f"{clash} given both in --grid and in --set")
    keys = [key for key, _ in grid]
    labels = [SYNTHETIC if d.path is None else d.path.stem for d in datasets]
    repeated = sorted({label for label in labels if labels.count(label) > 1})
    if repeated:
        raise ValueError(f"--datasets: several datasets are named {repeated}; cells are named "
                         "after their dataset's file stem, so give each a distinct name")
    cells = []
    for data, label in zip(datasets, labels, strict=True):
        for values in itertools.product(*(values for _, values in grid)):
            settings = dict(zip(keys, values, strict=True))
            learner = learner_settings({**fixed, **settings}, frame)
            config = SessionConfig(
                steps=steps, grid=side, learner=learner, user_error_rate=user_error_rate
            )
            name = "_".join([label, *(f"{k}={_text(v)}" for k, v in settings.items())])
            name = re.sub(r"[^A-Za-z0-9_.=-]", "-", name)
            cells.append(SweepCell(name, label, settings, data, config))
    return cells


def run_sweep(
    cells: list[SweepCell], seeds: list[int], out_dir: Path, *, scheduler: Scheduler,
    console: Console,
) -> tuple[list[CellResult], dict[str, Any]]:
    """Run every cell's sessions; write the cell files, ``summary.json``, ``summary.csv``
    and ``summary.png`` into ``out_dir``; return the cells' results and the summary."""
    for data in {cell.data for cell in cells}:  # fail early, here, on a bad dataset
        data.resolve(cells[0].config.learner.frame)
    out_dir.mkdir(parents=True, exist_ok=True)
    work = [SimulationJob(seed, cell.config, cell.data, False) for cell in cells for seed in seeds]
    start = time.perf_counter()
    outcomes = run_parallel(
        run_job, work, scheduler=scheduler, description="sweep sessions", console=console
    )
    wall_time = time.perf_counter() - start
    done = []
    for i, cell in enumerate(cells):
        results = [result for result, _ in outcomes[i * len(seeds):(i + 1) * len(seeds)]]
        report = simulation_report(cell.config, cell.data, seeds, results)
        (out_dir / f"{cell.name}.json").write_text(json.dumps(report, indent=2) + "\n")
        done.append(CellResult(cell, results, report))
    rows = [cell.row() for cell in done]
    summary = {
        "grid": {key: list(values) for key, values in _grid_of(cells).items()},
        "datasets": sorted({cell.data.describe() for cell in cells}),
        "seeds": len(seeds),
        "first_seed": seeds[0],
        "steps": cells[0].config.steps,
        "sessions": len(work),
        "scheduler": scheduler.describe(),
        "wall_time_s": round(wall_time, 3),
        "cells": rows,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    with (out_dir / "summary.csv").open("w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    summary_figure(done).savefig(out_dir / "summary.png", dpi=DPI)
    return done, summary


def _grid_of(cells: list[SweepCell]) -> dict[str, list[Any]]:
    """The grid's values per key, in first-seen order."""
    grid: dict[str, list[Any]] = {}
    for cell in cells:
        for key, value in cell.settings.items():
            if value not in grid.setdefault(key, []):
                grid[key].append(value)
    return grid


def summary_figure(cells: list[CellResult]) -> Any:
    """Three panels over the cells (a matplotlib Figure, built without pyplot).

    (a) steps to the first target per session (box plot and the seeds as dots; a session
    without a target is drawn at steps + 1, above the session length, then dotted), (b)
    correct targets per session, (c) wrong-target rate (wrong / all targets of the cell's
    sessions, %, counts above the bars). Cells of one dataset share a colour.
    """
    from matplotlib.figure import Figure  # only here: importing cfbci.cli stays light
    from matplotlib.ticker import MaxNLocator

    datasets = list(dict.fromkeys(c.cell.dataset for c in cells))
    colours = [f"C{datasets.index(c.cell.dataset) % 10}" for c in cells]
    positions = np.arange(len(cells), dtype=float)
    keys = list(cells[0].cell.settings)
    labels = [" / ".join(_text(v) for v in c.cell.settings.values()) for c in cells]
    figure = Figure(figsize=(max(7.5, 3 * (1.2 + 0.5 * len(cells))), 3.8), layout="constrained")
    axes = figure.subplots(1, 3)
    panels = (
        ("a", "steps to the first target", [c.first_targets() for c in cells]),
        ("b", "correct targets per session",
         [np.array([r.correct_targets for r in c.results], float) for c in cells]),
    )
    rng = np.random.default_rng(0)  # fixed horizontal jitter of the dots
    for ax, (letter, ylabel, values) in zip(axes, panels, strict=False):
        boxes = ax.boxplot(values, positions=positions, widths=0.55, showfliers=False,
                           patch_artist=True, medianprops={"color": "black"})
        for patch, colour in zip(boxes["boxes"], colours, strict=True):
            patch.set(facecolor=colour, alpha=0.35, edgecolor=colour)
        for x, ys, colour in zip(positions, values, colours, strict=True):
            ax.plot(x + rng.uniform(-0.15, 0.15, len(ys)), ys, ".", color=colour, ms=4)
        ax.set_ylabel(ylabel)
        ax.set_title(f"({letter})", loc="left", fontweight="bold")
    steps = cells[0].results[0].steps
    if any(r.first_target_step is None for c in cells for r in c.results):
        axes[0].axhline(steps, color="grey", ls=":", lw=1,
                        label="session length\n(above: no target)")
        axes[0].legend(loc="best", fontsize=7, frameon=False)
    axes[1].yaxis.set_major_locator(MaxNLocator(integer=True))
    rates = [100 * c.report["summary"]["wrong_target_rate"] for c in cells]
    axes[2].bar(positions, rates, width=0.55, color=colours, alpha=0.7)
    for x, rate, c in zip(positions, rates, cells, strict=True):
        wrong = sum(r.wrong_targets for r in c.results)
        total = wrong + sum(r.correct_targets for r in c.results)
        axes[2].text(x, rate, f"{wrong}/{total}", ha="center", va="bottom", fontsize=7)
    axes[2].set_ylabel("wrong-target rate (%)")
    axes[2].set_ylim(0, max(5.0, 1.25 * max(rates)))
    axes[2].set_title("(c)", loc="left", fontweight="bold")
    for ax in axes:
        ax.set_xticks(positions, labels, fontsize=8, rotation=30 if len(cells) > 6 else 0)
        ax.set_xlabel(" / ".join(keys), fontsize=8)
        ax.set_xlim(-0.6, len(cells) - 0.4)
        ax.grid(axis="y", alpha=0.3)
    if len(datasets) > 1:
        handles = [axes[2].bar([0], [0], color=f"C{i % 10}", alpha=0.7)[0]
                   for i in range(len(datasets))]
        figure.legend(handles, datasets, loc="outside upper right", fontsize=8)
    figure.suptitle(f"cfbci sweep: {len(cells[0].results)} seeds per cell, {steps} steps")
    return figure


def print_summary(cells: list[CellResult], summary: dict[str, Any], console: Console) -> None:
    """One row per cell: median (IQR) first target, mean correct and wrong, wrong rate."""
    keys = list(summary["grid"])
    table = Table(box=box.SIMPLE_HEAD, title=f"cfbci sweep: {summary['seeds']} seeds per cell",
                  caption="first target: median (quartiles) over the seeds, steps; correct, "
                  "wrong: mean targets per session; wrong rate: wrong / all targets",
                  caption_justify="left")
    table.add_column("dataset")
    for key in keys:
        table.add_column(key, justify="right", min_width=len(key))
    for name in ("first target (IQR)", "correct", "wrong", "wrong rate"):
        table.add_column(name, justify="right", no_wrap=True)
    for cell in cells:
        row = cell.row()
        table.add_row(
            row["dataset"], *(_text(row[k]) for k in keys),
            f"{row['median_first_target_step']:g} "
            f"({row['first_target_q1']:g}-{row['first_target_q3']:g})",
            f"{row['mean_correct_targets']:.2f}", f"{row['mean_wrong_targets']:.2f}",
            f"{100 * row['wrong_target_rate']:.1f} %",
        )
    console.print(table)
    console.print(
        f"{summary['sessions']} sessions in {summary['wall_time_s']:.1f} s wall time "
        f"({summary['scheduler']})"
    )


