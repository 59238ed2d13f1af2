"""Measure the memory one learner session really commits: peak resident growth in a fresh
process, beside `cfbci.service.limits.world_memory_bytes`' estimate of it.

Each measurement (`measure`) runs in its own spawned process, set up as the service
runs (`cfbci.memory.keep_freed_memory`, one BLAS thread). There it draws the
session's signals (a seeded K-class Gaussian set of ``features`` dimensions, 600 per
class, `acquisition.gaussian.generate_gaussian_features`), runs a 12-step warm-up
session on a 2 x 2 grid with the same learner settings (what a service pays once, not per
session: lazy imports, LAPACK workspaces), gives the heap's free memory back to the kernel,
resets the kernel's peak-RSS counter (``/proc/self/clear_refs``), reads ``VmRSS`` and runs
the session (`cfbci.offline.simulation.run_session`, the learner's session and a simulated
user, no network) with the learner stepped as the service steps it: every observation is
followed by the state message's fields (its ``after_observe``:
`session.tasks.state_fields`, whose cross-validated
balanced accuracy fits the k-fold decoders even for a likelihood that needs none). The
peak resident growth is ``VmHWM`` afterwards minus ``VmRSS`` before. Linux only.

``python tools/session_memory.py`` prints the table of cases (`TABLE_CASES`).
`measure_puddle` measures a puddle-world session the same way, from before its
world's policy tables are built.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.gaussian import generate_gaussian_features
from acquisition.loaders import N_CLASSES
from acquisition.mixed_teacher import SIGNAL_DIMS, gaussian_signals
from calibration_free.config import LearnerConfig
from calibration_free.learner import TaskLearner
from calibration_free.puddle_learner import PuddleConfig
from calibration_free.world import World
from calibration_free.worlds import make_world
from cfbci.blas import single_threaded_blas
from cfbci.memory import keep_freed_memory
from cfbci.offline.puddle import run_puddle_session
from cfbci.offline.simulation import SessionConfig, run_session
from cfbci.service.limits import world_memory_bytes
from session.plane import puddle_memory_bytes, puddle_world
from session.tasks import state_fields

#: Signals per class of a measured session's data set.
SIGNALS_PER_CLASS = 600
#: Nominal balanced accuracy of the measured sessions' Gaussian signals.
ACCURACY = 0.78
_WARM_UP_STEPS = 12
_SPAWN = multiprocessing.get_context("spawn")


@dataclass(frozen=True)
class MemoryCase:
    """One session to measure: world, learner settings, steps and feature length.

    Attributes
    ----------
    world : {"grid", "line", "pick-and-place"}
    grid : int
        Grid side (grid world only).
    steps : int
    features : int
        Length of the signals (d).
    learner : dict
        `LearnerConfig` settings (``frame``, ``decoder``,
        ``likelihood``, ...); the others default.
    seed : int
    """

    world: str = "grid"
    grid: int = 5
    steps: int = 100
    features: int = 8
    learner: dict[str, Any] = field(default_factory=dict)
    seed: int = 0

    @property
    def settings(self) -> LearnerConfig:
        return LearnerConfig.from_dict(self.learner)

    def make_world(self) -> World:
        return make_world(self.world, grid=self.grid) if self.world == "grid" else make_world(
            self.world
        )

    def estimate_bytes(self) -> int:
        """`cfbci.service.limits.world_memory_bytes` of this session."""
        return world_memory_bytes(self.make_world(), self.settings, self.steps, self.features)

    def describe(self) -> str:
        where = f"grid {self.grid}" if self.world == "grid" else self.world
        settings = self.settings
        return (f"{where}, {settings.frame}, {settings.decoder}, {settings.likelihood}, "
                f"{self.steps} steps, d={self.features}")


def _case(where: str, steps: int, features: int, **learner: Any) -> MemoryCase:
    """A case from e.g. ``"grid 10"`` or ``"line"``, steps, d and learner settings."""
    world, _, side = where.partition(" ")
    return MemoryCase(world, int(side or 5), steps, features, learner)


#: Worlds x frames x decoders x likelihoods x steps x feature lengths: the README's table
#: (``python tools/session_memory.py``).
TABLE_CASES: tuple[MemoryCase, ...] = (
    _case("grid 5", 100, 4),
    _case("grid 5", 400, 60, frame="guidance"),
    _case("grid 5", 200, 20, decoder="student_t"),
    _case("grid 10", 400, 57),
    _case("grid 10", 200, 20, frame="guidance"),
    _case("grid 10", 200, 20, likelihood="simple"),
    _case("grid 10", 200, 20, likelihood="batch", planner="signal"),
    _case("grid 10", 100, 20, decoder="student_t"),
    _case("grid 10", 100, 20, frame="guidance", decoder="gaussian"),
    _case("grid 10", 2000, 8),
    _case("grid 20", 200, 57),
    _case("grid 20", 100, 57, frame="guidance"),
    _case("grid 20", 100, 30, decoder="student_t"),
    _case("line", 400, 57),
    _case("line", 200, 60, frame="guidance", decoder="student_t"),
    _case("line", 100, 4, frame="guidance", decoder="gaussian"),
    _case("pick-and-place", 200, 57),
    _case("pick-and-place", 200, 57, frame="guidance"),
    _case("pick-and-place", 400, 4),
    _case("pick-and-place", 100, 10, decoder="student_t"),
    _case("pick-and-place", 100, 10, frame="guidance", decoder="gaussian"),
)


@dataclass(frozen=True)
class MemoryMeasurement:
    """A case's measured peak resident growth and its estimate, MiB."""

    case: MemoryCase
    measured_mib: float
    estimate_mib: float

    @property
    def ratio(self) -> float:
        """Estimate over measurement."""
        return self.estimate_mib / max(self.measured_mib, 1e-9)


