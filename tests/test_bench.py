"""``cfbci bench update`` and ``bench simulate`` run end to end and report what they
promise (no timing bounds)."""

import json

import numpy as np

from cfbci.bench.steps import NAIVE_TASKS, naive_slice
from cfbci.cli import main


def test_bench_update_reports_rows_with_the_naive_reference(tmp_path, capsys):
    out = tmp_path / "bench.json"
    code = main([
        "bench", "update", "--grids", "3", "6", "--histories", "12", "20",
        "--measured-steps", "3", "--naive-repeats", "1", "--continuous-history", "20",
        "--json", str(out),
    ])
    assert code == 0
    report = json.loads(out.read_text())
    rows = report["rows"]
    assert [(r["tasks"], r["history"]) for r in rows] == [(9, 12), (9, 20), (36, 12), (36, 20)]
    for row in rows:
        assert set(row) == {
            "tasks", "history", "median_ms", "p99_ms", "peak_memory_mb", "naive_median_ms",
            "naive_measured_tasks", "speedup",
        }
        assert 0 < row["median_ms"] <= row["p99_ms"]
        assert row["naive_median_ms"] > 0 and row["speedup"] > 0
        assert row["peak_memory_mb"] > 10  # an interpreter with numpy at least
    # Measured on every task of the small grid, on a 25-task slice of the larger one.
    assert [r["naive_measured_tasks"] for r in rows] == [9, 9, NAIVE_TASKS, NAIVE_TASKS]
    # The continuous-goal row: 3 steps from a history of 20 signals, default pool.
    continuous = report["continuous"]
    assert (continuous["history"], continuous["particles"], continuous["candidates"]) == (
        20, 50, 1000
    )
    assert 0 < continuous["median_ms"] <= continuous["p99_ms"]
    assert continuous["cpu_median_ms"] > 0
    printed = capsys.readouterr().out
    assert "speed-up" in printed and "extrapolated linearly" in printed
    assert "continuous-goal step: 50 particles x 20 sampled classifiers" in printed
    assert "share of the action interval of 3 s" in printed


def test_naive_slice_is_every_task_up_to_25_then_evenly_spaced():
    assert naive_slice(9).tolist() == list(range(9))
    assert naive_slice(25).tolist() == list(range(25))
    big = naive_slice(400)
    assert len(big) == NAIVE_TASKS and big[0] == 0 and big[-1] == 399
    assert np.all(np.diff(big) > 0)


def test_bench_simulate_reports_the_realtime_factor(tmp_path, capsys):
    rng = np.random.default_rng(0)
    labels = np.arange(120) % 2
    dataset = tmp_path / "data.npz"
    np.savez(dataset, features=rng.normal(size=(120, 4)) + labels[:, None], labels=labels)
    out = tmp_path / "simulate.json"
    code = main([
        "bench", "simulate", "--dataset", str(dataset), "--seeds", "2", "--steps", "30",
        "--json", str(out),
    ])
    assert code == 0
    report = json.loads(out.read_text())
    assert [s["seed"] for s in report["sessions"]] == [0, 1]
    for session in report["sessions"]:
        assert session["wall_s"] > 0
        assert session["realtime_factor"] == 30 * 3.0 / session["wall_s"]
    factors = [s["realtime_factor"] for s in report["sessions"]]
    assert report["realtime_factor"] == np.median(factors)
    assert "faster than real time" in capsys.readouterr().out


def _separable_dataset(path, shift):
    rng = np.random.default_rng(0)
    labels = np.arange(120) % 2
    np.savez(path, features=rng.normal(size=(120, 4)) + shift * labels[:, None], labels=labels)
    return path


def test_bench_simulate_prior_times_both_arms_on_the_same_steps(tmp_path, capsys):
    dataset = _separable_dataset(tmp_path / "data.npz", 2.0)
    out = tmp_path / "prior.json"
    code = main([
        "bench", "simulate", "--dataset", str(dataset), "--seeds", "2", "--steps", "30",
        "--prior", "--json", str(out),
    ])
    assert code == 0
    report = json.loads(out.read_text())
    arms = report["arms"]
    assert list(arms) == ["scratch", "prior"]
    for arm in arms.values():
        # The same users' day-2 sessions, every step timed in both arms.
        assert [(s["seed"], s["steps"]) for s in arm["sessions"]] == [(0, 30), (1, 30)]
        assert arm["steps"] == 60
        ms = arm["step_ms"]
        assert 0 < ms["p10"] <= ms["median"] <= ms["p90"] <= ms["p99"]
        assert arm["start_ms"] > 0
    assert all(s["decision"] is None for s in arms["scratch"]["sessions"])
    # The prior arm's learner is the returning user's: the prior check decided or is testing.
    assert all(s["decision"]["outcome"] in ("testing", "trusted", "fallen back")
               for s in arms["prior"]["sessions"])
    ratio = report["ratio"]
    assert ratio["median"] == arms["prior"]["step_ms"]["median"] / arms["scratch"]["step_ms"][
        "median"]
    assert ratio["per_seed"] == [
        p["median_ms"] / s["median_ms"]
        for s, p in zip(arms["scratch"]["sessions"], arms["prior"]["sessions"], strict=True)
    ]
    assert (ratio["min"], ratio["max"]) == (min(ratio["per_seed"]), max(ratio["per_seed"]))
    printed = capsys.readouterr().out
    assert "prior / scratch per step:" in printed and "the prior check at the end:" in printed


def test_bench_simulate_prior_says_why_it_has_no_prior(tmp_path, capsys):
    dataset = _separable_dataset(tmp_path / "data.npz", 0.0)  # no target in 10 steps
    base = ["bench", "simulate", "--dataset", str(dataset), "--seeds", "1", "--prior"]
    assert main([*base, "--steps", "10"]) == 2
    assert "seed 0's day-1 session of 10 steps declared fewer than two targets" in (
        capsys.readouterr().err)
    assert main([*base, "--steps", "10", "--frame", "guidance"]) == 2
    assert "day 1 is simulated in the feedback frame" in capsys.readouterr().err


def test_allocator_tuning_is_safe_to_repeat():
    import sys

    from cfbci.memory import keep_freed_memory

    first, again = keep_freed_memory(), keep_freed_memory()
    assert first == again and isinstance(first, bool)
    if sys.platform.startswith("linux"):  # glibc: every mallopt call must be accepted
        assert first is True
