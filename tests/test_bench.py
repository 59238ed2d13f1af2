"""``cfbci bench update`` runs end to end and reports what it promises (no timing bounds)."""

import json

from cfbci.cli import main


def test_bench_update_reports_rows_with_the_naive_reference(tmp_path, capsys):
    out = tmp_path / "bench.json"
    code = main([
        "bench", "update", "--grids", "3", "4", "--histories", "12", "20",
        "--measured-steps", "3", "--naive-repeats", "1", "--json", str(out),
    ])
    assert code == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["tasks"], r["history"]) for r in rows] == [(9, 12), (9, 20), (16, 12), (16, 20)]
    for row in rows:
        assert set(row) == {
            "tasks", "history", "median_ms", "p99_ms", "naive_median_ms", "speedup"
        }
        assert 0 < row["median_ms"] <= row["p99_ms"]
    # The naive reference runs on the smallest grid given, and only there.
    smallest = [r for r in rows if r["tasks"] == 9]
    assert all(r["naive_median_ms"] > 0 and r["speedup"] > 0 for r in smallest)
    assert all(r["naive_median_ms"] is None for r in rows if r["tasks"] == 16)
    assert "speed-up" in capsys.readouterr().out


def test_allocator_tuning_is_safe_to_repeat():
    import sys

    from cfbci.memory import keep_freed_memory

    first, again = keep_freed_memory(), keep_freed_memory()
    assert first == again and isinstance(first, bool)
    if sys.platform.startswith("linux"):  # glibc: every mallopt call must be accepted
        assert first is True
