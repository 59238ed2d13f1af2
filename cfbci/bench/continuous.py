"""The cost of one continuous-goal step (issue 10): resampling, probe choice, relabelling,
the sampled-classifier confidence and the uncertainty map, at a given history length.

``cfbci bench update`` prints it as its continuous row (`print_continuous`), timed in
a fresh process with one BLAS thread, as the service and ``cfbci simulate`` run it. The
uncertainty map's expected matches were once computed on a second thread beside the
particles' scores: on this project's 2-vCPU machine that step took 66 ms against 59 ms on
one thread (two threads, even two processes, ran numpy's exp at 1.2x one's throughput
there), so the step is one thread."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from rich.console import Console
from rich.table import Table

from acquisition.cardinal_teacher import CardinalTeacher
from acquisition.gaussian import generate_gaussian_features
from calibration_free.continuous_goals import ContinuousConfig, ContinuousGoalLearner
from cfbci.blas import single_threaded_blas
from cfbci.memory import keep_freed_memory
from session.plane import ContinuousSession, plane_config


@dataclass(frozen=True)
class ContinuousStepTimes:
    """Milliseconds per step (wall clock and this process's CPU time)."""

    history: int
    particles: int
    candidates: int
    median_ms: float
    p99_ms: float
    cpu_median_ms: float


def bench_continuous_step(
    history: int = 200, steps: int = 30, config: ContinuousConfig | None = None, seed: int = 0
) -> ContinuousStepTimes:
    """Time ``steps`` steps of a learner whose history holds ``history`` signals at the
    first timed step (11-D four-class Gaussian signals, like ``move_finger.mat``'s); the
    history grows by one signal per timed step. One BLAS thread and glibc told to keep freed
    memory (`cfbci.memory.keep_freed_memory`), as in ``cfbci simulate`` and the service
    (this process and its children: run it in a process of its own)."""
    config = config or ContinuousConfig()
    if history < 1 or steps < 1:
        raise ValueError(f"history and steps must be >= 1; got {history} and {steps}")
    keep_freed_memory()
    single_threaded_blas()
    rng = np.random.default_rng(seed)
    data = generate_gaussian_features(500, 4, 11, 0.98, rng)
    teacher = CardinalTeacher(data.labels, rng)
    # A step is a signal observed and the next probe chosen: one more step than signals.
    session = ContinuousSession(
        plane_config(seed, history + steps, config), ContinuousGoalLearner(config, rng)
    )
    move = session.start().move
    wall, cpu = [], []
    for n_seen in range(history - 1 + steps):  # the first history - 1 untimed
        assert move is not None
        signal = data.features[teacher.answer(np.array(move["from_state"]))[0]]
        start, start_cpu = time.perf_counter(), time.process_time()
        move = session.observe(signal).move
        if n_seen >= history - 1:
            wall.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
    wall_ms, cpu_ms = 1000 * np.array(wall), 1000 * np.array(cpu)
    return ContinuousStepTimes(
        history, config.n_hypotheses, config.n_candidates,
        float(np.median(wall_ms)), float(np.percentile(wall_ms, 99)), float(np.median(cpu_ms)),
    )


def print_continuous(
    times: ContinuousStepTimes, seconds_per_action: float, console: Console
) -> None:
    """The continuous row: wall and CPU times, and the wall median's share of an action."""
    table = Table(title="cfbci bench update - a continuous-goal step (new signal -> next probe)")
    for column in (
        "particles", "candidates", "history", "median ms", "p99 ms", "CPU median ms",
        "of the action interval",
    ):
        table.add_column(column, justify="right")
    share = times.median_ms / (10 * seconds_per_action)  # percent
    table.add_row(
        str(times.particles), str(times.candidates), str(times.history),
        f"{times.median_ms:.1f}", f"{times.p99_ms:.1f}", f"{times.cpu_median_ms:.1f}",
        f"{share:.2f} %",
    )
    console.print(table)
    console.print(
        f"continuous-goal step: 50 particles x 20 sampled classifiers scored on the whole "
        f"history, the uncertainty map over the candidates; CPU: this process's CPU time; "
        f"share of the action interval of {seconds_per_action:g} s. One BLAS thread.",
        soft_wrap=True,
    )
