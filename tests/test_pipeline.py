"""The live pipeline over real Zenoh (loopback TCP, multicast off, spawned processes).

Synchronisation is by messages only; every wait has a timeout that only guards against a
hang.
"""

from __future__ import annotations

import json
import os
import queue
import signal
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import zenoh
from jsonschema import Draft202012Validator
from live import SPAWN, TIMEOUT, answering_challenges, rewrite, service_process
from mcap.reader import make_reader

from acquisition.simulated_source import SourceSettings, SourceSummary, run_source
from acquisition.sources import DataSpec
from calibration_free.streams import StepRecord
from calibration_free.world import ACTIONS, GridWorld
from cfbci.cli import main
from cfbci.offline.simulation import SessionConfig, run_session
from cfbci.service import serve
from cfbci.service.running import STATE_DELAY
from replay.recording import decode_array, read_recording
from replay.rerun import replay_check
from wire import protocol
from wire.transport import Outbox, Pump, Received, reliable_publisher, wait_for_subscribers
from wire.zenoh_config import free_tcp_endpoint, peer_config

STEPS, GRID = 60, 3


def simulated(
    seed: int, user_error_rate: float = 0.0, world: str = "grid"
) -> tuple[list[StepRecord], object]:
    trace: list[StepRecord] = []
    config = SessionConfig(steps=STEPS, grid=GRID, user_error_rate=user_error_rate, world=world)
    result = run_session(seed, config, DataSpec().resolve("feedback"), trace.append)
    return trace, result


@contextmanager
def source_process(settings: SourceSettings, endpoint: str) -> Iterator[Future[SourceSummary]]:
    with ProcessPoolExecutor(1, mp_context=SPAWN) as pool:
        yield pool.submit(run_source, settings, [], [endpoint])


def test_live_session_equals_simulation_and_is_recorded(tmp_path: Path) -> None:
    seed = 3
    endpoint = free_tcp_endpoint()
    settings = SourceSettings("live-1", seed=seed, steps=STEPS, grid=GRID)
    with service_process(endpoint, tmp_path), source_process(settings, endpoint) as future:
        summary = future.result(TIMEOUT)
    trace, result = simulated(seed)

    assert summary.records == trace  # moves, confident flags, best tasks and target events
    assert summary.steps == STEPS
    assert summary.first_target_step == result.first_target_step
    assert (summary.correct_targets, summary.wrong_targets) == (
        result.correct_targets, result.wrong_targets,
    )

    recording = read_recording(tmp_path / "live-1.mcap")
    assert not recording.truncated
    assert recording.session == "live-1"
    assert recording.config["seed"] == seed and recording.config["signal"] == "epochs"
    counts = {topic: len(messages) for topic, messages in recording.messages.items()}
    n_targets = result.correct_targets + result.wrong_targets
    assert counts == {
        "/config": 1, "/epoch": STEPS, "/features": STEPS, "/move": STEPS,
        "/state": STEPS + 1, "/belief": STEPS + 1, "/truth": STEPS,
        "/event": 2 + n_targets, "/log": 2 + n_targets,
    }
    moves = [m for _, m in recording.messages["/move"]]
    assert [m["from_state"] for m in moves] == [r.state for r in trace]
    assert [m["action"] for m in moves] == [r.action for r in trace]
    states = [m for _, m in recording.messages["/state"]]
    assert [s["n_signals"] for s in states] == list(range(STEPS + 1))
    accuracies = [s["balanced_accuracy"] for s in states]
    assert accuracies[0] is None  # no signal yet
    assert all(0 <= a <= 1 for a in accuracies[-10:])  # both classes long present
    assert [s["confident"] for s in states[:-1]] == [r.confident for r in trace]
    events = [m["event"] for _, m in recording.messages["/event"]]
    assert events[0] == "session_started" and events[-1] == "session_ended"
    assert [m["step"] for _, m in recording.messages["/truth"]] == list(range(1, STEPS + 1))
    epoch = decode_array(recording.messages["/epoch"][0][1])
    features = decode_array(recording.messages["/features"][0][1])
    assert epoch.ndim == 2 and features.shape == (57,)
    assert all("update_ms" in m and m["update_ms"] > 0 for m in moves[1:])
    # Every message the service recorded is valid under its channel's schema.
    with (tmp_path / "live-1.mcap").open("rb") as stream:
        for schema, _, message in make_reader(stream).iter_messages():
            assert schema is not None
            Draft202012Validator(json.loads(schema.data)).validate(json.loads(message.data))

    # Offline replay of the recording reproduces every decision ...
    path = tmp_path / "live-1.mcap"
    result = replay_check(path)
    assert result.divergence is None
    assert (result.moves, result.states, result.events) == (STEPS, STEPS + 1, n_targets)
    # ... and a recording altered at one move is caught at that very step.
    altered = tmp_path / "altered.mcap"
    moves[24]["action"] = "goal" if moves[24]["action"] != "goal" else "up"
    rewrite(recording, altered)
    divergence = replay_check(altered).divergence
    assert divergence is not None
    assert (divergence.topic, divergence.step, divergence.field) == ("/move", 25, "action")
    assert main(["replay", str(altered)]) == 1 and main(["replay", str(path)]) == 0


