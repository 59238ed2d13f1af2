"""Re-run the results pages' commands and rewrite their tables and figures: ``make results``.

A results page marks what it regenerates with regions, HTML comments invisible on the
rendered page::

    <!-- results: KIND ID -->
    ...
    <!-- /results -->

``ID`` names the region on its page; ``KIND`` says how it is regenerated:

``page``
    the page's own runnable blocks run in order in a scratch folder as a reader's terminal
    would (``tools/docs_examples.py``), once per page; then the region's template, the HTML
    comment ``<!-- template ... -->`` at its top, is rendered from the JSON files and the
    output the blocks left (``{EXPRESSION:FORMAT}`` fields, ``let:``, ``for:`` and
    ``figure:`` lines), and replaces the rest of the region. Regenerated alone (``PAGE#ID``),
    a region whose template has the line ``blocks: above`` runs only the blocks between the
    region before it and itself.
``simulate``
    a table with a ``command`` column: every row's command runs with ``--json`` and the cells
    of the columns in ``SIMULATE_COLUMNS`` are rewritten from its report; the other cells are
    labels, kept.

Each regenerated region gets a *Produced on* line (today's date, this machine, the cfbci
version) in place of the one it had. docs/contributing/results.md is the contributors' page.

Usage: ``python tools/results.py [--test-sized] [PAGE[#ID] ...]`` (default: every page of
docs/results/). ``--test-sized`` runs the blocks' test-sized variants (their ``test:`` and
``replace:`` markers) and a ``simulate`` row with ``SIMULATE_TEST_OPTIONS``: minutes, to check
a page's templates; its figures are then not the page's.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import re
import shutil
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
#: A ``page`` region's template: an HTML comment at the top of its body.
TEMPLATE = re.compile(r"\A\s*<!-- template\n(?P<template>.*?)\n-->\n", re.DOTALL)
#: What ``--test-sized`` appends to a ``simulate`` row's command.
SIMULATE_TEST_OPTIONS = "--seeds 2 --steps 40 --jobs 1"

sys.path.insert(0, str(Path(__file__).resolve().parent))

from docs_examples import PageRun, page_blocks  # noqa: E402


class ResultsError(ValueError):
    """A region that cannot be regenerated; the message names the page and region."""


def _quantiles(values: list[float]) -> tuple[float, float, float]:
    """Median and quartiles as numpy's default (linear) percentiles."""
    import numpy as np

    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return float(median), float(q1), float(q3)


def _first_targets(report: dict[str, Any]) -> list[float]:
    steps = report["config"]["steps"]
    return [s["first_target_step"] or steps + 1 for s in report["sessions"]]


def _iqr(values: list[float]) -> str:
    median, q1, q3 = _quantiles(list(values))
    return f"{median:g} ({q1:g}-{q3:g})"


def _correct_range(report: dict[str, Any]) -> str:
    correct = [s["correct_targets"] for s in report["sessions"]]
    return f"{statistics.mean(correct):.2f} ({min(correct)}-{max(correct)})"


#: The ``simulate`` kind's columns: header -> the cell, from ``cfbci simulate --json``.
SIMULATE_COLUMNS: dict[str, Callable[[dict[str, Any]], str]] = {
    "median first target (IQR)": lambda r: _iqr(_first_targets(r)),
    "median first target": lambda r: f"{r['summary']['median_first_target_step']:g}",
    "mean correct (range)": _correct_range,
    "mean correct": lambda r: f"{r['summary']['mean_correct_targets']:.2f}",
    "mean wrong": lambda r: f"{r['summary']['mean_wrong_targets']:.2f}",
    "wrong-target rate": lambda r: f"{100 * r['summary']['wrong_target_rate']:.1f} %",
    "wrong first targets": lambda r: f"{100 * r['summary']['wrong_first_target_fraction']:.0f} %",
    "runs with a target": lambda r: str(r["summary"]["sessions_with_a_target"]),
    "median first confident": lambda r: f"{r['summary']['median_first_confident_step']:g}",
}


