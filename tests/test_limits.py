"""The service's limits and rejections, against a real service process over loopback Zenoh:
a session that cannot be run gets ``session_rejected`` naming its config; an idle session
is ended and its recording closed; a re-sent config is answered again."""

from __future__ import annotations

import argparse
import queue
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zenoh
from live import SPAWN, TIMEOUT, answering_challenges

from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.world import GridWorld
from calibration_free.worlds import make_world
from cfbci.bench.memory_probe import MemoryCase, measure
from cfbci.cli.service import add_limit_options, limits_from_args
from cfbci.service import serve, unfinished
from cfbci.service.limits import ServiceLimits, world_memory_bytes
from replay.recording import read_recording
from session import memory as memory_estimate
from wire import protocol
from wire.transport import Outbox, Pump, Received, wait_for_subscribers
from wire.zenoh_config import free_tcp_endpoint, peer_config

LIMITS = ServiceLimits(
    max_sessions=2, idle_timeout=2.0, start_timeout=2.0, subscriber_timeout=1.0, max_grid=6,
    max_steps=100, max_session_mb=2.0,
)


def _config(**changes: object) -> dict:
    return {
        "seed": 0, "world": "grid", "grid": 3, "frame": "feedback", "steps": 10, "learner": {},
        "dataset": {},
        "signal": "features", **changes,
    }


def _next(inbox: queue.SimpleQueue[Received], match: Callable[[protocol.Message], bool]):
    while True:
        message = protocol.decode(inbox.get(timeout=TIMEOUT).data)
        if match(message):
            return message


def _event(sid: str, kind: str) -> Callable[[protocol.Message], bool]:
    return lambda m: m.session == sid and m.fields["event"] == kind


def test_the_cli_flags_give_the_limits_and_bad_ones_are_refused() -> None:
    parser = argparse.ArgumentParser()
    add_limit_options(parser)
    assert limits_from_args(parser.parse_args([])) == ServiceLimits()
    limits = limits_from_args(parser.parse_args(["--max-sessions", "3", "--idle-timeout", "9.5"]))
    assert (limits.max_sessions, limits.idle_timeout) == (3, 9.5)
    with pytest.raises(ValueError, match="max_sessions must be positive"):
        ServiceLimits(max_sessions=0)


def test_the_memory_estimate_grows_with_world_steps_features_classes_and_decoder() -> None:
    def estimate(world: object = None, steps: int = 100, d: int = 57, **learner: object) -> int:
        return world_memory_bytes(
            world or GridWorld(5), LearnerConfig(**learner), steps, d  # type: ignore[arg-type]
        )

    base = estimate()
    assert estimate(GridWorld(6)) > base
    assert estimate(steps=200) > base
    assert estimate(d=58) > base
    assert estimate(frame="guidance") > base  # four classes
    assert estimate(make_world("pick-and-place")) > estimate(GridWorld(20)) > base
    # per-class scatter matrices: O(T F K d^2) against the pooled O(T F K d)
    assert estimate(decoder="student_t") > 5 * base
    assert estimate(decoder="gaussian", d=4) < estimate(decoder="gaussian", d=8)
    assert estimate(likelihood="bhattacharyya") > 3 * base  # keeps per-class scatters too
    assert estimate(d=0) < base  # at the config: no feature term yet


def test_the_memory_estimate_counts_the_row_indicators_the_planner_keeps() -> None:
    """On a 20 x 20 grid in feedback the information planner keeps one float per task and
    state-action between steps (6.4 MB): the estimate's resident tables count exactly what
    a learner holds; on 50 x 50 the indicators (250 MB) exceed the budget and are not kept."""
    def tables(world: GridWorld, planner: str) -> int:
        return memory_estimate.estimate(world, LearnerConfig(planner=planner), 100, 8).world_tables

    world = GridWorld(20)
    learner = CalibrationFreeLearner(world, LearnerConfig(), rng=0)
    rng = np.random.default_rng(0)
    state = 0
    for _ in range(15):  # past the random warm-up: the planner runs
        action = learner.propose(state).action
        learner.observe(state, action, rng.normal(size=8) + (action == 0))
        state = world.step(state, action)
    learner.propose(state)
    kept = learner._planner._kept_indicators
    assert kept is not None
    held = sum(indicator.nbytes for _, _, indicators in kept for indicator in indicators)
    assert held == tables(world, "information") - tables(world, "random") == 8 * 400 * 2000
    assert tables(GridWorld(50), "information") == tables(GridWorld(50), "random")


#: Small real sessions, measured in a fresh process each (peak resident growth, the
#: learner stepped as the service steps it). Each commits several MiB, so that the
#: estimate's constant overhead (1 MiB) does not decide the ratio.
MEASURED = (
    MemoryCase("pick-and-place", steps=20, features=8),  # value iteration's first epoch
    MemoryCase("grid", 10, steps=30, features=20, learner={"decoder": "student_t"}),
    MemoryCase("grid", 8, steps=150, features=40, learner={"frame": "guidance"}),
    MemoryCase("line", steps=60, features=60,
               learner={"frame": "guidance", "decoder": "gaussian"}),
)


@pytest.mark.parametrize("case", MEASURED, ids=MemoryCase.describe)
def test_the_memory_estimate_bounds_a_real_session_within_2_5_times(case: MemoryCase) -> None:
    result = measure(case)
    assert result.measured_mib > 0.5  # the session was measured
    assert result.measured_mib <= result.estimate_mib <= 2.5 * result.measured_mib


