"""Re-run the results pages' commands and rewrite their tables: ``make results``.

A results page marks each table it can regenerate::

    <!-- results: simulate s4-likelihoods -->
    *Produced on 2026-12-05 on ... .*

    | likelihood | median first target (IQR) | mean correct | ... | command |
    |---|---|---|---|---|
    | simple | ... | `cfbci simulate --dataset "$(cfbci datasets path s4)" --likelihood simple` |
    <!-- /results -->

``KIND`` says how a row's output becomes its figures and ``ID`` names the region on its page.
Every row's command (the ``command`` cell, in backquotes) runs at full size in a scratch
folder; the cells of the columns the kind knows are rewritten from its output, and the
*Produced on* line with today's date, this machine and the cfbci version. The other cells are
labels, kept. Regions of a kind this script does not know are listed as not regenerated.

Usage: ``python tools/results.py [PAGE[#ID] ...]`` (default: every page of docs/results/).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any

REPOSITORY = Path(__file__).resolve().parents[1]
RESULTS = REPOSITORY / "docs" / "results"
REGION = re.compile(
    r"<!-- results: (?P<kind>[a-z-]+) (?P<id>[a-z0-9-]+) -->\n(?P<body>.*?)<!-- /results -->\n",
    re.DOTALL,
)


def _quantiles(values: list[float]) -> tuple[float, float, float]:
    """Median and quartiles as numpy's default (linear) percentiles."""
    import numpy as np

    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return float(median), float(q1), float(q3)


def _first_targets(report: dict[str, Any]) -> list[float]:
    steps = report["config"]["steps"]
    return [s["first_target_step"] or steps + 1 for s in report["sessions"]]


def _first_target_iqr(report: dict[str, Any]) -> str:
    median, q1, q3 = _quantiles(_first_targets(report))
    return f"{median:g} ({q1:g}-{q3:g})"


def _correct_range(report: dict[str, Any]) -> str:
    correct = [s["correct_targets"] for s in report["sessions"]]
    return f"{statistics.mean(correct):.2f} ({min(correct)}-{max(correct)})"


#: The ``simulate`` kind's columns: header -> the cell, from ``cfbci simulate --json``.
SIMULATE_COLUMNS: dict[str, Callable[[dict[str, Any]], str]] = {
    "median first target (IQR)": _first_target_iqr,
    "median first target": lambda r: f"{r['summary']['median_first_target_step']:g}",
    "mean correct (range)": _correct_range,
    "mean correct": lambda r: f"{r['summary']['mean_correct_targets']:.2f}",
    "mean wrong": lambda r: f"{r['summary']['mean_wrong_targets']:.2f}",
    "wrong-target rate": lambda r: f"{100 * r['summary']['wrong_target_rate']:.1f} %",
    "wrong first targets": lambda r: f"{100 * r['summary']['wrong_first_target_fraction']:.0f} %",
    "runs with a target": lambda r: str(r["summary"]["sessions_with_a_target"]),
    "median first confident": lambda r: f"{r['summary']['median_first_confident_step']:g}",
}


def simulate_row(command: str, headers: list[str], scratch: Path) -> list[str]:
    """The figure cells of one ``simulate`` row: its command run with ``--json``."""
    out = scratch / "run.json"
    run(f"{command} --json {out}", scratch)
    report = json.loads(out.read_text())
    return [SIMULATE_COLUMNS[h](report) for h in headers]


#: What each kind of region does with a row: (command, figure headers, folder) -> cells.
KINDS: dict[str, Callable[[str, list[str], Path], list[str]]] = {"simulate": simulate_row}
#: The columns each kind fills (the others are labels, kept).
COLUMNS: dict[str, dict[str, Callable[[dict[str, Any]], str]]] = {"simulate": SIMULATE_COLUMNS}


def run(command: str, folder: Path) -> None:
    """Run a shell command in ``folder`` with the project's ``cfbci``; stop on failure."""
    environment = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}"
                   f"{os.environ.get('PATH', '')}", "MPLBACKEND": "Agg"}
    print(f"$ {command}", flush=True)
    subprocess.run(["bash", "-c", f"set -eo pipefail\n{command}"], cwd=folder,
                   env=environment, check=True)


