"""What ``cfbci simulate --frame hypotheses`` prints: tables a reader can read, not a dict."""

from __future__ import annotations

import json
import re
from pathlib import Path

from cfbci.cli import main


def test_frame_hypotheses_print_tables_with_explained_rows(tmp_path: Path, capsys) -> None:
    """Both tables, every group, the checkpoint steps as columns, each row explained; the
    printed figures are the JSON summary's."""
    out = tmp_path / "run.json"
    status = main(["simulate", "--world", "line", "--frame", "hypotheses", "--synthetic",
                   "gaussian", "--dims", "2", "--seeds", "2", "--steps", "31", "--jobs", "1",
                   "--json", str(out)])
    printed = capsys.readouterr().out
    assert status == 0
    assert "{'" not in printed and "'21'" not in printed  # no Python dict
    for label in ("all sessions", "feedback teacher", "guidance teacher", "decided",
                  "first decision right", "teacher's frame won", "user's pair by step 100",
                  "W > 0.9 by step 100", "median first decision", "undecided"):
        assert label in printed, label
    for label in ("decided:", "first decision right:", "W > 0.9 by step 100:", "W: a pair's"):
        assert re.search(rf"^{re.escape(label)} ", printed, re.MULTILINE), label
    summary = json.loads(out.read_text())["summary"]
    header = next(line for line in printed.splitlines() if " 21 " in line and " 31 " in line)
    assert header  # the checkpoints within 31 steps are the columns
    row = [line for line in printed.splitlines() if line.startswith("│ all sessions")][-1]
    for step in ("21", "31"):
        assert f"{summary['mean_user_pair_w'][step]:.3f}" in row
