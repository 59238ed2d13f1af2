"""How many distinct labellings the tasks form: the figure behind shared decoders.

Tasks whose labels agree on every signal since the last target share their decoders
(`calibration_free.task_decoders.TaskHistory.labellings`), so a step's fitting,
cross-validation and prediction cost follows the number of labellings, not of tasks. This
runs one simulated session (synthetic ErrP features, the default learner) and prints that
number's mean, median, 90th percentile and maximum over the steps, with the targets reached.

Usage::

    .venv/bin/python tools/labellings.py [--grid 20] [--steps 300] [--seed 0]
        [--accuracy 0.78] [--frame feedback]
"""

from __future__ import annotations

import argparse

import numpy as np

from acquisition.sources import synthetic_features
from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner, TaskLearner
from cfbci.offline.simulation import SessionConfig, run_session


def labellings_per_step(
    grid: int, steps: int, seed: int, accuracy: float, frame: str
) -> tuple[np.ndarray, int]:
    """The number of labellings after each of ``steps`` signals of the session ``cfbci
    simulate --grid GRID --steps STEPS --first-seed SEED --seeds 1 --synthetic-accuracy
    ACCURACY --frame FRAME`` runs, and the targets reached (correct or not)."""
    counts: list[int] = []

    def count(learner: TaskLearner) -> None:
        assert isinstance(learner, CalibrationFreeLearner)
        counts.append(len(learner.history.labellings[1]))

    config = SessionConfig(steps=steps, grid=grid, learner=LearnerConfig(frame=frame))
    result = run_session(
        seed, config, lambda rng: synthetic_features(accuracy, rng), after_observe=count
    )
    return np.array(counts), result.correct_targets + result.wrong_targets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--grid", type=int, default=20)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--accuracy", type=float, default=0.78)
    parser.add_argument("--frame", default="feedback")
    args = parser.parse_args()
    counts, targets = labellings_per_step(
        args.grid, args.steps, args.seed, args.accuracy, args.frame
    )
    print(
        f"{args.grid} x {args.grid} grid ({args.grid**2} tasks), {args.frame}, {args.steps} "
        f"steps, seed {args.seed}: labellings per step mean {counts.mean():.1f}, median "
        f"{np.median(counts):g}, 90th percentile {np.percentile(counts, 90):.1f}, max "
        f"{counts.max()}; {targets} targets"
    )


if __name__ == "__main__":
    main()