def test_each_moves_state_follows_it_and_comes_before_the_next_move(tmp_path: Path) -> None:
    """The service publishes a move first and its state (with the step's target events)
    `STATE_DELAY` later, or as soon as the move's epoch comes if that is sooner: a source
    that answers at once and one that answers a second later both get every state after its
    move and before the next move; the slow one's states come before its epochs (the
    loop's timer, not the next epoch, sent them); both recordings replay identically."""
    endpoint = free_tcp_endpoint()
    fast = SourceSettings("fast-1", seed=4, steps=STEPS, grid=GRID)
    slow = SourceSettings("slow-1", seed=5, steps=6, grid=GRID, interval=1.0)
    with service_process(endpoint, tmp_path), source_process(fast, endpoint) as answered_at_once, \
            source_process(slow, endpoint) as answered_later:
        assert answered_at_once.result(TIMEOUT).steps == STEPS
        assert answered_later.result(TIMEOUT).steps == 6

    for name, steps in (("fast-1", STEPS), ("slow-1", 6)):
        recording = read_recording(tmp_path / f"{name}.mcap")
        moves = {m["step"]: m["t_ns"] for _, m in recording.messages["/move"]}
        states = {m["n_signals"]: m["t_ns"] for _, m in recording.messages["/state"]}
        assert sorted(moves) == list(range(1, steps + 1))
        for step, sent in moves.items():
            assert sent < states[step - 1], (name, step)  # the move first
            if step < steps:
                assert states[step - 1] < moves[step + 1], (name, step)
        assert replay_check(tmp_path / f"{name}.mcap").divergence is None
    slow_recording = read_recording(tmp_path / "slow-1.mcap")
    moves = {m["step"]: m["t_ns"] for _, m in slow_recording.messages["/move"]}
    states = {m["n_signals"]: m["t_ns"] for _, m in slow_recording.messages["/state"]}
    epochs = {m["step"]: received for received, m in slow_recording.messages["/epoch"]}
    assert all(states[step - 1] - moves[step] >= STATE_DELAY * 1e9 for step in moves)
    assert all(states[step - 1] < epochs[step] for step in moves)


def _message(kind: str, session: str, seq: int, fields: dict, payload=None) -> bytes:
    return protocol.encode(protocol.Message(kind, session, seq, 1, fields, payload))


def _raw(header: dict, payload: bytes = b"") -> bytes:
    text = json.dumps(header).encode()
    return len(text).to_bytes(4, "little") + text + payload


def _epoch_header(session: str, seq: int, shape: list[int]) -> dict:
    return {
        "v": protocol.VERSION, "kind": "epoch", "session": session, "seq": seq, "t_ns": 1,
        "step": 1,
        "signal": "features", "shape": shape, "dtype": "float32", "units": "uV",
    }


def _wait_event(inbox: queue.SimpleQueue[Received], match: Callable[[str, dict], bool]) -> dict:
    """The next event (session, fields) that ``match``es; events before it are skipped."""
    while True:
        received = inbox.get(timeout=TIMEOUT)
        message = protocol.decode(received.data, key_expr=received.key_expr)
        if match(message.session, message.fields):
            return message.fields


