"""Non-grid worlds through the live path: real Zenoh over loopback, the service and the
source in spawned processes; the recording replayed and reported.

A live session in the line world (stochastic edges: the world stream) and one in
pick-and-place (624 tasks, guidance) each make exactly the decisions of ``run_session``;
their recordings have a ``/ranking`` channel instead of the grid's ``/belief``, replay
identically (re-published to a service too) and render a report; a config naming an
unknown world is rejected with an error naming the field, and the service goes on
serving; ``cfbci session --world line`` runs.
"""

from __future__ import annotations

import json
import queue
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import zenoh
from jsonschema import Draft202012Validator
from live import SPAWN, TIMEOUT, answering_challenges, service_process
from mcap.reader import make_reader

from acquisition.simulated_source import SourceSettings, run_source
from acquisition.sources import DataSpec
from calibration_free.config import LearnerConfig
from calibration_free.streams import StepRecord
from calibration_free.worlds import make_world
from cfbci.cli import main
from cfbci.offline.simulation import SessionConfig, SessionResult, run_session
from replay.recording import RANKED, read_recording
from replay.rerun import replay_check
from wire import protocol
from wire.transport import Outbox, Pump, Received, reliable_publisher, wait_for_subscribers
from wire.zenoh_config import free_tcp_endpoint, peer_config


def live_and_simulated(
    tmp_path: Path, settings: SourceSettings
) -> tuple[list[StepRecord], list[StepRecord], SessionResult]:
    """The live session's records (service and source spawned), and ``run_session``'s
    trace and result for the same world, data, frame and seed."""
    endpoint = free_tcp_endpoint()
    with service_process(endpoint, tmp_path), ProcessPoolExecutor(1, mp_context=SPAWN) as pool:
        summary = pool.submit(run_source, settings, [], [endpoint]).result(TIMEOUT)
    trace: list[StepRecord] = []
    config = SessionConfig(
        steps=settings.steps, world=settings.world,
        learner=LearnerConfig.from_dict({"frame": settings.frame, **settings.learner}),
    )
    result = run_session(settings.seed, config, settings.data.resolve(settings.frame),
                         trace.append)
    return summary.records, trace, result


def check_recording(path: Path, steps: int, world_kind: str) -> None:
    """Channels of a world without a grid layout, every message valid under its schema,
    and the ranking equal to the states' confidences."""
    recording = read_recording(path)
    assert not recording.truncated
    assert recording.config["world"] == world_kind and "grid" not in recording.config
    assert "/belief" not in recording.messages  # no grid layout, no foxglove.Grid
    rankings = [m for _, m in recording.messages["/ranking"]]
    states = [m for _, m in recording.messages["/state"]]
    assert len(rankings) == len(states) == steps + 1
    world = make_world(world_kind)
    for ranking, state in zip(rankings, states, strict=True):
        confidence = np.asarray(state["confidence"], dtype=np.float32)
        tasks = ranking["tasks"]
        assert len(tasks) == min(RANKED, world.n_tasks)
        assert tasks[0]["task"] == int(np.argmax(confidence))
        assert [t["confidence"] for t in tasks] == sorted(confidence, reverse=True)[: len(tasks)]
        assert all(t["name"] == world.task_name(t["task"]) for t in tasks)
        assert all(t["state"] == world.task_states[t["task"]] for t in tasks)
    with path.open("rb") as stream:
        for schema, _, message in make_reader(stream).iter_messages():
            assert schema is not None
            Draft202012Validator(json.loads(schema.data)).validate(json.loads(message.data))


