"""The cost of one continuous-goal step (issue 10): resampling, probe choice, relabelling,
the sampled-classifier confidence and the uncertainty map, at a given history length."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from acquisition.cardinal_teacher import CardinalTeacher
from acquisition.gaussian import generate_gaussian_features
from calibration_free.continuous_goals import ContinuousConfig, ContinuousGoalLearner


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
    history grows by one signal per timed step."""
    config = config or ContinuousConfig()
    rng = np.random.default_rng(seed)
    data = generate_gaussian_features(500, 4, 11, 0.98, rng)
    teacher = CardinalTeacher(data.labels, rng)
    learner = ContinuousGoalLearner(config, rng)
    for _ in range(history - 1):  # build the history without timing it
        point = learner.propose()
        learner.observe(point, data.features[teacher.answer(point)[0]])
    wall, cpu = [], []
    for _ in range(steps):
        start, start_cpu = time.perf_counter(), time.process_time()
        point = learner.propose()
        learner.observe(point, data.features[teacher.answer(point)[0]])
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    wall_ms, cpu_ms = 1000 * np.array(wall), 1000 * np.array(cpu)
    return ContinuousStepTimes(
        history, config.n_hypotheses, config.n_candidates,
        float(np.median(wall_ms)), float(np.percentile(wall_ms, 99)), float(np.median(cpu_ms)),
    )