def _grab(pattern: str, text: str) -> str:
    found = re.search(pattern, text, re.MULTILINE)
    if found is None:
        raise LookupError(f"no match for {pattern!r} in the output")
    return found[1] if found.groups() else found[0]


def _percent(fraction: float | None, digits: int = 1) -> str:
    return "-" if fraction is None else f"{100 * fraction:.{digits}f} %"


def _pick(items: list[Any], **fields: Any) -> Any:
    return next((i for i in items if all(i.get(k) == v for k, v in fields.items())), None)


#: The functions a ``page`` template may call, beside Python's built-ins.
HELPERS: dict[str, Callable[..., Any]] = {
    "percent": _percent,  # percent(0.985) == "98.5 %", percent(x, 0); None as "-"
    "pick": _pick,  # pick(items, rule="pairwise"): the first object with those fields, or None
    "median": statistics.median,
    "stdev": statistics.stdev,
    "mean": statistics.mean,
    "iqr": _iqr,  # "median (q1-q3)" of a list, numpy's linear percentiles
    "quantiles": _quantiles,  # (median, q1, q3)
    "first_targets": _first_targets,  # a simulate report's first targets, none as steps + 1
    "simulate": lambda report, column: SIMULATE_COLUMNS[column](report),  # a simulate cell
    "grab": _grab,  # grab(PATTERN, output): the pattern's first group in a text
    "findall": lambda pattern, text: re.findall(pattern, text, re.MULTILINE),  # every match
}


def simulate_row(command: str, headers: list[str], scratch: Path) -> list[str]:
    """The figure cells of one ``simulate`` row: its command run with ``--json``."""
    out = scratch / "run.json"
    run(f"{command} --json {out}", scratch)
    report = json.loads(out.read_text())
    return [SIMULATE_COLUMNS[h](report) for h in headers]


def environment() -> dict[str, str]:
    """The commands' environment: the project's ``cfbci`` first on ``PATH``, figures drawn
    off-screen, and the data sets where the user's ``cfbci datasets fetch`` keeps them (the
    ``page`` kind runs its blocks with a fresh ``HOME``)."""
    from acquisition.fetch import FOLDER_VARIABLE, data_folder

    return {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}"
            f"{os.environ.get('PATH', '')}", "MPLBACKEND": "Agg", "PYTHONUNBUFFERED": "1",
            FOLDER_VARIABLE: str(data_folder())}


def run(command: str, folder: Path) -> None:
    """Run a shell command in ``folder`` with the project's ``cfbci``; stop on failure."""
    print(f"$ {command}", flush=True)
    subprocess.run(["bash", "-c", f"set -eo pipefail\n{command}"], cwd=folder,
                   env=environment(), check=True)


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


def produced_line(test_sized: bool = False) -> str:
    """The line saying when and where a region was produced."""
    today = datetime.date.today().isoformat()
    size = ", test-sized runs: not the page's figures" if test_sized else ""
    return (f"*Produced on {today} on {machine()} (cfbci {metadata.version('cfbci')}), "
            f"by `make results`{size}.*")


def _with_produced_line(lines: list[str], test_sized: bool) -> list[str]:
    """``lines`` with their *Produced* paragraph replaced (or one put first)."""
    produced = next((i for i, line in enumerate(lines) if line.startswith("*Produced")), None)
    if produced is None:
        return [produced_line(test_sized), "", *lines]
    end = produced
    while end < len(lines) and lines[end].strip():
        end += 1
    return [*lines[:produced], produced_line(test_sized), *lines[end:]]


