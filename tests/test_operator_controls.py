"""The operator's commands (docs/protocol.md, "Operator controls") on live sessions: real
Zenoh on loopback, a real service and simulated source in spawned processes, ``cfbci
control`` and the browser view's operator page in headless Chromium.

A pause lasts longer than the service's idle timeout on purpose: that the session
survives it is what is tested (the wait is the pause, not a synchronisation). Every other
wait is for a message, with a timeout that only guards against a hang.
"""

from __future__ import annotations

import queue
import time
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import pytest
import zenoh
from live import SPAWN, TIMEOUT

from acquisition.simulated_source import SourceSettings, SourceSummary, run_source
from acquisition.sources import DataSpec
from calibration_free.streams import StepRecord
from cfbci.cli import main
from cfbci.offline.simulation import SessionConfig, run_session
from cfbci.service import serve
from cfbci.service.limits import ServiceLimits
from cfbci.service.process import spawned
from replay.recording import read_recording
from replay.rerun import replay_check
from wire import protocol
from wire.operator import send_command
from wire.transport import Pump, Received
from wire.zenoh_config import free_tcp_endpoint, peer_config

STEPS, GRID, SEED = 40, 3, 3
IDLE = 1.0  # the service's idle and start timeouts, s: a pause lasts 3 of them
LIMITS = ServiceLimits(idle_timeout=IDLE, start_timeout=30.0)
INTERVAL = 0.1  # the source's wait between a move and its answer, s


def simulated(seed: int) -> list[StepRecord]:
    """The trace of ``cfbci simulate`` for the seed (the unpaused session's decisions)."""
    trace: list[StepRecord] = []
    run_session(seed, SessionConfig(steps=STEPS, grid=GRID), DataSpec().resolve("feedback"),
                trace.append)
    return trace


@contextmanager
def service(record_dir: Path, connect: tuple[str, ...] = ()) -> Iterator[str]:
    """A service with short timeouts (`LIMITS`) in a spawned process: its endpoint."""
    endpoint = free_tcp_endpoint()
    with spawned(serve, [endpoint], list(connect), record_dir, limits=LIMITS):
        yield endpoint


@contextmanager
def source(sid: str, endpoint: str) -> Iterator[Future[SourceSummary]]:
    """The simulated source of session ``sid`` in a spawned process; if the test fails
    meanwhile, the operator ends the session, so that the source ends too."""
    settings = SourceSettings(sid, seed=SEED, steps=STEPS, grid=GRID, interval=INTERVAL)
    with ProcessPoolExecutor(1, mp_context=SPAWN) as pool:
        try:
            yield pool.submit(run_source, settings, [], [endpoint])
        except BaseException:
            with zenoh.open(peer_config((), [endpoint])) as session, suppress(Exception):
                send_command(session, sid, "end")
            raise


class Watch:
    """The moves and events of one session, as the service published them."""

    def __init__(self, session: zenoh.Session, sid: str) -> None:
        self.inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
        self.pumps = [Pump(session, protocol.key(sid, kind), kind, self.inbox)
                      for kind in ("move", "event")]
        self.moves: list[int] = []
        self.events: list[dict[str, Any]] = []

    def take(self, timeout: float) -> bool:
        """Take one message in (False: none came within ``timeout`` s)."""
        try:
            received = self.inbox.get(timeout=max(timeout, 0))
        except queue.Empty:
            return False
        message = protocol.decode(received.data, key_expr=received.key_expr)
        if message.kind == "move":
            self.moves.append(message.fields["step"])
        else:
            self.events.append(message.fields)
        return True

    def until_move(self, step: int) -> None:
        while not self.moves or self.moves[-1] < step:
            assert self.take(TIMEOUT), f"no move of step {step}"

    def close(self) -> None:
        for pump in self.pumps:
            pump.close()


@pytest.fixture
def operator() -> Iterator[list[zenoh.Session]]:
    """Zenoh sessions the test opens (closed after it)."""
    sessions: list[zenoh.Session] = []
    yield sessions
    for session in sessions:
        session.close()


