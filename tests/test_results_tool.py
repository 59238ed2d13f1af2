"""``make results`` (tools/results.py): every results page is regenerated from its commands.

The tool runs a page's blocks and rewrites its marked regions (docs/contributing/results.md).
These tests check that every results page has regions the tool regenerates, with templates
that parse, and regenerate pages from short runs of the real commands: a page written here,
and the live-latency page itself, test-sized.
"""

from __future__ import annotations

import ast
import builtins
import json
import os
import re
import shutil
import sys
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPOSITORY / "tools"))

import results  # noqa: E402
from docs_examples import ExampleError, page_blocks  # noqa: E402

#: The results pages (the index lists them and holds no figure of its own).
PAGES = [p for p in sorted(results.RESULTS.glob("*.md")) if p.name != "index.md"]


def _regions(page: Path) -> list:
    return list(results.REGION.finditer(page.read_text()))


def _free_names(expression: str) -> set[str]:
    """Names an expression reads that it does not bind itself (lambda arguments,
    comprehension variables)."""
    tree = ast.parse(expression, mode="eval")
    bound = {a.arg for node in ast.walk(tree) if isinstance(node, ast.Lambda)
             for a in node.args.args}
    bound |= {n.id for node in ast.walk(tree) if isinstance(node, ast.comprehension)
              for n in ast.walk(node.target) if isinstance(n, ast.Name)}
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} - bound


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_results_page_is_regenerated(page: Path) -> None:
    """Each results page has at least one region, every region is of a kind ``make results``
    regenerates, and each ``page`` region's template parses and reads only names it can
    have: the JSON files the page's blocks name, its own ``let:``/``for:`` names, the
    helpers and Python's built-ins."""
    regions = _regions(page)
    assert regions, f"{page.name}: no <!-- results: KIND ID --> region"
    blocks = [b for b in page_blocks(page) if b.runs_here]
    code = "\n".join(b.code for b in blocks)
    for region in regions:
        where = f"{page.name}#{region['id']}"
        assert region["kind"] in results.KINDS, f"{where}: kind {region['kind']!r} unknown"
        if region["kind"] != "page":
            continue
        assert blocks, f"{where}: a page region on a page without runnable blocks"
        template = results.TEMPLATE.match(region["body"])
        assert template, f"{where}: no <!-- template ... --> at the top of the region"
        known = {*results.HELPERS, *dir(builtins), "output", "files"}
        for line in template["template"].splitlines():
            if line.startswith("figure:"):
                source, target = line.removeprefix("figure:").split()
                assert Path(source).name in code or f"--out {Path(source).parts[0]}" in code, (
                    f"{where}: no block writes {source}")
                assert (page.parent / target).is_file(), f"{where}: {target} is not there"
                continue
            let = results._LET.fullmatch(line.strip())
            loop = results._FOR.fullmatch(line.strip())
            expressions = ([let["value"]] if let else [loop["items"]] if loop
                           else [e for e, _ in results.template_fields(line)])
            for expression in expressions:
                for name in _free_names(expression) - known:
                    stem = name.replace("_", "[-_/]")
                    written = re.search(rf"\b{stem}\.json\b", code) or re.search(
                        rf"--out {name.split('_')[0]}\b", code)
                    assert written, f"{where}: {{{expression}}} reads {name!r}: no block writes it"
            if let:
                known.add(let["name"])
            if loop:
                known |= {n.id for n in ast.walk(ast.parse(loop["target"]))
                          if isinstance(n, ast.Name)}


