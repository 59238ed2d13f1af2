"""``cfbci simulate --world continuous|puddle``: sessions of the two worlds in the plane.

* ``continuous`` (method-extensions §3): goal points anywhere in ``[0, 1]^2``, the cardinal
  guidance frame, a pool of ``--hypotheses`` particles resampled ``--sampling random|active``,
  probes chosen ``--planner random|uncertainty``; signals from a 4-class dataset
  (``--dataset``, e.g. ``move_finger.mat``) or ``--synthetic gaussian --dims D``. Reports each
  session's ``final_distance`` (best particle to goal) and the distance every 10 steps.
* ``puddle`` (§2): 660 tasks, the mixed feedback + guidance frame, ``--exploration
  random|epsilon-greedy|myopic|planning``; signals from the six-class 20-D Gaussian
  generator at nominal accuracy 0.95 (a stand-in for the thesis's speech words). Reports
  the taught task's normalised likelihood after every update (every 15 steps).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from acquisition.sources import DataSpec
from calibration_free.continuous_goals import ContinuousConfig
from calibration_free.puddle import PuddleWorld
from calibration_free.puddle_learner import PuddleConfig
from cfbci.offline.continuous import run_continuous_session
from cfbci.offline.puddle import run_puddle_session
from session.config import learner_settings
from session.plane import PLANE_FRAMES, plane_settings

PLANE_WORLDS: tuple[str, ...] = ("continuous", "puddle")
#: Steps at which the thesis reports the puddle world's curves.
THESIS_STEPS = (150, 240, 300, 450, 525)


@dataclass(frozen=True)
class PlaneJob:
    """One session of a plane world (picklable, for the workers)."""

    world: str
    seed: int
    steps: int
    data: DataSpec
    continuous: ContinuousConfig
    puddle: PuddleConfig
    class_order: tuple[int, ...] | None


@lru_cache(maxsize=1)
def _puddle_world() -> PuddleWorld:
    return PuddleWorld()  # its policies take a few seconds: once per process


def run_plane_job(job: PlaneJob) -> dict[str, Any]:
    """The JSON record of one session."""
    if job.world == "puddle":
        return run_puddle_session(job.seed, job.puddle, _puddle_world(), job.steps).to_dict()
    data = job.data.resolve("guidance")
    if callable(data):
        data = data(np.random.default_rng(job.seed))
    return run_continuous_session(
        job.seed, job.continuous, data, job.steps, job.class_order
    ).to_dict()


def live_source_fields(
    world: str, frame: str, learner: dict[str, Any], class_order: str | None
) -> dict[str, Any]:
    """The plane-world fields of a ``SourceSettings`` (``class_order``), after checking the
    learner settings as the service will (``LearnerConfig`` in a discrete world,
    `session.plane.plane_settings` in a plane world: ``ContinuousConfig`` or
    ``PuddleConfig`` settings).

    Raises
    ------
    ValueError
        On a bad setting, or a ``--class-order`` outside the continuous world.
    """
    if world != "continuous" and class_order is not None:
        raise ValueError("--class-order is an option of --world continuous only")
    if world not in PLANE_FRAMES:
        learner_settings(learner, frame)
        return {}
    plane_settings({"world": world, "frame": frame, "learner": learner})
    return {"class_order": parse_class_order(class_order)}


def parse_class_order(text: str | None) -> tuple[int, ...] | None:
    if text is None:
        return None
    try:
        order = tuple(int(k) for k in text.split(","))
    except ValueError:
        raise ValueError(
            f"--class-order takes four integers such as 2,0,3,1; got {text!r}"
        ) from None
    if sorted(order) != [0, 1, 2, 3]:
        raise ValueError(f"--class-order must be a permutation of 0,1,2,3; got {text!r}")
    return order


def plane_summary(sessions: Sequence[dict[str, Any]]) -> dict[str, Any]:
    if "final_distance" in sessions[0]:
        final = np.array([s["final_distance"] for s in sessions])
        q1, median, q3 = np.percentile(final, [25, 50, 75])
        return {"median_final_distance": median, "iqr_final_distance": [q1, q3],
                "mean_final_distance": float(final.mean())}
    curves = np.array([s["taught_likelihood"] for s in sessions])
    return {
        "update_steps": sessions[0]["update_steps"],
        "mean_taught_likelihood": curves.mean(axis=0).tolist(),
    }


def print_plane_report(report: dict[str, Any], console: Console) -> None:
    """A readable summary of `simulate_plane_world`'s report."""
    summary = report["summary"]
    if report["config"]["world"] == "continuous":
        table = Table(title=f"cfbci simulate --world continuous - {report['config']['dataset']}")
        table.add_column("seed", justify="right")
        table.add_column("final distance", justify="right")
        for session in report["sessions"]:
            table.add_row(str(session["seed"]), f"{session['final_distance']:.4f}")
        console.print(table)
        q1, q3 = summary["iqr_final_distance"]
        console.print(
            f"median final distance {summary['median_final_distance']:.4f} "
            f"(IQR {q1:.4f}-{q3:.4f}), mean {summary['mean_final_distance']:.4f}"
        )
        return
    steps, curve = summary["update_steps"], summary["mean_taught_likelihood"]
    shown = [k for k, s in enumerate(steps) if s in THESIS_STEPS] or [len(steps) - 1]
    console.print(
        "mean normalised likelihood of the taught task: "
        + ", ".join(f"{curve[k]:.2f} @{steps[k]}" for k in shown)
    )
