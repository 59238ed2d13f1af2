"""How ``cfbci source`` ends when its session does not run: one line on stderr and exit
status 1, as ``cfbci replay --publish`` and ``cfbci lsl-bridge`` end (the clients' loop,
`wire.client`).

The command runs in a process of its own, as a user runs it, over real Zenoh on loopback:
against a real service process that rejects its config, and against a peer that hears
its config but never answers. Synchronisation is by messages only; every wait has a
timeout that only guards against a hang.
"""

from __future__ import annotations

import logging
import math
import queue
import subprocess
import sys
import threading
from pathlib import Path

import zenoh
from live import TIMEOUT, service_process

from wire import protocol
from wire.client import Client
from wire.transport import Pump, Received
from wire.zenoh_config import free_tcp_endpoint, peer_config


def source_command(session: str, endpoint: str, *options: str) -> subprocess.CompletedProcess:
    """``cfbci source`` of a 5-step session connecting to ``endpoint``, run to its end."""
    return subprocess.run(
        [sys.executable, "-m", "cfbci.cli", "source", "--session", session, "--connect",
         endpoint, "--steps", "5", *options],
        capture_output=True, text=True, timeout=TIMEOUT,
    )


def test_a_rejected_session_ends_the_source_with_one_line_and_status_1(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    with service_process(endpoint, tmp_path):
        result = source_command("rejected", endpoint, "--grid", "11")  # the limit is 10
    assert result.returncode == 1
    (line,) = result.stderr.splitlines()
    assert line.startswith("error: the service rejected session 'rejected': ")
    assert "field 'grid' must be in 2..10; got 11" in line
    assert result.stdout == ""


def test_a_service_that_never_answers_ends_the_source_with_one_line_and_status_1() -> None:
    sid, endpoint = "unanswered", free_tcp_endpoint()
    configs: queue.SimpleQueue[Received] = queue.SimpleQueue()
    with zenoh.open(peer_config([endpoint], ())) as deaf:
        pump = Pump(deaf, protocol.key(sid, "config"), "config", configs)  # answers nothing
        try:
            result = source_command(sid, endpoint, "--timeout", "2")
            first, again = configs.get(timeout=TIMEOUT), configs.get(timeout=TIMEOUT)
        finally:
            pump.close()
    assert result.returncode == 1
    assert result.stderr.splitlines() == [
        f"error: session {sid!r}: no message from the service for 2 s (awaiting "
        "session_started)"
    ]
    assert again.data == first.data  # the config, re-sent unchanged while unanswered



class _Polls:
    """An answerer that counts its polls and would wait for the service for ever."""

    polls = 0

    def on_move(self, move: protocol.Message) -> None:
        raise AssertionError(f"no move expected; got {move}")

    def poll(self) -> float:
        self.polls += 1
        return math.inf


def test_a_wake_from_another_thread_ends_the_clients_wait_for_the_service() -> None:
    """The LSL bridge reads its streams in a thread that wakes the client's loop:
    `Client.wake` ends the loop's wait, though nothing is due (the config's re-sending is
    ``TIMEOUT`` away, and the peer subscribed to it never answers)."""
    sid, endpoint = "woken", free_tcp_endpoint()
    config = {"seed": 0, "world": "grid", "grid": 5, "frame": "feedback", "steps": 1,
              "learner": {}, "dataset": {}, "signal": "features"}
    with zenoh.open(peer_config([endpoint], ())) as peer:
        pump = Pump(peer, protocol.key(sid, "config"), "config", queue.SimpleQueue())
        try:
            with Client(peer, sid, logging.getLogger("test"), TIMEOUT, TIMEOUT) as client:
                answerer = _Polls()
                threading.Thread(target=client.wake).start()
                client.run(config, answerer, keep_running=lambda: answerer.polls < 1)
        finally:
            pump.close()
    assert answerer.polls == 1 and not client.started