def _reader_environment(monkeypatch: pytest.MonkeyPatch, data: Path) -> None:
    monkeypatch.setenv("CFBCI_DATA_DIR", str(data))
    monkeypatch.setenv("PATH", f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")


PAGE = """\
# A results page

<!-- example: test: simulate --seeds 2 --steps 12 --jobs 1 -->
```sh
cfbci simulate --seeds 20 --steps 500 --json run.json
python -c "open('figure.png', 'wb').write(b'not really a PNG')"
```

Text kept.

<!-- results: page table -->
<!-- template
figure: figure.png figure-copy.png
let: s = run.summary
| seeds | steps | mean correct | correct per session |
|---|---|---|---|
let: each = ", ".join(str(x.correct_targets) for x in run.sessions)
| {len(run.sessions)} | {run.config.steps} | {s.mean_correct_targets:.2f} | {each} |
for: x in run.sessions
| session {x.seed} | {x.steps} | {x.correct_targets} | {{literal}} |
-->
*Produced on 2026-01-01 on an old machine.*

| seeds | steps | mean correct | correct per session |
|---|---|---|---|
| 20 | 500 | 19.60 | ... |

<!-- /results -->

More text kept.
"""


def test_a_page_region_is_rewritten_from_a_short_run(tmp_path: Path, monkeypatch) -> None:
    """The page's block runs (test-sized), and the region's table is rendered from the JSON
    it wrote, its figure copied, its produced line today's; the rest of the page is kept."""
    _reader_environment(monkeypatch, tmp_path / "data")
    page = tmp_path / "page.md"
    page.write_text(PAGE)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    assert results.regenerate_page(page, None, scratch, test_sized=True) == []
    text = page.read_text()
    assert text.startswith(PAGE[:PAGE.index("<!-- results")])
    assert text.endswith("<!-- /results -->\n\nMore text kept.\n")
    assert PAGE[PAGE.index("<!-- template"):PAGE.index("-->\n*Produced")] in text  # kept
    assert "2026-01-01" not in text and "| 20 | 500 |" not in text
    assert results.produced_line(test_sized=True) in text
    rendered = text[text.index("test-sized runs"):]
    assert "| seeds | steps | mean correct | correct per session |" in rendered
    assert "| 2 | 12 |" in rendered
    assert "| session 0 | 12 |" in rendered and "| session 1 | 12 |" in rendered
    assert "{literal}" in rendered
    assert (tmp_path / "figure-copy.png").read_bytes() == b"not really a PNG"
    # regenerated again: the same template, one produced line, one table
    results.regenerate_page(page, "table", scratch, test_sized=True)
    again = page.read_text()
    assert again.count("*Produced on") == 1 and again.count("| session 0 |") == 1


def test_a_simulate_region_reruns_each_row(tmp_path: Path, monkeypatch) -> None:
    """A ``simulate`` region's figure cells come from its rows' commands; labels are kept."""
    _reader_environment(monkeypatch, tmp_path / "data")
    page = tmp_path / "page.md"
    page.write_text("""\
<!-- results: simulate rows -->
*Produced on 2026-01-01.*

| data | mean correct | runs with a target | command |
| --- | --- | --- | --- |
| easy | 99.00 | 99 | `cfbci simulate --synthetic-accuracy 0.95` |

<!-- /results -->
""")
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    results.regenerate_page(page, None, scratch, test_sized=True)
    row = next(line for line in page.read_text().splitlines() if line.startswith("| easy"))
    cells = results._cells(row)
    assert cells[0] == "easy" and cells[3] == "`cfbci simulate --synthetic-accuracy 0.95`"
    assert cells[1] != "99.00" and 0 <= float(cells[1]) <= 2  # 2 sessions of 40 steps
    assert 0 <= int(cells[2]) <= 2


def test_template_errors_name_the_page_and_the_expression(tmp_path: Path) -> None:
    """A field that reads what the run did not write is an error naming where and what."""
    outputs = results.PageOutputs(tmp_path, {Path("run.json"): results.Data(steps=3)}, "")
    body = "<!-- template\n| {run.steps} | {run.sessions} |\n-->\n"
    with pytest.raises(results.ResultsError, match=r"page\.md#t: \{run\.sessions\}: "
                       r"AttributeError: no key 'sessions'; keys: steps"):
        results.regenerate_page_region(tmp_path / "page.md", body, outputs, "page.md#t")
    with pytest.raises(results.ResultsError, match="does-not-exist"):
        results.regenerate_page_region(
            tmp_path / "page.md", "<!-- template\nfigure: does-not-exist.png x.png\n-->\n",
            outputs, "page.md#t")


def test_the_live_latency_page_regenerates(tmp_path: Path, monkeypatch) -> None:
    """A real results page, test-sized: its benches run (a service over loopback Zenoh) and
    its table is rewritten from their JSON."""
    _reader_environment(monkeypatch, tmp_path / "data")
    page = tmp_path / "live-latency.md"
    shutil.copyfile(results.RESULTS / "live-latency.md", page)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    results.regenerate_page(page, None, scratch, test_sized=True)
    text = page.read_text()
    region = text[text.index("<!-- results: page live-latency"):]
    rendered = region[region.index("*Produced on"):region.index("<!-- /results -->")]
    assert "test-sized runs" in rendered
    rows = [results._cells(line) for line in rendered.splitlines() if line.startswith("| ")]
    assert rows[0][0] == "bench" and rows[1][0] == "3 x 3 grid, 2 session(s)", rows
    assert rows[2][0] == "2 sessions, random phases", rows
    median, p99, maximum = (float(x.strip("*")) for x in rows[1][1].split(" / "))
    assert 0 < median <= p99 <= maximum


def test_json_names_follow_their_paths(tmp_path: Path) -> None:
    """A file's template name is its path without ``.json``, other characters as ``_``."""
    (tmp_path / "work" / "report").mkdir(parents=True)
    outputs = results.PageOutputs(tmp_path, {Path("report/metrics.json"): {},
                                             Path("grid-5.json"): {}}, "")
    assert set(outputs.names) == {"report_metrics", "grid_5"}
    assert json.dumps(results.Data(a=1)) == '{"a": 1}'


def test_a_failing_page_is_left_and_the_others_regenerated(tmp_path: Path, monkeypatch,
                                                           capsys) -> None:
    """``make results`` goes on past a page whose commands fail (hours of other pages are
    not lost), leaves that page as it was, names it, and exits 1."""
    _reader_environment(monkeypatch, tmp_path / "data")
    region = ("<!-- results: page r -->\n<!-- template\n| {answer.value} |\n-->\n| old |\n"
              "<!-- /results -->\n")
    broken = tmp_path / "broken.md"
    broken.write_text(f"```sh\ncfbci simulate --steps many\n```\n\n{region}")
    fine = tmp_path / "fine.md"
    fine.write_text("```python\nimport json\njson.dump({'value': 42}, open('answer.json', 'w'))\n"
                    f"```\n\n{region}")
    before = broken.read_text()
    assert results.main([str(broken), str(fine)]) == 1
    assert broken.read_text() == before
    assert "| 42 |" in fine.read_text() and "| old |" not in fine.read_text()
    assert "FAILED, left as it was: " + str(broken) in capsys.readouterr().err


def test_a_region_alone_runs_only_the_blocks_above_it(tmp_path: Path, monkeypatch) -> None:
    """``PAGE#ID`` of a region marked ``blocks: above`` runs only the blocks between the
    region before it and itself (a failing block elsewhere on the page is not run)."""
    _reader_environment(monkeypatch, tmp_path / "data")
    page = tmp_path / "page.md"
    page.write_text("""\
```sh
exit 1  # a long bench, not needed here
```

<!-- results: page first -->
<!-- template
| {missing} |
-->
<!-- /results -->

```python
import json
json.dump({"value": 7}, open("seven.json", "w"))
```

<!-- results: page second -->
<!-- template
blocks: above
| {seven.value} |
-->
| old |
<!-- /results -->
""")
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    results.regenerate_page(page, "second", scratch)
    text = page.read_text()
    assert "| 7 |" in text and "| old |" not in text and "| {missing} |" in text
    with pytest.raises(ExampleError, match="exit status 1"):
        results.regenerate_page(page, None, scratch)  # the whole page runs every block