def measure(case: MemoryCase) -> MemoryMeasurement:
    """Run ``case`` in a fresh spawned process and measure it (see the module docstring)."""
    with ProcessPoolExecutor(1, mp_context=_SPAWN) as pool:
        measured = pool.submit(_peak_growth_mib, case).result()
    return MemoryMeasurement(case, measured, case.estimate_bytes() / 2**20)


def _status_kib(name: str) -> int:
    """A ``/proc/self/status`` field in KiB (e.g. ``VmRSS``)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{name}:"):
            return int(line.split()[1])
    raise RuntimeError(f"no {name} in /proc/self/status")


def _release_free_heap() -> None:
    """Give the heap's free memory back to the kernel (glibc ``malloc_trim(0)``).

    `keep_freed_memory` keeps freed memory resident for reuse: without
    this, what the warm-up and the data's generation freed would serve the session's
    first allocations unseen by ``VmHWM``.
    """
    ctypes.CDLL(ctypes.util.find_library("c")).malloc_trim(0)


def _state_message(learner: TaskLearner) -> None:
    """What the service computes after every observation: the state message's fields."""
    state_fields(learner)


def _peak_growth_mib(case: MemoryCase) -> float:
    """In the measuring process: the session's peak resident growth, MiB."""
    keep_freed_memory()
    single_threaded_blas()
    frame = case.settings.frame
    data = generate_gaussian_features(
        SIGNALS_PER_CLASS, N_CLASSES[frame], case.features, ACCURACY, case.seed
    )
    config = SessionConfig(
        steps=case.steps, grid=case.grid, learner=case.settings, world=case.world
    )
    warm_up = replace(config, steps=_WARM_UP_STEPS, grid=2, world="grid")
    run_session(case.seed, warm_up, data, after_observe=_state_message)
    gc.collect()
    _release_free_heap()
    Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
    before = _status_kib("VmRSS")
    run_session(case.seed, config, data, after_observe=_state_message)
    return (_status_kib("VmHWM") - before) / 1024


def measure_puddle(steps: int, seed: int = 0) -> tuple[float, float]:
    """A puddle session of ``steps`` steps measured in a fresh spawned process, the world's
    policy tables built in it (what a service pays for its first puddle session), beside
    `session.plane.puddle_memory_bytes`' estimate: ``(measured MiB, estimate MiB)``."""
    with ProcessPoolExecutor(1, mp_context=_SPAWN) as pool:
        measured = pool.submit(_puddle_peak_growth_mib, steps, seed).result()
    estimate = puddle_memory_bytes(PuddleConfig(), steps, SIGNAL_DIMS) / 2**20
    return measured, estimate


def _puddle_peak_growth_mib(steps: int, seed: int) -> float:
    """In the measuring process: the peak resident growth of building the puddle world and
    running one session in it (its signals drawn before), MiB."""
    keep_freed_memory()
    single_threaded_blas()
    data = gaussian_signals(np.random.default_rng(seed))
    gc.collect()
    _release_free_heap()
    Path("/proc/self/clear_refs").write_text("5")
    before = _status_kib("VmRSS")
    run_puddle_session(seed, PuddleConfig(), puddle_world(), steps, data=data)
    return (_status_kib("VmHWM") - before) / 1024
