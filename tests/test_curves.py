"""``cfbci curves``: mean (or median) curves of per-session series of simulate runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cfbci.cli import main
from cfbci.offline.curves import plot_curves, run_series

PNG = b"\x89PNG\r\n\x1a\n"


def _run(path: Path, series: np.ndarray, steps: list[int] | None) -> Path:
    sessions = []
    for seed, row in enumerate(series):
        session = {"seed": seed, "taught_likelihood": row.tolist()}
        if steps is not None:
            session["update_steps"] = steps
        sessions.append(session)
    path.write_text(json.dumps({"sessions": sessions}))
    return path


def test_the_curves_are_the_sessions_mean_and_median(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    fast = rng.uniform(0.5, 1.0, size=(8, 4))
    slow = rng.uniform(0.0, 0.5, size=(8, 4))
    runs = {
        name: run_series(_run(tmp_path / f"{name}.json", data, [15, 30, 45, 60]),
                         "taught_likelihood")
        for name, data in (("fast", fast), ("slow", slow))
    }
    assert runs["fast"][0].tolist() == [15, 30, 45, 60]
    rows = plot_curves(runs, "taught_likelihood", "mean", tmp_path / "mean.png")
    assert rows[0]["mean"] == pytest.approx(fast.mean(axis=0).tolist())
    assert rows[1]["mean"] == pytest.approx(slow.mean(axis=0).tolist())
    rows = plot_curves(runs, "taught_likelihood", "median", tmp_path / "median.png", log_y=True)
    assert rows[0]["median"] == pytest.approx(np.median(fast, axis=0).tolist())
    for name in ("mean.png", "median.png"):
        assert (tmp_path / name).read_bytes()[:8] == PNG


def test_a_continuous_series_is_every_tenth_step(tmp_path: Path) -> None:
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"sessions": [{"distance_every_10": [0.3, 0.1, 0.01]}]}))
    steps, series = run_series(path, "distance_every_10")
    assert steps.tolist() == [10, 20, 30] and series.tolist() == [[0.3, 0.1, 0.01]]


def test_the_command_reads_real_puddle_runs(tmp_path: Path, capsys) -> None:
    for exploration in ("planning", "random"):
        assert main(["simulate", "--world", "puddle", "--exploration", exploration,
                     "--seeds", "2", "--steps", "30", "--json",
                     str(tmp_path / f"{exploration}.json")]) == 0
    out = tmp_path / "puddle.png"
    assert main(["curves", str(tmp_path / "planning.json"), str(tmp_path / "random.json"),
                 "--metric", "taught_likelihood", "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == PNG
    assert "2 runs, taught_likelihood, mean" in capsys.readouterr().out
    steps, series = run_series(tmp_path / "planning.json", "taught_likelihood")
    assert steps.tolist() == [15, 30] and series.shape == (2, 2)


@pytest.mark.parametrize(
    ("sessions", "message"),
    [
        ([], "no 'sessions' list"),
        ([{"taught_likelihood": [0.1, None], "update_steps": [15, 30]}], "session 0 has no"),
        ([{"taught_likelihood": [0.1], "update_steps": [15]},
          {"taught_likelihood": [0.1, 0.2], "update_steps": [15, 30]}], "differ in length"),
        ([{"taught_likelihood": [0.1, 0.2], "update_steps": [15]}], "differ in length"),
    ],
)
def test_bad_runs_are_refused_naming_the_file(tmp_path: Path, sessions, message) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"sessions": sessions}))
    with pytest.raises(ValueError, match=message) as error:
        run_series(bad, "taught_likelihood")
    assert str(bad) in str(error.value)


def test_runs_with_one_name_are_refused(tmp_path: Path, capsys) -> None:
    (tmp_path / "a").mkdir()
    first = _run(tmp_path / "run.json", np.ones((2, 2)), [15, 30])
    second = _run(tmp_path / "a" / "run.json", np.ones((2, 2)), [15, 30])
    assert main(["curves", str(first), str(second), "--metric", "taught_likelihood",
                 "--out", str(tmp_path / "x.png")]) == 2
    assert "same file name" in capsys.readouterr().err