def regenerate(body: str, kind: str, scratch: Path, test_sized: bool = False) -> str:
    """A ``simulate`` region's body with its figure cells and produced line rewritten."""
    lines = body.splitlines()
    table = [i for i, line in enumerate(lines) if line.startswith("|")]
    if len(table) < 3:
        raise ValueError("a results region needs a table with a header and rows")
    headers = _cells(lines[table[0]])
    if "command" not in headers:
        raise ValueError(f"the table has no 'command' column: {headers}")
    figures = [i for i, header in enumerate(headers) if header in SIMULATE_COLUMNS]
    if not figures:
        raise ValueError(f"no column the {kind} kind fills among {headers}; it fills: "
                         f"{', '.join(SIMULATE_COLUMNS)}")
    for index in table[2:]:
        cells = _cells(lines[index])
        command = cells[headers.index("command")].strip("`")
        if test_sized:
            command = f"{command} {SIMULATE_TEST_OPTIONS}"
        row_folder = Path(tempfile.mkdtemp(dir=scratch))
        values = simulate_row(command, [headers[i] for i in figures], row_folder)
        for column, value in zip(figures, values, strict=True):
            cells[column] = value
        lines[index] = "| " + " | ".join(cells) + " |"
    return "\n".join(_with_produced_line(lines, test_sized)) + "\n"


def _cells(row: str) -> list[str]:
    return [cell.strip() for cell in re.split(r"(?<!\\)\|", row.strip())[1:-1]]


# --- the page kind -------------------------------------------------------------------------


class Data(dict):
    """A JSON object whose keys also read as attributes (``run.summary``)."""

    def __getattr__(self, name: str) -> Any:
        try:
            return self[name]
        except KeyError:
            raise AttributeError(f"no key {name!r}; keys: {', '.join(self)}") from None


@dataclasses.dataclass
class PageOutputs:
    """What a page's blocks left: their folder, the JSON files by name, their output."""

    folder: Path
    files: dict[Path, Any]  #: every JSON file the blocks wrote, by its path in the folder
    output: str

    @property
    def names(self) -> dict[str, Any]:
        """The JSON files as template names: ``report/metrics.json`` is ``report_metrics``."""
        return {re.sub(r"\W", "_", str(path.with_suffix(""))): data
                for path, data in self.files.items()}


def run_page_blocks(page: Path, scratch: Path, test_sized: bool,
                    between: tuple[int, int] | None = None) -> PageOutputs:
    """Run the page's runnable blocks in order in a scratch folder, full size unless
    ``test_sized`` (only those whose fence is on a line ``between`` the two, if given);
    what they left."""
    blocks = [b for b in page_blocks(page) if b.runs_here
              and (between is None or between[0] < b.line < between[1])]
    if not blocks:
        raise ResultsError(f"{page}: a 'page' region, but the page has no runnable block")
    if not test_sized:
        blocks = [dataclasses.replace(b, variants=[], replacements=[], timeout=None)
                  for b in blocks]
    root = Path(tempfile.mkdtemp(dir=scratch))
    outputs: list[str] = []
    with PageRun(root, environment(), REPOSITORY) as page_run:
        for block in blocks:
            print(f"$ ({block.where})\n{block.code}", end="", flush=True)
            outputs.append(page_run.run(block))
    folder = root / "work"
    files = {path.relative_to(folder): json.loads(path.read_text(), object_hook=Data)
             for path in sorted(folder.rglob("*.json"))}
    return PageOutputs(folder, files, "\n".join(outputs))


_FIELD = re.compile(r"\{\{|\}\}|\{")
_FORMAT_SPEC = re.compile(r"[<>=^]?[+ -]?#?0?\d*[,_]?(?:\.\d+)?[bcdeEfFgGnosxX%]?")


def _field_end(template: str, start: int) -> int:
    """Index of the ``}`` closing the field that opens at ``start`` (nested braces kept)."""
    depth = 0
    for index in range(start, len(template)):
        if template[index] == "{":
            depth += 1
        elif template[index] == "}":
            depth -= 1
            if depth == 0:
                return index
    raise ResultsError(f"an unclosed '{{' at {template[start:start + 40]!r}")


