"""Restart and resume: a service killed with SIGKILL mid-session and started again on the
same record directory resumes the session from its recording, and the session decides as
an uninterrupted one would (real processes, real Zenoh over loopback, a real kill)."""

from __future__ import annotations

import os
import queue
import signal
from collections import Counter
from pathlib import Path

import pytest
import zenoh
from live import SPAWN, TIMEOUT, rewrite, service_process
from test_pipeline import GRID, STEPS, simulated, source_process

from acquisition.simulated_source import SourceSettings, SourceSummary
from cfbci.cli import main
from cfbci.service import serve, unfinished
from replay.recording import decode_array, read_recording
from replay.rerun import replay_check
from wire import protocol
from wire.transport import Pump, Received, reliable_publisher, wait_for_subscribers
from wire.zenoh_config import free_tcp_endpoint, peer_config

KILL_AT = 25  # the service is killed once the move of this step has been seen


def run_with_a_kill(settings: SourceSettings, tmp_path: Path, steps: int) -> SourceSummary:
    """Run a session of ``steps`` steps whose service, recording to ``tmp_path``, is killed
    with SIGKILL once the move of `KILL_AT` has been seen and started again on the
    same directory and endpoints; the source's summary."""
    sid = settings.session
    endpoint, observer_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    # The source connects to the service's endpoint (as `cfbci source --connect` does) and
    # reconnects to the new service on it; the service connects to the observer.
    args = ([endpoint], [observer_endpoint], tmp_path)
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    with zenoh.open(peer_config([observer_endpoint], ())) as observer:
        moves = Pump(observer, protocol.key(sid, "move"), "move", inbox)
        first = SPAWN.Process(target=serve, args=args)
        first.start()
        with source_process(settings, endpoint) as future:
            try:
                while protocol.decode(inbox.get(timeout=TIMEOUT).data).fields["step"] < KILL_AT:
                    pass
            finally:
                assert first.pid is not None
                os.kill(first.pid, signal.SIGKILL)
                first.join(TIMEOUT)
            assert first.exitcode == -signal.SIGKILL
            killed = read_recording(tmp_path / f"{sid}.mcap")
            assert killed.truncated and unfinished(killed)
            # The kill may come between publishing a move and recording it.
            assert KILL_AT - 1 <= len(killed.messages["/move"]) < steps

            second = SPAWN.Process(target=serve, args=args)  # same directory, same endpoints
            second.start()
            try:
                summary = future.result(TIMEOUT)
            finally:
                second.terminate()
                second.join(TIMEOUT)
            assert second.exitcode == 0
        moves.close()
    return summary


def check_resumed_recording(path: Path, steps: int) -> None:
    """One file, every step once, a resumption event, and the offline re-run reproduces it
    exactly."""
    recording = read_recording(path)
    assert not recording.truncated and not unfinished(recording)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    for topic in ("/move", "/truth"):  # a truth re-sent after the restart may come late
        recorded = [m["step"] for _, m in recording.messages[topic]]
        assert sorted(recorded) == list(range(1, steps + 1)), topic
    assert [m["step"] for _, m in recording.messages["/features"]] == list(range(1, steps + 1))
    assert len(recording.messages["/epoch"]) == steps
    assert [m["n_signals"] for _, m in recording.messages["/state"]] == list(range(steps + 1))
    events = Counter(m["event"] for _, m in recording.messages["/event"])
    assert events["session_started"] == events["session_ended"] == 1
    assert any("resumed at step" in m["message"] for _, m in recording.messages["/event"])
    check = replay_check(path)
    assert check.divergence is None and check.moves == steps
    assert main(["replay", str(path)]) == 0


# The line world's seed pushes into its walls after the kill: the resumed service's
# stochastic moves must continue the world stream.
@pytest.mark.parametrize(("world", "seed"), [("grid", 4), ("line", 0)])
def test_a_killed_service_resumes_the_session_and_decides_as_if_never_killed(
    tmp_path: Path, world: str, seed: int
) -> None:
    settings = SourceSettings("resumed", seed=seed, steps=STEPS, grid=GRID, timeout=TIMEOUT,
                              resend_interval=0.2, world=world)
    summary = run_with_a_kill(settings, tmp_path, STEPS)
    trace, result = simulated(seed, world=world)
    if world == "line":  # both outcomes of a push into a wall, after the kill
        pushes = [(r.state, r.action) in ((0, "left"), (4, "right")) for r in trace]
        after = {r.next_state == r.state for r, push in zip(trace, pushes, strict=True)
                 if push and r.step > KILL_AT}
        assert after == {True, False}
    assert summary.records == trace  # every move, confident flag, best task and event
    assert (summary.correct_targets, summary.wrong_targets) == (
        result.correct_targets, result.wrong_targets,
    )
    check_resumed_recording(tmp_path / "resumed.mcap", STEPS)


def test_a_session_ended_at_its_resumption_answers_a_resent_last_epoch_with_its_end(
    tmp_path: Path,
) -> None:
    """Killed after recording the last epoch but before ``session_ended``: the resumed
    service ends the session at once, before its source can have reconnected, so a re-send
    of that last epoch is answered with the last state and ``session_ended`` again (the
    source would otherwise wait for an end it never hears), and the recording is left as
    it was."""
    sid, done = "ending", tmp_path / "done"
    endpoint, client_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    settings = SourceSettings(sid, seed=1, steps=STEPS, grid=GRID, timeout=TIMEOUT)
    with service_process(endpoint, done), source_process(settings, endpoint) as future:
        future.result(TIMEOUT)
    recording = read_recording(done / f"{sid}.mcap")
    recording.messages["/event"] = [
        (t, m) for t, m in recording.messages["/event"] if m["event"] != "session_ended"
    ]
    cut = tmp_path / "cut"
    cut.mkdir()
    rewrite(recording, cut / f"{sid}.mcap")  # as if killed just before session_ended
    assert unfinished(read_recording(cut / f"{sid}.mcap"))
    last = recording.accepted_epochs()[-1]
    fields = {k: last[k] for k in ("step", "signal", "ch_names") if k in last}
    epoch = protocol.Message("epoch", sid, last["seq"], last["t_ns"], fields, decode_array(last))

    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    with (
        zenoh.open(peer_config([client_endpoint], ())) as client,
        service_process(endpoint, cut, (client_endpoint,)),
    ):
        pumps = [Pump(client, protocol.key(sid, kind), kind, inbox) for kind in ("event",
                                                                                "state")]
        publisher = reliable_publisher(client, protocol.key(sid, "epoch"))
        assert wait_for_subscribers(publisher, TIMEOUT)
        ended = read_recording(cut / f"{sid}.mcap")  # ended at the resumption
        assert not unfinished(ended)
        publisher.put(protocol.encode(epoch))
        states, again = [], None
        while again is None:
            message = protocol.decode(inbox.get(timeout=TIMEOUT).data)
            if message.kind == "state":
                states.append(message.fields["n_signals"])
            elif message.fields["event"] == "error":
                pytest.fail(message.fields["message"])  # e.g. "epoch for an unknown session"
            elif "sent again" in message.fields["message"]:
                again = message.fields["event"]
        for pump in pumps:
            pump.close()
    assert again == "session_ended" and states[-1] == STEPS
    after = read_recording(cut / f"{sid}.mcap")
    assert after.n_messages == ended.n_messages  # the answer again is not recorded
