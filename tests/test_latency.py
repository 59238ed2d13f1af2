"""``cfbci bench latency`` runs end to end and reports what it promises (no timing bounds)."""

import json
from pathlib import Path

import pytest

from cfbci.cli import main


def test_bench_latency_reports_end_to_end_update_and_transport(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "latency.json"
    assert main(["bench", "latency", "--steps", "20", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert set(report) == {
        "steps", "sessions", "interval_s", "end_to_end_ms", "update_ms", "queued_ms",
        "transport_ms", "steady_end_to_end_ms", "non_learner_share",
    }
    assert (report["steps"], report["sessions"]) == (20, 1)
    assert report["steady_end_to_end_ms"]["max"] <= report["end_to_end_ms"]["max"]
    for key in ("end_to_end_ms", "update_ms", "queued_ms", "transport_ms"):
        assert set(report[key]) == {"median", "p99", "max"}
        assert all(isinstance(value, float) for value in report[key].values())
    assert report["update_ms"]["median"] > 0
    assert report["end_to_end_ms"]["max"] >= report["end_to_end_ms"]["median"] > 0
    assert "non-learner share" in capsys.readouterr().out


def test_bench_latency_runs_more_sessions_than_the_default_limit_on_one_service(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Nine sessions, one over the service's default maximum of 8: the bench raises it, and
    # every session's every epoch is timed (bench_latency raises otherwise).
    out = tmp_path / "latency.json"
    assert main(["bench", "latency", "--steps", "5", "--sessions", "9", "--interval", "0.02",
                 "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert (report["sessions"], report["interval_s"]) == (9, 0.02)
    assert report["queued_ms"]["max"] >= report["queued_ms"]["median"] >= 0
    assert report["end_to_end_ms"]["median"] > report["update_ms"]["median"] > 0
    assert "9 session(s) x 5 epochs" in capsys.readouterr().out
