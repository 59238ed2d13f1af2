"""``cfbci bench simulate --prior``: the per-step cost of a returning user's session
(`calibration_free.prior.ReturningLearner`) against the same session from scratch.

For each seed ``u`` (0..N-1), as ``cfbci bench returning`` halves a dataset file
(`cfbci.bench.returning`): user ``u``'s day-1 session on one half (5 x 5 grid, feedback
frame) is recorded and read back as a prior (`replay.prior.read_prior`); then user ``u``'s
day-2 session (seed ``u + DAY2_SEED_OFFSET``, the other half) runs twice, from scratch and
from the prior, one after the other in this process with one BLAS thread. A step is timed
from one move to the next, as ``cfbci simulate`` runs it: the user's answer, the learner's
update with the new signal, the next move chosen. The start (the learner built, the prior
adopted, the first move) is timed apart. With the prior check's defaults both learners
observe every signal to the session's end unless the prior is abandoned (then the blank
learner alone goes on).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import Progress

from acquisition.labelled import LabelledFeatures
from cfbci.bench.returning import (
    DAY2_SEED_OFFSET,
    DayJob,
    ReturningData,
    as_features,
    data_space,
    decision_of,
    run_day,
)
from cfbci.blas import single_threaded_blas
from cfbci.memory import keep_freed_memory
from cfbci.offline.simulation import SessionConfig, run_session
from replay.prior import NoLabelledSignals, read_prior

#: The two arms, in the order each seed runs them.
ARMS = ("scratch", "prior")


def timed_session(
    seed: int, config: SessionConfig, data: LabelledFeatures
) -> tuple[np.ndarray, float, dict[str, Any] | None]:
    """Run one session and time it.

    Returns
    -------
    step_ms : ndarray, shape (config.steps,)
        Wall time of each step, ms: from one move to the next.
    start_ms : float
        From the call to the first move (learner built, prior adopted), ms.
    decision : dict or None
        The prior check's decision at the end (`cfbci.bench.returning.decision_of`); None
        without a prior.
    """
    marks: list[float] = []
    learners: list[Any] = []

    def mark(session: Any, _: Any) -> None:
        marks.append(time.perf_counter())
        if not learners:
            learners.append(session.learner)

    start = time.perf_counter()
    run_session(seed, config, data, on_move=mark)
    return 1000 * np.diff(marks), 1000 * (marks[0] - start), decision_of(learners[0])


def _spread(ms: np.ndarray) -> dict[str, float]:
    """Median and spread (10th, 90th, 99th percentiles) of step times, ms."""
    p10, median, p90, p99 = np.percentile(ms, [10, 50, 90, 99])
    return {"median": float(median), "p10": float(p10), "p90": float(p90), "p99": float(p99)}


def bench_prior_steps(
    dataset: Path, seeds: int, steps: int, frame: str, grid: int, console: Console
) -> dict[str, Any]:
    """Day-2 sessions of ``steps`` steps from scratch and from a day-1 prior for seeds
    0..``seeds - 1`` (module docstring): each arm's per-step times (median, spread, per
    session) and the ratio of the prior's to scratch's (pooled medians, and per seed).

    Raises
    ------
    ValueError
        On ``seeds`` or ``steps`` below 1, a frame other than feedback (day 1's), or a day 1
        that gives no prior (fewer than two targets declared).
    """
    if seeds < 1 or steps < 1:
        raise ValueError("--seeds and --steps must be at least 1")
    if frame != "feedback":
        raise ValueError(f"--prior: day 1 is simulated in the feedback frame; --frame {frame} "
                         "takes no prior from it")
    keep_freed_memory()
    single_threaded_blas()
    data = ReturningData(dataset)
    config = SessionConfig(steps=steps, grid=grid)
    times: dict[str, list[np.ndarray]] = {arm: [] for arm in ARMS}
    sessions: dict[str, list[dict[str, Any]]] = {arm: [] for arm in ARMS}
    with tempfile.TemporaryDirectory(prefix="cfbci-bench-prior-") as folder, Progress(
        console=console, transient=True
    ) as progress:
        task = progress.add_task("users (day 1, day 2 from scratch and from the prior)",
                                 total=seeds)
        for seed in range(seeds):
            recording = str(Path(folder) / f"day1-{seed}.mcap")
            run_day(DayJob(data, seed, "day1", steps, (recording,)))
            day2 = data.day(seed, 2)
            try:
                prior = read_prior([recording])
            except NoLabelledSignals:
                raise ValueError(
                    f"--prior: seed {seed}'s day-1 session of {steps} steps declared fewer "
                    "than two targets, so it gives no prior; use more --steps"
                ) from None
            prior.check_space(data_space(day2, frame))
            for arm in ARMS:
                arm_config = replace(config, prior=prior if arm == "prior" else None)
                step_ms, start_ms, decision = timed_session(
                    seed + DAY2_SEED_OFFSET, arm_config, as_features(day2))
                times[arm].append(step_ms)
                sessions[arm].append({
                    "seed": seed, "steps": len(step_ms), "start_ms": start_ms,
                    "median_ms": float(np.median(step_ms)), "decision": decision,
                })
            progress.advance(task)
    per_seed = [informed["median_ms"] / blank["median_ms"]
                for blank, informed in zip(sessions["scratch"], sessions["prior"], strict=True)]
    arms = {
        arm: {"step_ms": _spread(np.concatenate(times[arm])),
              "start_ms": float(np.median([s["start_ms"] for s in sessions[arm]])),
              "steps": sum(s["steps"] for s in sessions[arm]), "sessions": sessions[arm]}
        for arm in ARMS
    }
    return {
        "dataset": str(dataset), "frame": frame, "grid": grid, "steps": steps,
        "day2_seed_offset": DAY2_SEED_OFFSET, "arms": arms,
        "ratio": {
            "median": arms["prior"]["step_ms"]["median"] / arms["scratch"]["step_ms"]["median"],
            "per_seed": per_seed, "min": min(per_seed), "max": max(per_seed),
        },
    }


def print_prior_steps(report: dict[str, Any], console: Console) -> None:
    """Each arm's step times, the ratio, and the prior check's decisions."""
    arms = report["arms"]
    console.print(
        f"{len(arms['scratch']['sessions'])} users' day-2 sessions of {report['steps']} steps on "
        f"{report['dataset']} ({report['frame']}, {report['grid']} x {report['grid']}), "
        "from scratch and from day 1's prior:",
        soft_wrap=True,
    )
    for arm in ARMS:
        ms = arms[arm]["step_ms"]
        console.print(
            f"  {arm}: per step median {ms['median']:.2f} ms (p10 {ms['p10']:.2f}, p90 "
            f"{ms['p90']:.2f}, p99 {ms['p99']:.2f}; {arms[arm]['steps']} steps), start "
            f"{arms[arm]['start_ms']:.1f} ms (median)",
            highlight=False,
            soft_wrap=True,
        )
    ratio = report["ratio"]
    outcomes = [s["decision"]["outcome"] for s in arms["prior"]["sessions"]]
    counts = ", ".join(f"{outcome} {outcomes.count(outcome)}" for outcome in sorted(set(outcomes)))
    console.print(
        f"prior / scratch per step: {ratio['median']:.2f}x (pooled medians; per user "
        f"{ratio['min']:.2f}-{ratio['max']:.2f}x); the prior check at the end: {counts}",
        highlight=False,
        soft_wrap=True,
    )
