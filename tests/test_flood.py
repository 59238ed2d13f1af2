"""Isolation: a hostile client floods the service while a real session runs (the short
version of ``cfbci bench flood``: real processes, real Zenoh over loopback)."""

from __future__ import annotations

from pathlib import Path

from calibration_free.config import LearnerConfig
from calibration_free.world import GridWorld
from cfbci.bench.flood import attacks, bench_flood, largest_fitting_features, memory_bound
from cfbci.service.limits import ServiceLimits, world_memory_bytes
from wire import protocol

LIMITS = ServiceLimits(
    max_sessions=4, idle_timeout=30.0, max_grid=6, max_steps=400, max_features=1024,
    max_epoch_values=4096, max_session_mb=48.0,
)


def test_the_flood_covers_every_category_and_is_rejected_by_the_decoder() -> None:
    categories = {category for category, _, _ in attacks("real", LIMITS, 0)}
    assert categories == {
        "undecodable bytes", "lying header length", "huge numbers", "oversized payload",
        "garbage on the live session's keys", "unfollowed config",
    }
    for category, key_expr, data in attacks("real", LIMITS, 0):
        if category in ("unfollowed config", "garbage on the live session's keys"):
            continue  # well-formed: rejected by the service's session checks, if at all
        try:
            message = protocol.decode(data, key_expr=key_expr, max_bytes=LIMITS.max_message_bytes)
        except protocol.ProtocolError:
            continue
        # Well-formed but beyond the limits: a config of a 2**62 grid.
        assert category == "huge numbers" and message.fields["grid"] > LIMITS.max_grid


def test_the_maximum_sessions_fit_the_memory_limit_exactly() -> None:
    d = largest_fitting_features(LIMITS, LIMITS.max_grid, LIMITS.max_steps)
    budget = LIMITS.max_session_mb * 2**20
    assert 0 < d < LIMITS.max_features
    world, learner = GridWorld(LIMITS.max_grid), LearnerConfig()
    assert world_memory_bytes(world, learner, LIMITS.max_steps, d) <= budget
    assert world_memory_bytes(world, learner, LIMITS.max_steps, d + 1) > budget


def test_a_real_session_under_a_flood_decides_as_alone(tmp_path: Path) -> None:
    report = bench_flood(steps=40, grid=3, seed=2, rounds=300, limits=LIMITS,
                         record_dir=tmp_path)
    assert report.decisions_equal_simulation
    assert report.replay_identical
    assert report.exit_code == 0  # SIGTERM after the flood: a clean exit
    assert report.peak_rss_mb <= memory_bound(LIMITS)
    assert sum(report.sent.values()) >= 300  # the flood ran ...
    assert report.sent["maximum-size config"] == LIMITS.max_sessions - 1
    # The slot hog's configs, heard with a wildcard subscription but never answered,
    # started no session, and held no slot from the real one.
    assert report.sent["slot hog config"] == 4 * LIMITS.max_sessions
    assert report.sent["slot hog sessions started"] == 0
    assert report.queued_ms_max >= report.queued_ms_median >= 0  # ... and was measured
    # The flood's own sessions left their recordings; the one fed an epoch over the
    # memory limit was rejected at it.
    assert (tmp_path / "real.mcap").exists()
