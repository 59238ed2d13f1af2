"""Peak resident memory of real learner sessions against the service's estimate of it.

    python tools/session_memory.py [--json OUT]

Runs every case of `cfbci.bench.memory_probe.TABLE_CASES` in its own fresh process
(`cfbci.bench.memory_probe.measure`; Linux) and prints, per case, the estimate
(`cfbci.service.limits.world_memory_bytes`), the measured peak resident growth and their
ratio, as the README's table. Cases run one after the other (a pnp session with d = 57
takes about a minute on a loaded 2-core machine).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

from cfbci.bench.memory_probe import TABLE_CASES, measure


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, help="write the measurements as JSON")
    args = parser.parse_args()
    print("| session | estimate MiB | measured MiB | estimate / measured |")
    print("|---|---:|---:|---:|")
    rows = []
    for case in TABLE_CASES:
        result = measure(case)
        rows.append({**asdict(result), "ratio": result.ratio})
        print(f"| {case.describe()} | {result.estimate_mib:.1f} | {result.measured_mib:.1f} | "
              f"{result.ratio:.2f} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
