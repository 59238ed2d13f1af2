"""Run a ``cfbci bench`` command with two checkouts of the project, alternately, and
compare their figures: is a change slower?

Usage::

    python tools/bench_compare.py --before ../before --rounds 3 -- bench update --grids 5 20

``--before`` is a checkout of the reference commit (a ``git worktree``); its code is run
with this interpreter (``PYTHONPATH``), so both sides share the installed dependencies.
Each round runs the command once with each side, in alternating order, so that load on
the machine falls on both alike. Every numeric figure of the command's ``--json`` output
whose key ends in ``median_ms`` (or is ``seconds``, ``wall_s``, or the ``median`` of an
``..._ms`` object) is reported: the median
over the rounds on each side, and the ratio after / before.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

TIMED = ("median_ms", "seconds", "wall_s", "elapsed_s")


def figures(data: Any, prefix: str = "") -> dict[str, float]:
    """The timing figures of a bench's JSON, by their path (``rows[1].median_ms``)."""
    found: dict[str, float] = {}
    if isinstance(data, dict):
        for key, value in data.items():
            path = f"{prefix}.{key}" if prefix else key
            timed = key.endswith(TIMED) or (key == "median" and prefix.endswith("_ms"))
            if isinstance(value, int | float) and not isinstance(value, bool) and (
                timed and "naive" not in path and "per_session" not in path
            ):
                found[path] = float(value)
            else:
                found |= figures(value, path)
    elif isinstance(data, list):
        for index, value in enumerate(data):
            found |= figures(value, f"{prefix}[{index}]")
    return found


def run(command: list[str], code: Path | None, out: Path) -> dict[str, float]:
    """One run of ``cfbci COMMAND --json OUT`` with the code at ``code`` (None: this one)."""
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = str(code)
    main = "import sys; from cfbci.cli import main; sys.exit(main(sys.argv[1:]))"
    subprocess.run([sys.executable, "-c", main, *command, "--json", str(out)], env=env,
                   check=True, stdout=subprocess.DEVNULL, cwd=out.parent)
    return figures(json.loads(out.read_text()))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="reference checkout")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- bench NAME [options]")
    args = parser.parse_args()
    command = [c for c in args.command if c != "--"]
    runs: dict[str, list[dict[str, float]]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as directory:
        for round_ in range(args.rounds):
            order = ("before", "after") if round_ % 2 == 0 else ("after", "before")
            for side in order:
                code = args.before.resolve() if side == "before" else None
                runs[side].append(run(command, code, Path(directory) / f"{side}.json"))
                print(f"round {round_ + 1} {side} done", file=sys.stderr)
    print(f"cfbci {' '.join(command)}: median of {args.rounds} alternating rounds")
    print(f"{'figure':40s} {'before':>10s} {'after':>10s} {'after/before':>13s}")
    for name in runs["before"][0]:
        before = statistics.median(r[name] for r in runs["before"])
        after = statistics.median(r[name] for r in runs["after"])
        print(f"{name:40s} {before:10.2f} {after:10.2f} {after / before:13.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