def _error(session: str, *words: str, kind: str = "error") -> Callable[[str, dict], bool]:
    return lambda s, f: s == session and f["event"] == kind and all(
        w in f["message"] for w in words
    )


def _rejected(session: str, *words: str) -> Callable[[str, dict], bool]:
    return _error(session, *words, kind="session_rejected")


def test_malformed_messages_yield_errors_and_the_session_finishes(tmp_path: Path) -> None:
    seed = 5
    endpoint = free_tcp_endpoint()
    settings = SourceSettings("main", seed=seed, steps=STEPS, grid=GRID, interval=0.05)
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    client_endpoint = free_tcp_endpoint()
    # The client listens first and the service connects to it, so that the client is on
    # the network (its event subscription known) before the source starts.
    with (
        zenoh.open(peer_config([client_endpoint], ())) as client,
        service_process(endpoint, tmp_path, (client_endpoint,)),
        answering_challenges(client),
    ):
        events = Pump(client, "cfbci/**/event", "event", inbox)
        bad = {key: reliable_publisher(client, key) for key in (
            "cfbci/main/epoch", "cfbci/nosuch/epoch", "cfbci/_/epoch",
        )}
        for publisher in bad.values():
            assert wait_for_subscribers(publisher, TIMEOUT)  # the service is connected
        with source_process(settings, endpoint) as future:
            _wait_event(inbox, lambda s, f: s == "main" and f["event"] == "session_started")
            main = bad["cfbci/main/epoch"]
            header = _epoch_header("main", 0, [2])

            main_errors = []
            for data, expected in (
                (_raw({**header, "v": 1}, np.zeros(2, "<f4").tobytes()), "protocol version 1"),
                (_raw(header, np.array([1.0, np.nan], "<f4").tobytes()), "NaN"),
                ((100).to_bytes(4, "little") + b'{"v":1', "truncated"),
                (_raw(header, np.zeros(3, "<f4").tobytes()), "needs 8 payload bytes; got 12"),
            ):
                main.put(data)
                main_errors.append(_wait_event(inbox, _error("main", expected))["message"])
            fields = {"step": 1, "signal": "features"}
            bad["cfbci/nosuch/epoch"].put(_message("epoch", "nosuch", 0, fields, np.zeros(2)))
            _wait_event(inbox, _error("nosuch", "unknown session"))
            bad["cfbci/_/epoch"].put(_raw({**header, "session": "_"}))
            _wait_event(inbox, _error("_", "reserved"))

            # A session of the client's own: session-level checks, deterministically.
            own = Outbox(client)
            assert wait_for_subscribers(own.publisher("cfbci/own/config"), TIMEOUT)
            config = {
                "seed": 0, "world": "grid", "grid": GRID, "frame": "feedback", "steps": 5,
                "learner": {},
                "dataset": {}, "signal": "features",
            }
            own.send("config", "own", config)
            _wait_event(inbox, lambda s, f: s == "own" and f["event"] == "session_started")
            epoch = own.publisher("cfbci/own/epoch")
            epoch.put(_message("epoch", "own", 0, fields, np.ones(4)))  # accepted
            epoch.put(_message("epoch", "own", 0, {**fields, "step": 2}, np.ones(4)))
            _wait_event(inbox, _error("own", "duplicate: seq 0"))
            epoch.put(_message("epoch", "own", 1, {**fields, "step": 7}, np.ones(4)))
            _wait_event(inbox, _error("own", "epoch of step 7", "step 2"))
            epoch.put(_message("epoch", "own", 2, {**fields, "step": 2}, np.ones(5)))
            _wait_event(inbox, _error("own", "shape [5]", "[4]"))
            epoch.put(_message("epoch", "own", 5, {**fields, "step": 2}, np.ones(4)))  # accepted
            gap = _wait_event(inbox, lambda s, f: s == "own" and f["event"] == "info")
            # Rejected epochs do not count: seq 1 and 2 were not accepted, so 1 is expected.
            assert gap["message"] == "gap: expected 1, got 5 (4 messages lost)"
            # A config that cannot be run is a session_rejected event naming that config;
            # one for a running id leaves the running session alone.
            second = own.send("config", "own", config)
            rejected = _wait_event(inbox, _rejected("own", "already running"))
            assert rejected["config_t_ns"] == second.t_ns
            bad_learner = {**config, "learner": {"eps": 0.9}}
            own.send("config", "own2", bad_learner)
            _wait_event(inbox, _rejected("own2", "bad config", "eps"))
            own.close()

            summary = future.result(TIMEOUT)
        events.close()
        for publisher in bad.values():
            publisher.undeclare()

    trace, _ = simulated(seed)
    assert summary.records == trace  # the learner never saw a rejected message
    recording = read_recording(tmp_path / "main.mcap")
    errors = [m["message"] for _, m in recording.messages["/event"] if m["event"] == "error"]
    assert set(errors) <= set(main_errors)  # those that came while the session ran
    assert len(recording.messages["/move"]) == STEPS
    # The client's session was running at SIGTERM: its recording was closed all the same,
    # with the two accepted epochs observed and every rejected one left out of the learner.
    own = read_recording(tmp_path / "own.mcap")
    assert not own.truncated
    assert len(own.messages["/epoch"]) == len(own.messages["/features"]) == 2  # accepted only
    assert [m["n_signals"] for _, m in own.messages["/state"]] == [0, 1, 2]


