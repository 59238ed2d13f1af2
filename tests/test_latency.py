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
        "steps", "end_to_end_ms", "update_ms", "transport_ms", "non_learner_share"
    }
    assert report["steps"] == 20
    for key in ("end_to_end_ms", "update_ms", "transport_ms"):
        assert set(report[key]) == {"median", "p99", "max"}
        assert all(isinstance(value, float) for value in report[key].values())
    assert report["update_ms"]["median"] > 0
    assert report["end_to_end_ms"]["max"] >= report["end_to_end_ms"]["median"] > 0
    assert "non-learner share" in capsys.readouterr().out