def _split_field(field: str) -> tuple[str, str]:
    """``(expression, format)`` of a field's text: the format after the last ``:`` when it
    is a format specification and the expression before it compiles."""
    head, colon, spec = field.rpartition(":")
    if colon and _FORMAT_SPEC.fullmatch(spec):
        try:
            compile(head, "<field>", "eval")
            return head, spec
        except SyntaxError:
            pass
    return field, ""


def template_fields(template: str) -> list[tuple[str, str]]:
    """Every ``(expression, format)`` of a template, in order."""
    fields = []
    position = 0
    for match in _FIELD.finditer(template):
        if match.start() < position or match[0] != "{":
            continue
        end = _field_end(template, match.start())
        fields.append(_split_field(template[match.start() + 1:end]))
        position = end + 1
    return fields


def render(template: str, names: dict[str, Any], where: str) -> str:
    """The template with its fields computed over ``names`` (and `HELPERS`)."""
    scope = {**HELPERS, **names}
    pieces: list[str] = []
    position = 0
    for match in _FIELD.finditer(template):
        if match.start() < position:
            continue
        pieces.append(template[position:match.start()])
        if match[0] != "{":
            pieces.append(match[0][0])
            position = match.end()
            continue
        end = _field_end(template, match.start())
        expression, spec = _split_field(template[match.start() + 1:end])
        value = _evaluate(expression, scope, where)
        try:
            pieces.append("-" if value is None else format(value, spec))
        except (TypeError, ValueError) as error:
            raise ResultsError(f"{where}: {{{expression}:{spec}}}: {error}") from None
        position = end + 1
    pieces.append(template[position:])
    return "".join(pieces)


def regenerate_page_region(page: Path, body: str, outputs: PageOutputs, where: str,
                           test_sized: bool = False) -> str:
    """A ``page`` region's body: its template kept, the rest rendered from the outputs."""
    match = TEMPLATE.match(body)
    if match is None:
        raise ResultsError(f"{where}: a 'page' region starts with <!-- template ... -->")
    lines = []
    for line in match["template"].splitlines():
        if line.strip() == "blocks: above":
            continue
        if line.startswith("figure:"):
            source, _, target = line.removeprefix("figure:").strip().partition(" ")
            if not (outputs.folder / source).is_file():
                raise ResultsError(f"{where}: the blocks wrote no {source!r} (figure)")
            shutil.copyfile(outputs.folder / source, page.parent / target.strip())
        else:
            lines.append(line)
    files = {str(path.with_suffix("")): data for path, data in outputs.files.items()}
    rendered = render_lines(lines, {**outputs.names, "files": files, "output": outputs.output},
                            where)
    return f"{match[0]}{produced_line(test_sized)}\n\n{rendered.strip()}\n\n"


_FOR = re.compile(r"for:\s*(?P<target>.+?)\s+in\s+(?P<items>.+)")
_LET = re.compile(r"let:\s*(?P<name>[A-Za-z_]\w*)\s*=\s*(?P<value>.+)")


def render_lines(lines: list[str], names: dict[str, Any], where: str) -> str:
    """A template's lines rendered. A line ``let: NAME = EXPRESSION`` binds a name for the
    lines after it; a line ``for: TARGET in EXPRESSION`` renders the next line once per item,
    ``TARGET`` (a name, or names as in a Python ``for``) bound to it."""
    out: list[str] = []
    names = dict(names)
    index = 0
    while index < len(lines):
        loop = _FOR.fullmatch(lines[index].strip())
        let = _LET.fullmatch(lines[index].strip())
        if let is not None:
            names[let["name"]] = _evaluate(let["value"], {**HELPERS, **names}, where)
            index += 1
            continue
        if loop is None:
            out.append(render(lines[index], names, where))
            index += 1
            continue
        if index + 1 == len(lines):
            raise ResultsError(f"{where}: 'for:' must be followed by the line it repeats")
        items = _evaluate(loop["items"], {**HELPERS, **names}, where)
        for item in items:
            scope = {**names, "__item": item}
            exec(f"{loop['target']} = __item", {**HELPERS, **scope}, scope)
            del scope["__item"]
            out.append(render(lines[index + 1], scope, where))
        index += 2
    return "\n".join(out)


