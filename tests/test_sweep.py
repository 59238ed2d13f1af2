"""``cfbci sweep`` on a real Dask cluster, and where jobs run (`cfbci.offline.parallel`)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from distributed import LocalCluster
from rich.console import Console

from acquisition.sources import DEFAULT_SYNTHETIC_ACCURACY, synthetic_features
from cfbci.cli import main
from cfbci.offline.parallel import Scheduler, run_parallel
from wire.zenoh_config import free_tcp_endpoint

STEPS, SIDE, SEEDS = 30, 3, 2
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def features_file(path: Path, seed: int) -> Path:
    """A features ``.npz`` dataset of synthetic ErrP features."""
    data = synthetic_features(DEFAULT_SYNTHETIC_ACCURACY, np.random.default_rng(seed))
    np.savez(path, features=data.features, labels=data.labels)
    return path


def test_a_sweep_on_an_existing_cluster_equals_simulate_per_cell(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The cross product (2 settings x 2 datasets x 2 seeds) runs on a Dask cluster joined
    by its scheduler's address; every cell's file is what `cfbci simulate --jobs 1` writes
    for that dataset and setting."""
    datasets = {"errp": features_file(tmp_path / "errp.npz", 3),
                "other": features_file(tmp_path / "other.npz", 4)}
    out = tmp_path / "sweep"
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0") as cluster:
        assert main([
            "sweep", "--grid", "shrinkage=0.2,0.5 beta=0.95", "--datasets",
            *map(str, datasets.values()), "--seeds", str(SEEDS), "--first-seed", "3",
            "--steps", str(STEPS), "--side", str(SIDE), "--set", "eps=0.15", "--out", str(out),
            "--scheduler", cluster.scheduler_address,
        ]) == 0
    printed = capsys.readouterr().out
    assert "8 sessions in" in printed and f"cluster at {cluster.scheduler_address}" in printed

    summary = json.loads((out / "summary.json").read_text())
    assert summary["grid"] == {"shrinkage": [0.2, 0.5], "beta": [0.95]}
    assert summary["sessions"] == 8 and summary["wall_time_s"] > 0
    names = [row["file"] for row in summary["cells"]]
    assert names == [
        "errp_shrinkage=0.2_beta=0.95.json", "errp_shrinkage=0.5_beta=0.95.json",
        "other_shrinkage=0.2_beta=0.95.json", "other_shrinkage=0.5_beta=0.95.json",
    ]
    for row in summary["cells"]:
        cell = json.loads((out / row["file"]).read_text())
        expected_path = tmp_path / f"simulate-{row['file']}"
        assert main([
            "simulate", "--dataset", str(datasets[row["dataset"]]), "--seeds", str(SEEDS),
            "--first-seed", "3", "--steps", str(STEPS), "--grid", str(SIDE), "--set",
            "eps=0.15", "--set", f"shrinkage={row['shrinkage']}", "--set", "beta=0.95",
            "--jobs", "1", "--json", str(expected_path),
        ]) == 0
        assert cell == json.loads(expected_path.read_text())
        assert cell["config"]["learner"]["shrinkage"] == row["shrinkage"]
        assert row["median_first_target_step"] == cell["summary"]["median_first_target_step"]
        assert row["sessions"] == SEEDS
    with (out / "summary.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    assert [r["file"] for r in rows] == names
    assert [float(r["wrong_target_rate"]) for r in rows] == [
        row["wrong_target_rate"] for row in summary["cells"]
    ]
    assert (out / "summary.png").read_bytes().startswith(PNG_MAGIC)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--grid", "shrinkage"], "KEY=V1,V2"),
        (["--grid", "shrinkage=0.2,"], "KEY=V1,V2"),
        (["--grid", "beta=0.9 beta=0.95"], "'beta' twice"),
        (["--grid", "colour=red,blue"], "unknown learner setting"),
        (["--grid", "beta=0.9,2"], "beta must be in"),
        (["--grid", "beta=0.9", "--set", "beta=0.95"], "both in --grid and in --set"),
        (["--grid", "beta=0.9", "--datasets", "synthetic", "synthetic"], "distinct name"),
        (["--grid", "beta=0.9", "--datasets", "/nonexistent/s4.mat"], "s4.mat: no such file"),
        (["--grid", "beta=0.9", "--scheduler", "cluster"], "tcp://HOST:PORT"),
    ],
)
def test_bad_sweeps_are_clear_errors_before_anything_runs(
    arguments: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    defaults = ["--datasets", "synthetic"] if "--datasets" not in arguments else []
    out = tmp_path / "out"
    code = main(["sweep", *defaults, *arguments, "--seeds", "1", "--steps", "5", "--jobs", "1",
                 "--out", str(out)])
    assert code == 2
    assert message in " ".join(capsys.readouterr().err.split())
    assert not out.exists()


def test_a_scheduler_that_does_not_answer_is_a_clear_error() -> None:
    address = "tcp://" + free_tcp_endpoint().removeprefix("tcp/")  # nothing listens there
    scheduler = Scheduler(address, connect_timeout=1.0)
    with pytest.raises(ValueError, match=f"--scheduler {address}: no Dask scheduler answered"):
        run_parallel(abs, [-1, -2], scheduler=scheduler, description="jobs", console=Console())


def test_where_jobs_run() -> None:
    assert Scheduler.from_options(None, 1).describe() == "this process"
    assert Scheduler.from_options(None, 3).describe() == "local cluster, 3 workers"
    assert Scheduler.from_options("local", 1).describe() == "local cluster, 1 worker"
    assert Scheduler.from_options("tcp://127.0.0.1:8786", 0).describe() == (
        "cluster at tcp://127.0.0.1:8786"
    )
    with pytest.raises(ValueError, match="--jobs must be 0"):
        Scheduler.from_options(None, -1)
