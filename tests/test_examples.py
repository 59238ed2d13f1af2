"""Every example of README.md and docs/**/*.md runs: a broken example fails ``make test``.

Each page's shell, console and Python blocks run in order, test-sized where a block says
so, in a fresh folder as one reader's terminal (``tools/docs_examples.py`` says how;
docs/contributing/examples.md is the contributors' page). Pages that need a real data set
the machine does not have (``cfbci datasets path s4``) are skipped; the real files come from
``../shared/datasets`` when it is there, checked by their sha256, as ``cfbci datasets
fetch`` would have left them.
"""

from __future__ import annotations

import hashlib
import os
import re
import shlex
import shutil
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from system_deps import require

from acquisition.fetch import DATASETS

REPOSITORY = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPOSITORY / "tools"))

from docs_examples import (  # noqa: E402
    ExampleError,
    PageRun,
    check_same_as,
    group_alive,
    page_blocks,
    variant_code,
)

#: The pages whose examples are run.
PAGES = [REPOSITORY / "README.md", *sorted((REPOSITORY / "docs").rglob("*.md"))]
#: Where a clone's sibling folder keeps the real data sets (not in a fresh clone).
SHARED_DATA = REPOSITORY.parent / "shared" / "datasets"


def _runnable(page: Path) -> list:
    return [b for b in page_blocks(page) if b.runs_here]


@pytest.fixture(scope="session")
def reader_environment(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, str], set]:
    """The environment the examples start from, and the real data sets it holds."""
    data = tmp_path_factory.mktemp("data")
    for dataset in DATASETS.values():
        for candidate in SHARED_DATA.rglob(dataset.file_name):
            if hashlib.sha256(candidate.read_bytes()).hexdigest() == dataset.sha256:
                shutil.copyfile(candidate, data / dataset.file_name)
                break
    available = {d.name for d in DATASETS.values() if (data / d.file_name).is_file()}
    environment = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
        "CFBCI_DATA_DIR": str(data),
        "MPLBACKEND": "Agg",
        "PYTHONUNBUFFERED": "1",
    }
    environment.pop("CFBCI_VIEW_TOKEN", None)
    return environment, available


def _page_id(page: Path) -> str:
    return str(page.relative_to(REPOSITORY))


@pytest.mark.parametrize(
    "page", [p for p in PAGES if _runnable(p)], ids=_page_id
)
def test_page_examples_run(page: Path, tmp_path: Path, reader_environment) -> None:
    """The page's runnable blocks, in order, each exits 0 (and prints what it promises)."""
    environment, available = reader_environment
    blocks = _runnable(page)
    missing = set().union(*(b.datasets for b in blocks)) - available
    if missing:
        pytest.skip(f"needs the real data set(s) {sorted(missing)}, absent here")
    for block in blocks:  # Debian's programs a block needs: skip, or fail under CI
        for program, package in block.needs:
            require(program, package)
    with PageRun(tmp_path, environment, REPOSITORY) as run:
        for block in blocks:
            run.run(block)


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_markers_are_well_formed(page: Path) -> None:
    """Every marker is a known directive right above a runnable block, every test variant
    names a command its block runs (a renamed command breaks it here), and a block marked
    as run on another page is there, markers included, and run there."""
    for block in page_blocks(page):
        if block.kind:
            variant_code(block)
        if block.same_as:
            check_same_as(block, REPOSITORY)


def _page(tmp_path: Path, text: str) -> Path:
    page = tmp_path / "page.md"
    page.write_text(text)
    return page


def test_a_broken_example_fails(tmp_path: Path, reader_environment) -> None:
    """A block whose command fails fails the page, naming the block's line and the error."""
    page = _page(tmp_path, "# A page\n\nText.\n\n```sh\ncfbci simulate --steps many\n```\n")
    (block,) = _runnable(page)
    with PageRun(tmp_path / "run", reader_environment[0], REPOSITORY) as run, \
            pytest.raises(ExampleError, match=r"page\.md:5: exit status 2") as failure:
        run.run(block)
    assert "invalid int value: 'many'" in str(failure.value)


def test_a_missing_promise_fails(tmp_path: Path, reader_environment) -> None:
    """A block that runs but does not print what its ``expect`` marker promises fails."""
    page = _page(tmp_path, "<!-- example: expect: identical: -->\n```sh\necho different\n```\n")
    with PageRun(tmp_path / "run", reader_environment[0], REPOSITORY) as run, \
            pytest.raises(ExampleError, match="lacks 'identical:'"):
        run.run(*_runnable(page))


