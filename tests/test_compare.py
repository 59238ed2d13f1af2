"""``cfbci compare``: the one-sided Mann-Whitney test between two simulate runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cfbci.cli import main
from cfbci.offline.compare import rank_test


def _run(path: Path, values: list[object], metric: str = "final_distance") -> Path:
    sessions = [{"seed": seed, metric: value} for seed, value in enumerate(values)]
    path.write_text(json.dumps({"config": {}, "sessions": sessions}))
    return path


def test_a_run_whose_values_are_smaller_wins_the_one_sided_test(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    smaller = _run(tmp_path / "a.json", list(rng.uniform(0.0, 0.6, size=30)))
    larger = _run(tmp_path / "b.json", list(rng.uniform(0.4, 1.0, size=30)))
    test = rank_test(smaller, larger, "final_distance", "less")
    assert (test.n_a, test.n_b) == (30, 30)
    assert test.median_a < test.median_b
    assert test.p_value < 1e-3
    assert rank_test(smaller, larger, "final_distance", "greater").p_value > 0.999
    reverse = rank_test(larger, smaller, "final_distance", "less")
    assert reverse.p_value > 0.999
    # U of A < B and of B < A add up to n_a n_b.
    assert test.u_statistic + reverse.u_statistic == pytest.approx(30 * 30)


def test_two_draws_of_one_distribution_do_not_differ(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    a = _run(tmp_path / "a.json", list(rng.normal(size=40)))
    b = _run(tmp_path / "b.json", list(rng.normal(size=40)))
    assert rank_test(a, b, "final_distance", "two-sided").p_value > 0.05


def test_the_command_prints_the_test_and_writes_json(tmp_path: Path, capsys) -> None:
    a = _run(tmp_path / "a.json", [0.01, 0.02, 0.03, 0.015, 0.025])
    b = _run(tmp_path / "b.json", [0.2, 0.3, 0.1, 0.25, 0.15])
    out = tmp_path / "test.json"
    assert main(["compare", str(a), str(b), "--metric", "final_distance", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "Mann-Whitney U = 0.0" in printed and "one-sided, A < B" in printed
    written = json.loads(out.read_text())
    assert written["u_statistic"] == 0.0 and written["p_value"] < 0.01  # exact: 1/252


def test_a_real_simulate_json_is_read_and_a_missing_number_is_named(
    tmp_path: Path, capsys
) -> None:
    rng = np.random.default_rng(2)
    labels = np.arange(120) % 2
    dataset = tmp_path / "data.npz"
    np.savez(dataset, features=rng.normal(size=(120, 4)) + 2 * labels[:, None], labels=labels)
    run = tmp_path / "run.json"
    assert main(["simulate", "--dataset", str(dataset), "--seeds", "3", "--steps", "20",
                 "--json", str(run)]) == 0
    test = rank_test(run, run, "steps", "two-sided")
    assert (test.n_a, test.median_a, test.p_value) == (3, 20.0, 1.0)
    capsys.readouterr()
    assert main(["compare", str(run), str(run), "--metric", "final_distance"]) == 2
    error = capsys.readouterr().err
    assert "session 0 has no finite number 'final_distance'" in error
    assert "correct_targets" in error and "steps" in error  # the numbers it has


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("not json", "not a readable JSON file"),
        (json.dumps({"sessions": []}), "no 'sessions' list"),
        (json.dumps([1, 2]), "no 'sessions' list"),
        (json.dumps({"sessions": [3]}), "session 0 is not an object"),
        (json.dumps({"sessions": [{"final_distance": None}]}), "got None"),
        (json.dumps({"sessions": [{"final_distance": True}]}), "got True"),
        (json.dumps({"sessions": [{"final_distance": "0.1"}]}), "got '0.1'"),
    ],
)
def test_bad_files_are_refused_naming_the_file(tmp_path: Path, text: str, message: str) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    good = _run(tmp_path / "good.json", [0.1, 0.2])
    with pytest.raises(ValueError, match=message) as error:
        rank_test(good, bad, "final_distance", "less")
    assert str(bad) in str(error.value)


def test_a_nan_value_is_refused(tmp_path: Path) -> None:
    nan = tmp_path / "nan.json"
    nan.write_text('{"sessions": [{"final_distance": NaN}]}')
    good = _run(tmp_path / "good.json", [0.1, 0.2])
    with pytest.raises(ValueError, match="got nan"):
        rank_test(nan, good, "final_distance", "less")