def test_rejections_idle_timeout_and_a_re_sent_config(tmp_path: Path) -> None:
    endpoint, client_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    with zenoh.open(peer_config([client_endpoint], ())) as client, answering_challenges(client):
        pump = Pump(client, "cfbci/**/event", "event", inbox)
        service = SPAWN.Process(
            target=serve, args=([endpoint], [client_endpoint], tmp_path),
            kwargs={"limits": LIMITS},
        )
        service.start()
        try:
            outbox = Outbox(client)
            assert wait_for_subscribers(outbox.publisher("cfbci/a/config"), TIMEOUT)
            rejected = {
                "big": (_config(grid=7), "field 'grid' must be in 2..6"),
                "long": (_config(steps=101), "field 'steps' must be in 1..100"),
                # pick-and-place's tables alone (and their value iteration) exceed 2 MiB
                "heavy": ({k: v for k, v in _config(frame="guidance").items() if k != "grid"}
                          | {"world": "pick-and-place"}, "MiB"),
                "eps": (_config(learner={"eps": 0.9}), "bad config"),
            }
            for sid, (config, problem) in rejected.items():
                sent = outbox.send("config", sid, config)
                event = _next(inbox, _event(sid, "session_rejected"))
                assert problem in event.fields["message"]
                assert event.fields["config_t_ns"] == sent.t_ns

            # A running session, and its config sent again: answered, not rejected.
            first = outbox.send("config", "a", _config())
            started = _next(inbox, _event("a", "session_started"))
            assert started.fields["config_t_ns"] == first.t_ns
            outbox.repeat(first)
            again = _next(inbox, lambda m: m.session == "a")
            assert again.fields["event"] == "session_started"
            assert again.fields["config_t_ns"] == first.t_ns
            # Another config on its id is rejected under its own t_ns; "a" goes on.
            other = outbox.send("config", "a", _config(seed=1))
            event = _next(inbox, _event("a", "session_rejected"))
            assert event.fields["config_t_ns"] == other.t_ns != first.t_ns
            outbox.send("config", "b", _config())
            _next(inbox, _event("b", "session_started"))
            outbox.send("config", "c", _config())  # a third: over max_sessions
            assert "maximum of 2" in _next(inbox, _event("c", "session_rejected")).fields[
                "message"
            ]
            # No epoch within start_timeout: "a" is ended with a rejection naming its config.
            idle = _next(inbox, lambda m: m.session == "a" and m.fields["event"] != "info")
            assert idle.fields["event"] == "session_rejected"
            assert "no epoch within 2 s of the start" in idle.fields["message"]
            assert idle.fields["config_t_ns"] == first.t_ns
            # "b" (started after "a") is ended next: by then "a"'s recording was closed,
            # while the service still runs (it handles one thing at a time).
            _next(inbox, _event("b", "session_rejected"))
            recording = read_recording(tmp_path / "a.mcap")
            assert not recording.truncated and not unfinished(recording)
            outbox.close()
        finally:
            service.terminate()
            service.join(TIMEOUT)
            pump.close()
    assert service.exitcode == 0


def test_user_quotas_and_the_start_handshake(tmp_path: Path) -> None:
    """Sessions ``<user>/<name>`` count against their user's quota, not another's; a
    config starts only when its source answers the challenge: a wrong answer is an error
    and starts nothing, a listener that never answers holds no slot."""
    endpoint, client_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    limits = replace(LIMITS, max_sessions=3, user_sessions=1, start_timeout=60.0,
                     idle_timeout=60.0)
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    with zenoh.open(peer_config([client_endpoint], ())) as client:
        pump = Pump(client, "cfbci/**/event", "event", inbox)  # listens, answers nothing
        service = SPAWN.Process(
            target=serve, args=([endpoint], [client_endpoint], tmp_path),
            kwargs={"limits": limits},
        )
        service.start()
        try:
            outbox = Outbox(client)
            assert wait_for_subscribers(outbox.publisher("cfbci/u/a/config"), TIMEOUT)
            silent = outbox.send("config", "u/silent", _config())
            assert _next(inbox, _event("u/silent", "session_pending")).fields[
                "config_t_ns"] == silent.t_ns
            rejected = _next(inbox, _event("u/silent", "session_rejected"))
            assert "answered its challenge" in rejected.fields["message"]
            with answering_challenges(client):
                outbox.send("config", "u/a", _config())
                _next(inbox, _event("u/a", "session_started"))
                outbox.send("config", "u/b", _config())  # over user u's quota of 1
                quota = _next(inbox, _event("u/b", "session_rejected")).fields["message"]
                assert "user 'u' runs its maximum of 1 sessions" in quota
                outbox.send("config", "v/a", _config())  # another user: starts
                _next(inbox, _event("v/a", "session_started"))
            # A wrong answer to a challenge is an error, and starts nothing.
            sent = outbox.send("config", "w/b", _config())
            pending = _next(inbox, _event("w/b", "session_pending"))
            outbox.send("ready", "w/b", {"config_t_ns": sent.t_ns, "challenge": "wrong"})
            error = _next(inbox, lambda m: m.session == "w/b" and m.fields["event"] == "error")
            assert "does not answer the session's challenge" in error.fields["message"]
            outbox.send("ready", "w/b", {"config_t_ns": sent.t_ns,
                                         "challenge": pending.fields["challenge"]})
            _next(inbox, _event("w/b", "session_started"))
            # Each user's sessions are recorded in its own folder.
            assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*.mcap")
                          ) == ["u/a.mcap", "v/a.mcap", "w/b.mcap"]
            outbox.close()
        finally:
            service.terminate()
            service.join(TIMEOUT)
            pump.close()
    assert service.exitcode == 0