def test_two_sessions_at_once_each_equal_their_simulation(tmp_path: Path) -> None:
    """Two sessions, one of them with a user who gives the wrong label 20 % of the time."""
    endpoint = free_tcp_endpoint()
    sessions = {"twin-a": (7, 0.0), "twin-b": (11, 0.2)}
    with service_process(endpoint, tmp_path), ProcessPoolExecutor(2, mp_context=SPAWN) as pool:
        futures = {
            sid: pool.submit(
                run_source,
                SourceSettings(sid, seed=seed, steps=STEPS, grid=GRID, user_error_rate=rate),
                [],
                [endpoint],
            )
            for sid, (seed, rate) in sessions.items()
        }
        summaries = {sid: future.result(TIMEOUT) for sid, future in futures.items()}
    for sid, (seed, rate) in sessions.items():
        assert summaries[sid].records == simulated(seed, rate)[0], sid
        recording = read_recording(tmp_path / f"{sid}.mcap")
        assert recording.config["seed"] == seed
        assert len(recording.messages["/move"]) == STEPS
    # Recorded truth: the error-free user's labels are the frame's, the other's are wrong
    # about 20 % of the time (60 steps: 12 expected, binomial sd 3.1).
    world = GridWorld(GRID)
    wrong = {}
    for sid in sessions:
        recording = read_recording(tmp_path / f"{sid}.mcap")
        truths = [m for _, m in recording.messages["/truth"]]
        moves = [m for _, m in recording.messages["/move"]]
        wrong[sid] = sum(
            truth["label"]
            != int(not world.optimal[truth["target"], move["from_state"],
                                     ACTIONS.index(move["action"])])
            for move, truth in zip(moves, truths, strict=True)
        )
    assert wrong["twin-a"] == 0
    assert 4 <= wrong["twin-b"] <= 22


KILLED = "killed"
KILL_AFTER = 20  # moves seen before the kill (then the first move declaring no target)


