"""The continuous-goal world through the live path: real Zenoh over loopback, the service
and the source in spawned processes; the recording replayed.

A live continuous session equals ``run_continuous_session`` step by step (probe points,
particles, their confidences, best particle); its recording holds the particles as a
``foxglove.PointCloud`` valid under its schema and replays identically (and re-published
to a service, which makes the same probes and states); a SIGKILLed service resumes the
session, which still equals the simulation; a config with the
wrong frame, an unknown learner setting or settings over the memory limit is rejected
naming the field (or the memory), and the service goes on serving; ``cfbci session
--world continuous`` records the simulation's probes, replays and reports.
"""

from __future__ import annotations

import base64
import json
import queue
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import zenoh
from jsonschema import Draft202012Validator
from live import SPAWN, TIMEOUT, answering_challenges, service_process
from mcap.reader import make_reader
from test_resume import KILL_AT, check_resumed_recording, run_with_a_kill
from test_world_pipeline import check_republished, next_event_of

from acquisition.gaussian import generate_gaussian_features
from acquisition.loaders import save_features_npz
from acquisition.simulated_source import SourceSettings, run_source
from acquisition.sources import DataSpec
from calibration_free.continuous_goals import ContinuousConfig, ContinuousGoalLearner
from cfbci.cli import main
from cfbci.offline.continuous import run_continuous_session
from replay.recording import read_recording
from replay.rerun import replay_check
from wire.transport import Outbox, Pump, Received, wait_for_subscribers
from wire.zenoh_config import free_tcp_endpoint, peer_config


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four classes of 11-D Gaussian signals (like ``move_finger.mat``'s) in a features
    ``.npz``: a real file both the live source and the simulation read."""
    data = generate_gaussian_features(60, 4, 11, 0.98, 0)
    path = tmp_path_factory.mktemp("data") / "four-classes.npz"
    save_features_npz(path, data.features, data.labels)
    return path
#: Short sessions: a continuous step costs 100-250 ms on the loaded machine.
STEPS = 30
LEARNER = {"n_hypotheses": 20, "n_candidates": 200, "n_initial": 12}


def test_a_live_continuous_session_equals_its_simulation(tmp_path: Path, dataset: Path) -> None:
    seed, order = 3, (2, 0, 3, 1)
    data = DataSpec(path=dataset)
    settings = SourceSettings(
        "plane-3", data=data, seed=seed, steps=STEPS, world="continuous", frame="cardinal",
        learner=LEARNER, class_order=order,
    )
    endpoint = free_tcp_endpoint()
    with service_process(endpoint, tmp_path), ProcessPoolExecutor(1, mp_context=SPAWN) as pool:
        summary = pool.submit(run_source, settings, [], [endpoint]).result(TIMEOUT * 4)
    assert summary.steps == STEPS

    snapshots: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def snapshot(learner: ContinuousGoalLearner) -> None:
        snapshots.append(
            (learner.particles.copy(), learner.confidence.copy(), learner.estimate().copy())
        )

    result = run_continuous_session(
        seed, ContinuousConfig(**LEARNER), data.resolve("guidance"), STEPS, order, snapshot
    )

    path = tmp_path / "plane-3.mcap"
    recording = read_recording(path)
    assert not recording.truncated and recording.config["world"] == "continuous"
    moves = [m for _, m in recording.messages["/move"]]
    states = [m for _, m in recording.messages["/state"]]
    assert len(moves) == STEPS and len(states) == STEPS + 1
    # Probe points: exactly the simulation's (float64 through JSON).
    assert [tuple(m["to_state"]) for m in moves] == list(result.probes)
    assert all(m["action"] == "probe" and m["from_state"] == m["to_state"] for m in moves)
    # The state after epoch k: the particles the learner scored, their confidences, and
    # the best particle (the simulation's estimate).
    for k, (particles, confidence, estimate) in enumerate(snapshots, start=1):
        state = states[k]
        assert state["n_signals"] == k
        assert np.array_equal(np.array(state["points"]), particles)
        assert np.array_equal(np.array(state["confidence"]), confidence.astype(np.float32))
        assert np.array_equal(np.array(state["points"][state["best_task"]]), estimate)
    # The confidences moved: the scoring ran (from step n_initial on).
    assert len({tuple(s["confidence"]) for s in states}) > STEPS - LEARNER["n_initial"]
    truths = [m for _, m in recording.messages["/truth"]]
    assert all(t["target"] == list(result.goal) for t in truths)
    assert {t["label"] for t in truths} <= {0, 1, 2, 3}

    # The particles as a foxglove.PointCloud: x, y, confidence of every particle.
    clouds = [m for _, m in recording.messages["/particles"]]
    assert len(clouds) == len(states)
    for cloud, state in zip(clouds, states, strict=True):
        packed = np.frombuffer(base64.b64decode(cloud["data"]), dtype="<f4").reshape(-1, 3)
        expected = np.column_stack([state["points"], state["confidence"]]).astype(np.float32)
        assert np.array_equal(packed, expected)
    with path.open("rb") as stream:
        for schema, _, message in make_reader(stream).iter_messages():
            assert schema is not None
            Draft202012Validator(json.loads(schema.data)).validate(json.loads(message.data))

    assert replay_check(path).divergence is None
    assert main(["replay", str(path)]) == 0

    # Re-published to a live service, the same probes and states (particles included).
    check_republished(path, tmp_path, "plane-again")


def test_a_killed_service_resumes_a_continuous_session(tmp_path: Path, dataset: Path) -> None:
    """SIGKILLed after the scoring began, the service resumes from its recording and the
    session makes the simulation's probes (resampled particles included)."""
    seed = 5
    settings = SourceSettings(
        "resumed", data=DataSpec(path=dataset), seed=seed, steps=STEPS, world="continuous",
        frame="cardinal", learner=LEARNER, timeout=TIMEOUT, resend_interval=0.2,
    )
    assert KILL_AT > LEARNER["n_initial"]
    summary = run_with_a_kill(settings, tmp_path, STEPS)
    assert summary.steps == STEPS
    path = tmp_path / "resumed.mcap"
    check_resumed_recording(path, STEPS)
    result = run_continuous_session(
        seed, ContinuousConfig(**LEARNER), DataSpec(path=dataset).resolve("guidance"), STEPS
    )
    moves = sorted((m for _, m in read_recording(path).messages["/move"]),
                   key=lambda m: m["step"])
    assert [tuple(m["to_state"]) for m in moves] == list(result.probes)


def test_a_bad_continuous_config_is_rejected_naming_the_field(tmp_path: Path) -> None:
    endpoint, client_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    base = {"seed": 0, "world": "continuous", "steps": 2, "dataset": {},
            "signal": "features"}

    with (
        zenoh.open(peer_config([client_endpoint], ())) as client,
        service_process(endpoint, tmp_path, (client_endpoint,)),
        answering_challenges(client),
    ):
        pumps = [Pump(client, f"cfbci/{sid}/event", "event", inbox)
                 for sid in ("frame", "setting", "huge", "next")]
        outbox = Outbox(client)
        for sid, fields, problem in (
            ("frame", {"frame": "guidance", "learner": {}},
             "field 'frame' must be 'cardinal' in world 'continuous'; got 'guidance'"),
            ("setting", {"frame": "cardinal", "learner": {"particles": 5}},
             "unknown learner setting(s) 'particles' for world 'continuous'"),
            ("huge", {"frame": "cardinal", "learner": {"n_candidates": 10**9}},
             "MiB (continuous world, 2 steps), more than the limit of"),
        ):
            assert wait_for_subscribers(outbox.publisher(f"cfbci/{sid}/config"), TIMEOUT)
            outbox.send("config", sid, {**base, **fields})
            rejected = next_event_of(inbox, sid)
            assert rejected["event"] == "session_rejected"
            assert problem in rejected["message"]
        # The service still serves: a continuous session starts.
        assert wait_for_subscribers(outbox.publisher("cfbci/next/config"), TIMEOUT)
        outbox.send("config", "next", {**base, "frame": "cardinal", "learner": LEARNER})
        started = next_event_of(inbox, "next")
        assert started["event"] == "session_started"
        assert "continuous world" in started["message"]
        outbox.close()
        for pump in pumps:
            pump.close()


def test_cfbci_session_runs_a_continuous_session_that_replays_and_reports(
    tmp_path: Path, dataset: Path,
) -> None:
    """The commands: ``cfbci session --world continuous`` records the simulation's probes;
    ``cfbci replay`` finds it identical; ``cfbci report`` draws the particles and probes."""
    steps, seed = 20, 1
    record, summary = tmp_path / "plane.mcap", tmp_path / "plane.json"
    options = [f"--set={k}={v}" for k, v in LEARNER.items()]
    assert main(["session", "--world", "continuous", "--frame", "cardinal", "--dataset",
                 str(dataset), "--class-order", "1,0,3,2", "--steps", str(steps), "--seed",
                 str(seed), *options, "--record", str(record), "--json", str(summary)]) == 0
    assert json.loads(summary.read_text())["steps"] == steps
    recording = read_recording(record)
    assert recording.config["dataset"]["class_order"] == [1, 0, 3, 2]
    result = run_continuous_session(
        seed, ContinuousConfig(**LEARNER), DataSpec(path=dataset).resolve("guidance"), steps,
        (1, 0, 3, 2),
    )
    assert [tuple(m["to_state"]) for _, m in recording.messages["/move"]] == list(
        result.probes)
    assert main(["replay", str(record)]) == 0

    out = tmp_path / "report"
    assert main(["report", str(record), "--out", str(out), "--jobs", "1"]) == 0
    session = json.loads((out / "metrics.json").read_text())["sessions"][0]
    assert session["world"] == "continuous" and session["replay_identical"] is True
    assert session["distance"] == list(result.distances)
    assert session["final_distance"] == result.final_distance
    kinds = [f["kind"] for f in session["figures"]]
    assert kinds == ["distance", "particles", "probes", "latency"]
    assert all((out / f["path"]).stat().st_size > 0 for f in session["figures"])
    page = (out / "index.html").read_text()
    assert "particles and probe points" in page