def _evaluate(expression: str, scope: dict[str, Any], where: str) -> Any:
    try:
        return eval(expression, scope)  # the page's own expression
    except Exception as error:  # any error of the page's expression
        names = sorted(k for k in scope if k not in HELPERS and not k.startswith("__"))
        raise ResultsError(f"{where}: {{{expression}}}: {type(error).__name__}: {error} "
                           f"(names: {', '.join(names) or 'none'})") from None


def regenerate_page(page: Path, only: str | None, scratch: Path,
                    test_sized: bool = False) -> list[str]:
    """Rewrite a page's regions (or the one named ``only``); the regions not regenerated."""
    text = page.read_text()
    skipped: list[str] = []
    outputs: list[PageOutputs] = []  # the page's blocks run once, at the first page region

    def region(match: re.Match[str]) -> str:
        try:
            name = f"{page.relative_to(REPOSITORY)}#{match['id']}"
        except ValueError:
            name = f"{page}#{match['id']}"
        if (only and match["id"] != only) or match["kind"] not in KINDS:
            if not only or match["id"] == only:
                skipped.append(f"{name} (kind {match['kind']!r})")
            return match[0]
        print(f"== {name}", flush=True)
        if match["kind"] == "page":
            template = TEMPLATE.match(match["body"])
            if only and template and "\nblocks: above\n" in f"\n{template['template']}\n":
                ran = run_page_blocks(page, scratch, test_sized, _above(text, match))
            else:
                if not outputs:
                    outputs.append(run_page_blocks(page, scratch, test_sized))
                ran = outputs[0]
            body = regenerate_page_region(page, match["body"], ran, name, test_sized)
        else:
            body = regenerate(match["body"], match["kind"], scratch, test_sized)
        return f"<!-- results: {match['kind']} {match['id']} -->\n{body}<!-- /results -->\n"

    if only and only not in {m["id"] for m in REGION.finditer(text)}:
        raise ValueError(f"{page}: no results region {only!r}")
    page.write_text(REGION.sub(region, text))
    return skipped


def _above(text: str, region: re.Match[str]) -> tuple[int, int]:
    """The lines between the region before ``region`` (or the page's start) and it."""
    before = [m for m in REGION.finditer(text) if m.end() <= region.start()]
    start = text.count("\n", 0, before[-1].end()) + 1 if before else 0
    return start, text.count("\n", 0, region.start()) + 1


#: The kinds of region this script regenerates.
KINDS = ("simulate", "page")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pages", nargs="*", help="PAGE or PAGE#ID (default: docs/results/*.md)")
    parser.add_argument("--test-sized", action="store_true",
                        help="the blocks' test-sized variants (to check a page's template)")
    args = parser.parse_args(argv)
    targets = args.pages or [str(p) for p in sorted(RESULTS.glob("*.md"))]
    skipped: list[str] = []
    failed: list[str] = []
    with tempfile.TemporaryDirectory(prefix="cfbci-results-") as scratch:
        for target in targets:  # a page that fails is left as it was; the others go on
            page, _, only = target.partition("#")
            try:
                skipped += regenerate_page(Path(page).resolve(), only or None, Path(scratch),
                                           args.test_sized)
            except (ValueError, AssertionError, OSError, subprocess.CalledProcessError) as error:
                failed.append(f"{target}: {error}")  # ResultsError, ExampleError among them
    for name in skipped:
        print(f"not regenerated: {name}")
    for failure in failed:
        print(f"FAILED, left as it was: {failure}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