def check_replay_and_report(path: Path, tmp_path: Path, result: SessionResult) -> dict:
    """``cfbci replay`` identical, ``cfbci report`` rendered; the report's metrics."""
    replayed = replay_check(path)
    assert replayed.divergence is None
    assert main(["replay", str(path)]) == 0
    out = tmp_path / "report"
    assert main(["report", str(path), "--out", str(out), "--jobs", "1"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())["sessions"][0]
    assert metrics["replay_identical"] is True
    assert metrics["grid"] is None
    assert (metrics["correct_targets"], metrics["wrong_targets"]) == (
        result.correct_targets, result.wrong_targets,
    )
    assert metrics["first_target_step"] == result.first_target_step
    page = (out / "index.html").read_text()
    assert "most confident tasks" in page and metrics["world_text"] in page
    return metrics


def test_a_live_line_world_session_equals_its_simulation(tmp_path: Path) -> None:
    steps, seed = 50, 0
    settings = SourceSettings("line-0", seed=seed, steps=steps, world="line")
    records, trace, result = live_and_simulated(tmp_path, settings)
    assert records == trace
    # The seed exercises both outcomes of the edge trick (drawn from the world stream)
    # and declares a target, so that the equality covers them.
    pushes = [r for r in trace if (r.state, r.action) in ((0, "left"), (4, "right"))]
    assert {r.next_state == r.state for r in pushes} == {True, False}
    assert result.correct_targets + result.wrong_targets >= 1

    path = tmp_path / "line-0.mcap"
    check_recording(path, steps, "line")
    recording = read_recording(path)
    assert recording.config["signal"] == "epochs"
    truths = [m for _, m in recording.messages["/truth"]]
    assert {t["target"] for t in truths} <= {0, 1}  # the line world's two tasks
    events = [m["message"] for _, m in recording.messages["/event"]
              if m["event"] == "target_reached"]
    assert events and all("(state " in e for e in events)
    metrics = check_replay_and_report(path, tmp_path, result)
    assert metrics["world"] == "line" and metrics["n_tasks"] == 2

    check_republished(path, tmp_path, "line-again")


def check_republished(path: Path, tmp_path: Path, session: str) -> None:
    """Re-published to a live service (``cfbci replay --publish``), the recording makes the
    same moves and states, and the service's new recording replays identically."""
    endpoint = free_tcp_endpoint()
    with service_process(endpoint, tmp_path / "again"):
        code = main(["replay", str(path), "--publish", "--connect", endpoint, "--speed", "0",
                     "--session", session, "--json", str(tmp_path / "again.json")])
    assert code == 0
    published = json.loads((tmp_path / "again.json").read_text())
    assert published["moves_equal"] and published["states_equal"]
    assert replay_check(tmp_path / "again" / f"{session}.mcap").divergence is None


def test_a_live_pick_and_place_guidance_session_equals_its_simulation(tmp_path: Path) -> None:
    steps, seed = 40, 1
    data = DataSpec(synthetic="gaussian", dims=2)
    settings = SourceSettings(
        "pick-1", data=data, seed=seed, steps=steps, world="pick-and-place", frame="guidance",
        learner={"likelihood": "simple"},  # the likelihood rides in the config's learner
    )
    records, trace, result = live_and_simulated(tmp_path, settings)
    assert records == trace
    assert {r.action for r in trace} == {"right", "left", "grasp", "release"}

    path = tmp_path / "pick-1.mcap"
    check_recording(path, steps, "pick-and-place")
    recording = read_recording(path)
    assert recording.config["signal"] == "features"
    # Recorded with every setting the learner ran with: it replays under them whatever
    # later defaults are.
    assert recording.config["learner"] == LearnerConfig(
        frame="guidance", likelihood="simple"
    ).to_dict()
    assert {m["label"] for _, m in recording.messages["/truth"]} <= {0, 1, 2, 3}
    assert all(len(m["confidence"]) == 624 for _, m in recording.messages["/state"])
    metrics = check_replay_and_report(path, tmp_path, result)
    assert metrics["class_names"] == ["right", "left", "grasp", "release"]


def _raw_config(session: str, **fields: object) -> bytes:
    header = {"v": protocol.VERSION, "kind": "config", "session": session, "seq": 0,
              "t_ns": 1, **fields}
    text = json.dumps(header).encode()
    return len(text).to_bytes(4, "little") + text


def next_event_of(inbox: queue.SimpleQueue[Received], session: str) -> dict:
    """The fields of the next event of ``session`` in ``inbox`` (others, and the
    ``session_pending`` challenges that `live.answering_challenges` answers, are
    skipped)."""
    while True:
        received = inbox.get(timeout=TIMEOUT)
        message = protocol.decode(received.data, key_expr=received.key_expr)
        if message.session == session and message.fields["event"] != "session_pending":
            return message.fields


def test_an_unknown_world_is_named_and_the_service_keeps_serving(tmp_path: Path) -> None:
    endpoint, client_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    config = {"seed": 0, "frame": "feedback", "steps": 2, "learner": {}, "dataset": {},
              "signal": "features"}

    def next_event(session: str) -> dict:
        return next_event_of(inbox, session)

    with (
        zenoh.open(peer_config([client_endpoint], ())) as client,
        service_process(endpoint, tmp_path, (client_endpoint,)),
        answering_challenges(client),
    ):
        events = Pump(client, "cfbci/*/event", "event", inbox)
        publisher = reliable_publisher(client, "cfbci/maze/config")
        assert wait_for_subscribers(publisher, TIMEOUT)
        publisher.put(_raw_config("maze", world="maze", **config))
        error = next_event("maze")
        assert error["event"] == "error"
        assert ('field \'world\' must be one of "grid", "line", "pick-and-place", '
                '"continuous", "puddle"; got "maze"') in error["message"]
        publisher.put(_raw_config("maze", world="line", grid=5, **config))
        error = next_event("maze")
        assert error["event"] == "error"
        assert "'grid' is allowed only when 'world' is \"grid\"" in error["message"]
        publisher.undeclare()
        # The service still serves: a line-world session starts.
        outbox = Outbox(client)
        assert wait_for_subscribers(outbox.publisher("cfbci/next/config"), TIMEOUT)
        outbox.send("config", "next", {"world": "line", **config})
        started = next_event("next")
        assert started["event"] == "session_started"
        assert "line world (5 states, 2 tasks)" in started["message"]
        outbox.close()
        events.close()


def test_cfbci_session_runs_a_line_world_session(tmp_path: Path) -> None:
    """The command: ``cfbci session --world line`` records the simulation's moves."""
    steps, seed = 12, 0
    record, summary = tmp_path / "line.mcap", tmp_path / "line.json"
    assert main(["session", "--world", "line", "--steps", str(steps), "--seed", str(seed),
                 "--record", str(record), "--json", str(summary)]) == 0
    assert json.loads(summary.read_text())["steps"] == steps
    recording = read_recording(record)
    assert recording.config["world"] == "line"
    trace: list[StepRecord] = []
    run_session(seed, SessionConfig(steps=steps, world="line"),
                DataSpec().resolve("feedback"), trace.append)
    moves = [m for _, m in recording.messages["/move"]]
    assert [(m["from_state"], m["action"], m["to_state"]) for m in moves] == [
        (r.state, r.action, r.next_state) for r in trace
    ]


def test_a_live_grid_guidance_session_with_resplit_labels_equals_its_simulation(
    tmp_path: Path,
) -> None:
    # The default learner (matching) splits ambiguous guidance labels again at every
    # signal from out-of-fold probabilities: the live service, its replay and the offline
    # session make the same decisions.
    steps = 60
    settings = SourceSettings(
        "grid-guidance", data=DataSpec(synthetic="gaussian", dims=2), seed=3, steps=steps,
        frame="guidance",
    )
    records, trace, result = live_and_simulated(tmp_path, settings)
    assert records == trace
    assert result.correct_targets + result.wrong_targets >= 1  # a switch is covered too
    recording = read_recording(tmp_path / "grid-guidance.mcap")
    assert recording.config["learner"]["resplit_labels"] is True
    assert replay_check(tmp_path / "grid-guidance.mcap").divergence is None