def _cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    status = main(["control", *args])
    return status, capsys.readouterr().out


def test_a_pause_longer_than_the_idle_timeout_holds_the_session_and_it_completes_as_simulated(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], operator: list[zenoh.Session],
) -> None:
    sid = "lab-pause"
    with service(tmp_path) as endpoint, source(sid, endpoint) as future:
        session = zenoh.open(peer_config((), [endpoint]))
        operator.append(session)
        watch = Watch(session, sid)
        watch.until_move(3)
        status, out = _cli(capsys, "pause", sid, "--connect", endpoint, "--json")
        assert status == 0 and '"session_paused"' in out
        while not any(e["event"] == "session_paused" for e in watch.events):
            assert watch.take(TIMEOUT)
        paused = next(e for e in watch.events if e["event"] == "session_paused")
        step = paused["step"]
        # Pause three idle timeouts long: the session neither ends nor moves on.
        until = time.monotonic() + 3 * IDLE
        while watch.take(until - time.monotonic()):
            pass
        assert max(watch.moves) == step
        assert not [e for e in watch.events if e["event"] in ("session_rejected",
                                                               "session_ended")]
        # A second pause, a target that is no cell: refused, the session untouched.
        with pytest.raises(ValueError, match="paused already"):
            send_command(session, sid, "pause")
        with pytest.raises(ValueError, match="no task of the session's world"):
            send_command(session, sid, "target", GRID * GRID)
        target = 4  # the cell the subject says they chose
        marked = send_command(session, sid, "target", target)
        assert (marked["event"], marked["target"], marked["step"]) == (
            "target_marked", target, step)
        status, out = _cli(capsys, "resume", sid, "--connect", endpoint)
        assert status == 0 and out.startswith("session_resumed: resumed by the operator")
        summary = future.result(TIMEOUT)
        with pytest.raises(ValueError, match="not running"):
            send_command(session, sid, "resume")
        watch.close()

    assert summary.records == simulated(SEED)  # every decision as without the pause
    path = tmp_path / f"{sid}.mcap"
    recording = read_recording(path)
    logged = [(m["event"], m.get("step"), m.get("target"))
              for _, m in recording.messages["/event"] if "step" in m]
    assert logged == [("session_paused", step, None), ("target_marked", step, target),
                      ("session_resumed", step, None)]
    texts = [m["message"] for _, m in recording.messages["/log"]]
    assert any(t.startswith("session_paused: paused by the operator") for t in texts)
    result = replay_check(path)
    assert result.divergence is None and (result.moves, result.states) == (STEPS, STEPS + 1)
    assert [m["event"] for _, m in recording.messages["/event"]][-1] == "session_ended"


def test_the_operator_ends_a_session_early_and_its_recording_replays(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], operator: list[zenoh.Session],
) -> None:
    sid = "lab-end"
    with service(tmp_path) as endpoint, source(sid, endpoint) as future:
        session = zenoh.open(peer_config((), [endpoint]))
        operator.append(session)
        watch = Watch(session, sid)
        watch.until_move(8)
        status, out = _cli(capsys, "end", sid, "--connect", endpoint)
        assert status == 0 and "ended by the operator" in out
        summary = future.result(TIMEOUT)  # the source ends, without an error
        watch.close()
    recording = read_recording(tmp_path / f"{sid}.mcap")
    last = recording.messages["/event"][-1][1]
    ended = last["step"]  # the last move's step: its epoch was not taken
    assert last["event"] == "session_ended" and 8 <= ended < STEPS
    assert summary.steps in (ended - 1, ended)  # the last move shown before the end, or not
    assert summary.records == simulated(SEED)[: summary.steps]
    result = replay_check(tmp_path / f"{sid}.mcap")
    assert result.divergence is None and (result.moves, result.states) == (ended, ended)


def test_cfbci_control_refuses_bad_input_with_a_message(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["control", "pause", "bad id", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "session id" in capsys.readouterr().err
    assert main(["control", "pause", "s"]) == 2
    assert "--connect" in capsys.readouterr().err