def _stop_mid_session(
    tmp_path: Path, session: str, signum: int
) -> tuple[int | None, dict[int, dict], Counter[str]]:
    """Be the source (feature vectors) of a session; stop answering after move k and its
    state, wait for every event known to be due, and send ``signum`` to the service.

    Returns the service's exit code, the moves by step, and the messages seen per kind.
    """
    endpoint, client_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    rng = np.random.default_rng(0)
    seen: Counter[str] = Counter()
    moves: dict[int, dict] = {}
    with zenoh.open(peer_config([client_endpoint], ())) as client, answering_challenges(client):
        pumps = [
            Pump(client, protocol.key(session, kind), kind, inbox)
            for kind in ("move", "state", "event")
        ]
        outbox = Outbox(client)
        service = SPAWN.Process(target=serve, args=([endpoint], [client_endpoint], tmp_path))
        service.start()
        try:
            assert wait_for_subscribers(
                outbox.publisher(protocol.key(session, "config")), TIMEOUT
            )
            outbox.send("config", session, {
                "seed": 0, "world": "grid", "grid": GRID, "frame": "feedback", "steps": STEPS,
                "learner": {},
                "dataset": {}, "signal": "features",
            })
            answered = 0
            while True:
                received = inbox.get(timeout=TIMEOUT)
                message = protocol.decode(received.data, key_expr=received.key_expr)
                seen[message.kind] += 1
                if message.kind == "move":
                    moves[message.fields["step"]] = message.fields
                step = answered + 1  # the move to answer once it and its state are in
                if step not in moves or seen["state"] < step:
                    continue
                declared = sum(move["target_reached"] for move in moves.values())
                if step >= KILL_AFTER and not moves[step]["target_reached"]:
                    # session_pending, session_started, target_reached's
                    if seen["event"] == 2 + declared:
                        break
                    continue
                fields = {"step": step, "signal": "features"}
                outbox.send("epoch", session, fields, rng.normal(size=4).astype(np.float32))
                answered = step
        finally:
            assert service.pid is not None
            os.kill(service.pid, signum)
            service.join(TIMEOUT)
            if service.is_alive():
                service.kill()
                service.join()
            for pump in pumps:
                pump.close()
            outbox.close()
    return service.exitcode, moves, seen


def test_a_killed_service_leaves_a_recording_with_all_it_sent(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    exitcode, moves, seen = _stop_mid_session(tmp_path, KILLED, signal.SIGKILL)
    assert exitcode == -signal.SIGKILL
    k = len(moves)
    assert seen["move"] == k >= KILL_AFTER and seen["state"] == k

    path = tmp_path / f"{KILLED}.mcap"
    recording = read_recording(path)
    assert recording.truncated and recording.session == KILLED
    counts = {topic: len(messages) for topic, messages in recording.messages.items()}
    # Recorded right after being sent, and before the service sent state k: all of them.
    assert counts["/move"] == k
    assert counts["/epoch"] == counts["/features"] == k - 1  # every epoch answered by a move
    # Every event heard is recorded, but the session_pending before the recording began.
    assert counts["/event"] == counts["/log"] == seen["event"] - 1
    # The last message the service sent is state k; the kill may have cut its records.
    assert k - 1 <= counts["/state"] <= k
    assert counts["/state"] - 1 <= counts["/belief"] <= counts["/state"]
    assert counts["/truth"] == 0 and counts["/config"] == 1
    states = [m for _, m in recording.messages["/state"]]
    assert [m["n_signals"] for m in states] == list(range(len(states)))

    clean = tmp_path / f"{KILLED}.recovered.mcap"  # the default output
    assert main(["recover", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"recovered {recording.n_messages} messages" in out and "truncated" in out
    recovered = read_recording(clean)
    assert not recovered.truncated and recovered.messages == recording.messages


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_an_interrupted_service_closes_its_recording(tmp_path: Path, signum: int) -> None:
    """SIGINT or SIGTERM mid-session: the service exits with 0, its recording closed
    (summary and index written) and holding every message it sent."""
    exitcode, moves, seen = _stop_mid_session(tmp_path, "interrupted", signum)
    assert exitcode == 0
    k = len(moves)
    recording = read_recording(tmp_path / "interrupted.mcap")
    assert not recording.truncated and recording.warning is None
    counts = {topic: len(messages) for topic, messages in recording.messages.items()}
    assert counts["/move"] == counts["/state"] == counts["/belief"] == seen["state"] == k
    assert counts["/epoch"] == counts["/features"] == k - 1
    assert counts["/event"] == counts["/log"] == seen["event"] - 1  # not session_pending
    # Closed means indexed: the mcap library's seeking reader opens it.
    with open(tmp_path / "interrupted.mcap", "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    assert sum(summary.statistics.channel_message_counts.values()) == recording.n_messages


def test_recover_names_a_missing_or_non_mcap_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["recover", str(tmp_path / "nope.mcap")]) == 2
    assert "no such file" in capsys.readouterr().err
    text = tmp_path / "text.mcap"
    text.write_text("not a recording")
    assert main(["recover", str(text), "--out", str(tmp_path / "out.mcap")]) == 2
    assert "not an MCAP file" in capsys.readouterr().err
    assert not (tmp_path / "out.mcap").exists()
