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
        "steps", "sessions", "interval_s", "grid", "tasks", "burst", "end_to_end_ms",
        "update_ms", "queue_ms", "transport_ms", "steady_end_to_end_ms", "non_learner_share",
        "worst_session", "per_session",
    }
    assert (report["steps"], report["sessions"], report["tasks"]) == (20, 1, 25)
    assert report["interval_s"] == 0.0  # one session: as fast as possible
    assert report["steady_end_to_end_ms"]["max"] <= report["end_to_end_ms"]["max"]
    [only] = report["per_session"]
    for key in ("end_to_end_ms", "update_ms", "queue_ms", "transport_ms"):
        assert only[key] == report[key]  # one session: its figures are the pooled ones
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
    # Its phases are random in [0, interval); the burst run's all zero.
    out = tmp_path / "latency.json"
    assert main(["bench", "latency", "--steps", "5", "--sessions", "9", "--interval", "0.02",
                 "--grid", "3", "--burst", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert (report["sessions"], report["interval_s"], report["tasks"]) == (9, 0.02, 9)
    assert report["queue_ms"]["max"] >= report["queue_ms"]["median"] >= 0
    assert report["end_to_end_ms"]["median"] > report["update_ms"]["median"] > 0
    phases = [row["phase_s"] for row in report["per_session"]]
    assert all(0 <= phase < 0.02 for phase in phases) and len(set(phases)) == 9
    worst = max(report["per_session"], key=lambda row: row["end_to_end_ms"]["p99"])
    assert report["worst_session"] == worst["session"]
    assert max(row["end_to_end_ms"]["max"] for row in report["per_session"]) == (
        report["end_to_end_ms"]["max"]
    )
    burst = report["burst_run"]
    assert burst["burst"] and not report["burst"]
    assert [row["phase_s"] for row in burst["per_session"]] == [0.0] * 9
    out_text = capsys.readouterr().out
    assert "9 session(s) x 5 epochs" in out_text and "all starting at once" in out_text
    assert "worst session" in out_text
