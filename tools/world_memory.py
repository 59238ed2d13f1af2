"""Memory and time of a grid world's tables: ``GridWorld(N)``, its frame and the planner.

    python tools/world_memory.py 50 feedback

Prints tracemalloc's peak and retained sizes, the process's peak RSS, the time to build
the objects (cheap: tables are built on first use), to build the tables (what a session's
first epoch pays) and one uncertainty-planner reward evaluation (20 signals, random task
weights). Set ``OPENBLAS_NUM_THREADS=1`` on a loaded machine.
"""

from __future__ import annotations

import argparse
import resource
import time
import tracemalloc

import numpy as np

from calibration_free.frames import FRAMES, Frame
from calibration_free.planning import UncertaintyPlanner
from calibration_free.world import GridWorld


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("size", type=int, help="grid side")
    parser.add_argument("frame", choices=FRAMES)
    args = parser.parse_args()
    baseline = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    tracemalloc.start()
    start = time.perf_counter()
    world = GridWorld(args.size)
    frame = Frame(world, args.frame)
    planner = UncertaintyPlanner(frame)
    built = time.perf_counter()
    frame.weights_at(0, 0)  # what the first epoch does: the tables are built here
    tables = time.perf_counter()
    rng = np.random.default_rng(0)
    corrected = rng.dirichlet(np.ones(frame.n_classes), size=(world.n_tasks, 20))
    weights = rng.dirichlet(np.ones(world.n_tasks))
    planner.rewards(corrected, weights)
    rewarded = time.perf_counter()
    current, peak = tracemalloc.get_traced_memory()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    print(
        f"grid {args.size}, {args.frame}: tracemalloc peak {peak / 2**20:.1f} MiB, retained "
        f"{current / 2**20:.1f} MiB; peak RSS {rss / 1024:.0f} MiB ({baseline / 1024:.0f} "
        f"after imports); construction {built - start:.3f} s, tables {tables - built:.2f} s, "
        f"one planner reward {rewarded - tables:.3f} s"
    )


if __name__ == "__main__":
    main()