def machine() -> str:
    """This machine as the pages name one: CPU model, cores, AVX-512."""
    model, flags = platform.processor() or platform.machine(), ""
    try:
        info = Path("/proc/cpuinfo").read_text()
        model = re.search(r"model name\s*:\s*(.+)", info)[1].strip()
        flags = re.search(r"flags\s*:\s*(.+)", info)[1]
    except (OSError, TypeError):
        pass
    avx512 = " with AVX-512" if " avx512f" in f" {flags}" else ""
    return f"{model}, {os.cpu_count()} vCPUs{avx512}"


def produced_line() -> str:
    """The line saying when and where a region was produced."""
    today = datetime.date.today().isoformat()
    return (f"*Produced on {today} on {machine()} (cfbci {metadata.version('cfbci')}), "
            "by `make results`.*")


def regenerate(body: str, kind: str, scratch: Path) -> str:
    """A region's body with its table's figure cells and its produced line rewritten."""
    lines = body.splitlines()
    table = [i for i, line in enumerate(lines) if line.startswith("|")]
    if len(table) < 3:
        raise ValueError("a results region needs a table with a header and rows")
    headers = _cells(lines[table[0]])
    if "command" not in headers:
        raise ValueError(f"the table has no 'command' column: {headers}")
    figures = [i for i, header in enumerate(headers) if header in COLUMNS[kind]]
    if not figures:
        raise ValueError(f"no column the {kind} kind fills among {headers}; it fills: "
                         f"{', '.join(COLUMNS[kind])}")
    for index in table[2:]:
        cells = _cells(lines[index])
        command = cells[headers.index("command")].strip("`")
        row_folder = Path(tempfile.mkdtemp(dir=scratch))
        values = KINDS[kind](command, [headers[i] for i in figures], row_folder)
        for column, value in zip(figures, values, strict=True):
            cells[column] = value
        lines[index] = "| " + " | ".join(cells) + " |"
    produced = next((i for i, line in enumerate(lines) if line.startswith("*Produced")), None)
    if produced is None:
        lines[0:0] = [produced_line(), ""]
    else:  # the whole paragraph
        end = produced
        while end < len(lines) and lines[end].strip():
            end += 1
        lines[produced:end] = [produced_line()]
    return "\n".join(lines) + "\n"


def _cells(row: str) -> list[str]:
    return [cell.strip() for cell in re.split(r"(?<!\\)\|", row.strip())[1:-1]]


def regenerate_page(page: Path, only: str | None, scratch: Path) -> list[str]:
    """Rewrite a page's regions (or the one named ``only``); the regions not regenerated."""
    text = page.read_text()
    skipped: list[str] = []

    def region(match: re.Match[str]) -> str:
        name = f"{page.relative_to(REPOSITORY)}#{match['id']}"
        if (only and match["id"] != only) or match["kind"] not in KINDS:
            if not only or match["id"] == only:
                skipped.append(f"{name} (kind {match['kind']!r})")
            return match[0]
        print(f"== {name}", flush=True)
        body = regenerate(match["body"], match["kind"], scratch)
        return f"<!-- results: {match['kind']} {match['id']} -->\n{body}<!-- /results -->\n"

    new = REGION.sub(region, text)
    if only and only not in {m["id"] for m in REGION.finditer(text)}:
        raise ValueError(f"{page}: no results region {only!r}")
    page.write_text(new)
    return skipped


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pages", nargs="*", help="PAGE or PAGE#ID (default: docs/results/*.md)")
    args = parser.parse_args(argv)
    targets = args.pages or [str(p) for p in sorted(RESULTS.glob("*.md"))]
    skipped: list[str] = []
    with tempfile.TemporaryDirectory(prefix="cfbci-results-") as scratch:
        for target in targets:
            page, _, only = target.partition("#")
            skipped += regenerate_page(Path(page).resolve(), only or None, Path(scratch))
    for name in skipped:
        print(f"not regenerated: {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