def test_test_variants_files_and_environment_carry_over(tmp_path: Path,
                                                         reader_environment) -> None:
    """The test variant overrides the page's options; later blocks see earlier blocks'
    files, exported variables and working directory, as in one terminal."""
    page = _page(tmp_path, """\
<!-- example: test: simulate --seeds 1 --steps 8 -->
```sh
export ANSWER=42
mkdir out && cd out
cfbci simulate --seeds 20 --steps 500 --json run.json  # the full run
```

<!-- example: skip: shown, never run -->
```sh
exit 1
```

```python
import json, os
report = json.load(open("run.json"))
assert os.environ["ANSWER"] == "42"
assert [s["seed"] for s in report["sessions"]] == [0], report["sessions"]
assert report["config"]["steps"] == 8
```
""")
    blocks = _runnable(page)
    assert len(blocks) == 2
    with PageRun(tmp_path / "run", reader_environment[0], REPOSITORY) as run:
        for block in blocks:
            run.run(block)


def test_background_blocks_serve_the_next_and_are_ended(tmp_path: Path,
                                                       reader_environment) -> None:
    """A background block runs on (ready once it says so) while the next block uses it;
    every process of the page is ended when the page is done. Ports are the page's own."""
    page = _page(tmp_path, """\
<!-- example: background -->
<!-- example: ready: serving on -->
```sh
cfbci serve --listen tcp/127.0.0.1:7447 --record-dir runs
```

<!-- example: expect: session 'demo': 5 steps -->
```sh
cfbci source --session demo --connect tcp/127.0.0.1:7447 --steps 5
```
""")
    background, source = _runnable(page)
    with PageRun(tmp_path / "run", reader_environment[0], REPOSITORY) as run:
        assert run.ports["7447"] != "7447"
        run.run(background)
        run.run(source)
        service = run.processes[0][1]
        assert service.poll() is None
    assert not group_alive(service.pid)  # every process of the page is gone
    with (tmp_path / "run" / "work" / "runs" / "demo.mcap").open("rb") as recording:
        summary = make_reader(recording).get_summary()  # SIGTERM: closed, indexed
    assert summary is not None and summary.statistics.message_count > 0


def test_malformed_markers_are_errors(tmp_path: Path) -> None:
    """An unknown directive, or a marker away from its block, is an error naming the line."""
    with pytest.raises(ExampleError, match=r"page\.md:1: unknown example marker"):
        page_blocks(_page(tmp_path, "<!-- example: sikp -->\n```sh\ntrue\n```\n"))
    with pytest.raises(ExampleError, match=r"page\.md:1: an example marker must be right"):
        page_blocks(_page(tmp_path, "<!-- example: skip: x -->\nText.\n```sh\ntrue\n```\n"))
    with pytest.raises(ExampleError, match="does not run"):
        variant_code(*page_blocks(_page(
            tmp_path, "<!-- example: test: simulate --seeds 1 -->\n```sh\ncfbci replay x\n```\n"
        )))


def _results_commands() -> list[tuple[str, str]]:
    """(where, command) of every row of the results pages' regenerated tables."""
    results = _tool("results")
    found = []
    for page in sorted((REPOSITORY / "docs" / "results").glob("*.md")):
        for region in results.REGION.finditer(page.read_text()):
            rows = [line for line in region["body"].splitlines() if line.startswith("|")]
            if not rows or "command" not in results._cells(rows[0]):
                continue
            column = results._cells(rows[0]).index("command")
            for row in rows[2:]:
                found.append((f"{page.name}#{region['id']}", results._cells(row)[column]))
    return found


def _tool(name: str):
    import importlib

    return importlib.import_module(name)


@pytest.mark.parametrize("where, command", _results_commands())
def test_results_commands_parse(where: str, command: str) -> None:
    """Every command of a regenerated results table is a valid ``cfbci`` command line (what
    ``make results`` will run), with the data set paths the reader's."""
    from cfbci.cli import build_parser
    from cfbci.offline.presets import PRESETS

    assert command.startswith("`cfbci ") and command.endswith("`"), (where, command)
    line = re.sub(r'"\$\(cfbci datasets path (\w+)\)"', r"/data/\1.mat", command.strip("`"))
    args = shlex.split(line)[1:]
    parsed = build_parser().parse_args(args)
    if getattr(parsed, "preset", None):
        build_parser(PRESETS[parsed.preset]).parse_args(args)


def test_a_block_run_elsewhere_must_be_there(tmp_path: Path) -> None:
    """A ``same-as`` block whose twin changed (or lost a marker) is an error."""
    block = "<!-- example: test: simulate --seeds 1 -->\n```sh\ncfbci simulate\n```\n"
    twin = _page(tmp_path, block)
    (tmp_path / "readme.md").write_text(f"<!-- example: same-as: {twin} -->\n{block}")
    (same,) = page_blocks(tmp_path / "readme.md")
    assert not same.runs_here
    check_same_as(same, tmp_path)
    twin.write_text("```sh\ncfbci simulate\n```\n")  # the marker dropped there
    with pytest.raises(ExampleError, match="not run on"):
        check_same_as(same, tmp_path)
