"""``cfbci simulate --world continuous|puddle``: the reports and the errors."""

from __future__ import annotations

import json
from pathlib import Path

from cfbci.cli import main


def test_a_continuous_world_report_gives_each_sessions_final_distance(tmp_path: Path) -> None:
    out = tmp_path / "continuous.json"
    argv = ["simulate", "--world", "continuous", "--synthetic", "gaussian", "--dims", "4",
            "--synthetic-accuracy", "0.95", "--seeds", "2", "--steps", "30", "--hypotheses", "8",
            "--jobs", "1", "--json", str(out)]
    assert main(argv) == 0
    report = json.loads(out.read_text())
    assert [s["seed"] for s in report["sessions"]] == [0, 1]
    for session in report["sessions"]:
        assert len(session["distance_every_10"]) == 3
        assert session["final_distance"] == session["distance_every_10"][-1]
        assert 0.0 <= session["final_distance"] <= 2**0.5
    assert report["config"]["sampling"] == "active"


def test_a_puddle_report_gives_the_taught_tasks_likelihood_per_update(tmp_path: Path) -> None:
    out = tmp_path / "puddle.json"
    argv = ["simulate", "--world", "puddle", "--exploration", "random", "--seeds", "1",
            "--steps", "30", "--jobs", "1", "--json", str(out)]
    assert main(argv) == 0
    (session,) = json.loads(out.read_text())["sessions"]
    assert session["update_steps"] == [15, 30]
    assert all(0.0 <= p <= 1.0 for p in session["taught_likelihood"])


def test_bad_plane_world_options_are_named(capsys) -> None:
    base = ["simulate", "--world", "continuous", "--synthetic", "gaussian", "--seeds", "1",
            "--steps", "5", "--jobs", "1"]
    assert main([*base, "--class-order", "0,1,1,2"]) == 2
    assert "--class-order must be a permutation" in capsys.readouterr().err
    assert main(["simulate", "--world", "puddle", "--dataset", "x.mat"]) == 2
    assert "leave --dataset and --synthetic out" in capsys.readouterr().err
    # On the grid the option was silently ignored: a "permuted" finger run gave the
    # dataset's order's sessions exactly.
    for world in ("grid", "puddle"):
        assert main(["simulate", "--world", world, "--class-order", "2,0,3,1", "--seeds", "1"]) == 2
        assert "--class-order is an option of --world continuous only" in capsys.readouterr().err
