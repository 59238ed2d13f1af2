"""Learner step time of each likelihood, measured side by side in one run.

Closed-loop sessions on the 5 x 5 grid with a dataset (default ``s4.mat``, 34 features):
for every seed, one session per likelihood, one after the other (so that the machine's
load drifts across all of them alike); the time of every step of the session (a signal
observed, the next action chosen), in milliseconds, with one BLAS thread (as ``cfbci
simulate`` runs). Prints,
per likelihood and window of steps, the median and the 10th-90th percentiles, and the
"matching" median of the same window divided by that median (the speed-up)::

    .venv/bin/python tools/likelihood_timing.py [--dataset PATH] [--seeds 3] [--steps 500]
        [--likelihoods matching simple batch] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np

from acquisition.loaders import load_labelled
from acquisition.user import SimulatedUser
from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.streams import session_streams
from calibration_free.world import GridWorld
from cfbci.blas import single_threaded_blas
from cfbci.cli.options import parse_settings
from session.tasks import TaskSession


def step_times(config: LearnerConfig, features: np.ndarray, labels: np.ndarray, seed: int,
               steps: int) -> np.ndarray:
    """Milliseconds of every step (a signal observed and the next action chosen) of one
    session."""
    world = GridWorld(5)
    _, user_rng, learner_rng = session_streams(seed)
    user = SimulatedUser(world, config.frame, labels, user_rng)
    learner = CalibrationFreeLearner(world, config, learner_rng)
    # One more step than signals: the last signal's next action is chosen too.
    session = TaskSession(world, learner, seed, steps + 1)
    move = session.start().move
    times = np.empty(steps)
    for step in range(steps):
        assert move is not None
        index, _ = user.answer(session.agent, session.action)
        if move["target_reached"]:
            user.new_target()
        start = time.perf_counter()
        move = session.observe(features[index]).move
        times[step] = time.perf_counter() - start
    return 1000 * times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="../shared/datasets/errp-features-s4/s4.mat")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--likelihoods", nargs="+", default=["matching", "simple", "batch"])
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    single_threaded_blas()  # as cfbci simulate and the benches: one BLAS thread
    extra = parse_settings(args.set)
    data = load_labelled(args.dataset)
    features = np.asarray(data.features, dtype=np.float32)
    times: dict[str, list[np.ndarray]] = {kind: [] for kind in args.likelihoods}
    for seed in range(args.seeds):
        for kind in args.likelihoods:
            config = LearnerConfig.from_dict({**extra, "likelihood": kind})
            times[kind].append(step_times(config, features, data.labels, seed, args.steps))
    edges = [edge for edge in (0, 100, 300) if edge < args.steps] + [args.steps]
    reference = "matching" if "matching" in times else args.likelihoods[0]
    print(f"{args.dataset}: {args.seeds} seeds x {args.steps} steps, 5 x 5 grid, "
          f"settings {extra or 'default'}")
    header = f"{'likelihood':<14}{'steps':>10}{'median ms':>11}{'p10-p90 ms':>16}"
    print(f"{header}{'speed-up vs ' + reference:>22}")
    for kind, runs in times.items():
        for low, high in itertools.pairwise(edges):
            window = np.concatenate([run[low:high] for run in runs])
            base = np.median(np.concatenate([run[low:high] for run in times[reference]]))
            p10, p90 = np.percentile(window, [10, 90])
            print(f"{kind:<14}{f'{low + 1}-{high}':>10}{np.median(window):>11.2f}"
                  f"{f'{p10:.2f}-{p90:.2f}':>16}{base / np.median(window):>21.1f}x")


if __name__ == "__main__":
    main()
