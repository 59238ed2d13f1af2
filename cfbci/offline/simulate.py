"""``cfbci simulate``: many offline sessions, on Dask (`cfbci.offline.parallel`),
summarised."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from acquisition.labelled import LabelledFeatures
from acquisition.sources import DataFactory, DataSpec
from calibration_free.streams import StepRecord
from cfbci.offline.parallel import Scheduler, run_parallel
from cfbci.offline.simulation import SessionConfig, SessionResult, run_session, summarise
from replay.calibration import bin_of


@dataclass(frozen=True)
class SimulationJob:
    """One session to run in a worker."""

    seed: int
    config: SessionConfig
    data: DataSpec
    keep_trace: bool


@lru_cache(maxsize=4)
def _resolved(data: DataSpec, frame: str) -> LabelledFeatures | DataFactory:
    """The dataset of a job, loaded (or its generator built) once per worker process."""
    return data.resolve(frame)


def run_job(job: SimulationJob) -> tuple[SessionResult, list[StepRecord]]:
    """Run one session (a job of `cfbci.offline.parallel.run_parallel`); its trace if
    asked."""
    trace: list[StepRecord] = []
    result = run_session(
        job.seed,
        job.config,
        _resolved(job.data, job.config.learner.frame),
        trace.append if job.keep_trace else None,
    )
    return result, trace


def simulate(
    config: SessionConfig,
    data: DataSpec,
    seeds: list[int],
    *,
    scheduler: Scheduler,
    console: Console,
    trace_path: Path | None = None,
) -> dict[str, Any]:
    """Run the sessions where ``scheduler`` says; write the trace; return the JSON report."""
    data.resolve(config.learner.frame)  # fail early, in this process, on a bad dataset
    work = [SimulationJob(seed, config, data, trace_path is not None) for seed in seeds]
    outcomes = run_parallel(
        run_job, work, scheduler=scheduler, description="sessions", console=console
    )
    if trace_path is not None:
        with trace_path.open("w") as stream:
            for _, trace in outcomes:
                for record in trace:
                    stream.write(json.dumps(asdict(record)) + "\n")
    return simulation_report(config, data, seeds, [result for result, _ in outcomes])


def simulation_report(
    config: SessionConfig, data: DataSpec, seeds: list[int], results: list[SessionResult]
) -> dict[str, Any]:
    """The JSON report of sessions: ``{"config": ..., "sessions": [...], "summary": ...}``."""
    return {
        "config": {
            "dataset": data.describe(),
            "synthetic_accuracy": data.synthetic_accuracy if data.path is None else None,
            "seeds": len(seeds),
            "first_seed": seeds[0],
            **config.to_dict(),
        },
        "sessions": [asdict(r) for r in results],
        "summary": summarise(results),
    }


def print_report(report: dict[str, Any], console: Console) -> None:
    """A readable table of the sessions and the summary."""
    table = Table(title=f"cfbci simulate - {report['config']['dataset']}")
    columns = ("seed", "first confident", "first target", "first correct", "correct", "wrong")
    for column in columns:
        table.add_column(column, justify="right")
    for session in report["sessions"]:
        table.add_row(
            str(session["seed"]),
            str(session["first_confident_step"] or "-"),
            str(session["first_target_step"] or "-"),
            str(session["first_correct_target_step"] or "-"),
            str(session["correct_targets"]),
            str(session["wrong_targets"]),
        )
    console.print(table)
    summary = report["summary"]
    console.print(
        f"median first target: {summary['median_first_target_step']:g} steps   "
        f"mean correct targets: {summary['mean_correct_targets']:.2f}   "
        f"mean wrong targets: {summary['mean_wrong_targets']:.2f}   "
        f"wrong-target rate: {100 * summary['wrong_target_rate']:.1f} %\n"
        f"sessions with a target: {summary['sessions_with_a_target']}/{len(report['sessions'])}"
        f"   wrong first targets: {100 * summary['wrong_first_target_fraction']:.1f} %   "
        f"median first confident step: {summary['median_first_confident_step']:g}"
    )
    likelihood = summary["mean_user_task_likelihood"]
    shown = [f"{likelihood[s]:.2f} @{s}" for s in list(likelihood)[4::5]]  # every 50 steps
    if shown:
        console.print(f"mean normalised likelihood of the user's task: {', '.join(shown)}")
    curve = summary["confidence_calibration"]
    bins = [b for b in curve if b["steps"]]
    for rule in summary["confidence_calibration_by_rule"]:
        in_bin, above = rule["curve"][bin_of(rule["threshold"])], rule["above_threshold"]
        if in_bin["steps"]:
            console.print(
                f"{rule['rule']} confidence, threshold {rule['threshold']:g}: the best task "
                f"was the user's target at {in_bin['fraction_right']:.1%} of the "
                f"{in_bin['steps']} steps in the threshold's bin"
                + (f", {above['right'] / above['steps']:.1%} of the {above['steps']} above it"
                   if above["steps"] else ""))
    console.print("confidence calibration (best task's confidence: fraction of steps it was "
                  "the user's target, steps): " + "; ".join(
                      f"{b['low']:.1f}-{b['high']:.1f}: {b['fraction_right']:.2f} ({b['steps']})"
                      for b in bins))
