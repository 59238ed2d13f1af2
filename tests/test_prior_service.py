"""A returning user's prior through the live service (real Zenoh on loopback, spawned
service and source processes, real MCAP files): uploaded into the user's prior store and
named by its SHA-256 in the config, the session decides as `cfbci simulate --prior` does,
its recording holds the prior and replays identically without the store, and a prior that
is missing, another user's, too large, altered or of another feature space is refused with
a message that says so while the service keeps running; `cfbci priors delete` removes one.

Synchronisation is by messages only; every wait has a timeout that only guards against a
hang.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import queue
import shutil
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zenoh
from live import SPAWN, TIMEOUT, rewrite, service_process
from test_access_control import (
    Deployment,
    cfbci,
    deployment,  # noqa: F401  (the fixture)
    router,
    service,
)
from test_lsl import lsl_clients
from test_resume import run_with_a_kill

from acquisition.gaussian import generate_gaussian_features
from acquisition.simulated_source import (
    SourceSettings,
    SourceSummary,
    run_source,
    session_config,
)
from acquisition.sources import DataSpec
from calibration_free.config import LearnerConfig
from calibration_free.streams import StepRecord
from cfbci.bench.returning import DayOneTape, recorded_config, simulation_prior
from cfbci.cli import main
from cfbci.offline.simulation import SessionConfig, run_session
from cfbci.recordings.publish import publish_recording
from cfbci.service import serve
from cfbci.service.limits import ServiceLimits
from cfbci.service.process import spawned
from replay.recording import SessionRecorder, read_recording
from replay.rerun import replay_check
from wire import protocol
from wire.client import Client
from wire.prior_upload import file_sha256, upload_priors
from wire.transport import Outbox, Pump, Received
from wire.zenoh_config import free_tcp_endpoint, peer_config

LOG = logging.getLogger("test_prior_service")
STEPS, GRID = 80, 3
DAY_ONE_SEED, DAY_TWO_SEED = 3, 5


@contextmanager
def source_process(settings: SourceSettings, endpoint: str) -> Iterator[Future[SourceSummary]]:
    with ProcessPoolExecutor(1, mp_context=SPAWN) as pool:
        yield pool.submit(run_source, settings, [], [endpoint])


@pytest.fixture(scope="module")
def record_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A service's record directory holding day 1 of user ``lab``, ``lab/day1.mcap``: a
    live session (its service stopped since, so the recording is closed)."""
    directory = tmp_path_factory.mktemp("service")
    endpoint = free_tcp_endpoint()
    settings = SourceSettings("lab/day1", seed=DAY_ONE_SEED, steps=STEPS, grid=GRID)
    with service_process(endpoint, directory), source_process(settings, endpoint) as future:
        assert future.result(TIMEOUT).correct_targets >= 2  # a labelled segment at least
    return directory


def simulated(
    seed: int, prior: Path | None, steps: int = STEPS, grid: int = GRID
) -> list[StepRecord]:
    """The session of ``cfbci simulate --prior`` (or none) for ``seed``, step by step."""
    trace: list[StepRecord] = []
    config = SessionConfig(steps=steps, grid=grid)
    if prior is not None:
        config = replace(config, prior=simulation_prior([prior], DataSpec(), "feedback"))
    run_session(seed, config, DataSpec().resolve("feedback"), trace.append)
    return trace


def test_a_session_with_a_prior_equals_its_simulation_and_replays_identically(
    record_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    day_one = record_dir / "lab" / "day1.mcap"
    sha256 = file_sha256(day_one)
    endpoint = free_tcp_endpoint()
    settings = SourceSettings(
        "lab/day2", seed=DAY_TWO_SEED, steps=STEPS, grid=GRID, prior=(day_one,)
    )
    with service_process(endpoint, record_dir), source_process(settings, endpoint) as future:
        summary = future.result(TIMEOUT)

    trace = simulated(DAY_TWO_SEED, day_one)
    assert summary.records == trace  # every move, confidence flag, best task and target
    assert trace != simulated(DAY_TWO_SEED, None)  # the prior made a difference
    stored = record_dir / "priors" / "lab" / f"{sha256}.mcap"
    assert stored.read_bytes() == day_one.read_bytes()  # uploaded, hash checked

    recording = read_recording(record_dir / "lab" / "day2.mcap")
    assert recording.config["prior"] == [sha256]
    held = [m for _, m in recording.messages["/prior"]]
    assert [m["sha256"] for m in held] == [sha256]
    assert base64.b64decode(held[0]["data"]) == day_one.read_bytes()
    # The recording alone, away from the store, replays identically.
    alone = tmp_path / "day2.mcap"
    shutil.copyfile(record_dir / "lab" / "day2.mcap", alone)
    result = replay_check(alone)
    assert result.divergence is None and result.complete
    assert result.moves == STEPS
    assert main(["replay", str(alone)]) == 0
    # Re-scored open loop, its own settings start from its prior and give its beliefs.
    rescored = tmp_path / "rescored.json"
    assert main(["replay", str(alone), "--option", "beta=0.95", "--json", str(rescored)]) == 0
    own = json.loads(rescored.read_text())["settings"][0]
    assert own["name"] == "own settings" and own["identical_to_recording"] is True
    # Its report re-runs it with the prior too (the decoders' accuracy on today's signals).
    assert main(["report", str(alone), "--out", str(tmp_path / "report")]) == 0
    metrics = json.loads((tmp_path / "report" / "metrics.json").read_text())
    assert metrics["errors"] == []
    (session,) = metrics["sessions"]
    assert session["replay_identical"] is True
    assert session["final_accuracy_truth"] is not None
    # A recording whose copy of the prior is altered is refused, saying so.
    data = bytearray(day_one.read_bytes())
    data[len(data) // 2] ^= 1
    recording.messages["/prior"][0][1]["data"] = base64.b64encode(bytes(data)).decode()
    altered = tmp_path / "altered.mcap"
    rewrite(recording, altered)
    capsys.readouterr()
    assert main(["replay", str(altered)]) == 2
    assert "recorded copy of prior" in capsys.readouterr().err


def test_a_killed_service_resumes_a_session_with_a_prior(
    record_dir: Path, tmp_path: Path
) -> None:
    """Killed with SIGKILL mid-session and started again, the service re-runs the session
    with the prior its recording holds, and goes on as if never killed."""
    day_one = record_dir / "lab" / "day1.mcap"
    settings = SourceSettings("lab/resumed", seed=DAY_TWO_SEED, steps=STEPS, grid=GRID,
                              timeout=TIMEOUT, resend_interval=0.2, prior=(day_one,))
    summary = run_with_a_kill(settings, tmp_path, STEPS)
    assert summary.records == simulated(DAY_TWO_SEED, day_one)
    path = tmp_path / "lab" / "resumed.mcap"
    recording = read_recording(path)  # rewritten in place at the resumption, then closed
    assert not recording.truncated
    assert [m["step"] for _, m in recording.messages["/move"]] == list(range(1, STEPS + 1))
    assert [m["sha256"] for _, m in recording.messages["/prior"]] == [file_sha256(day_one)]
    assert any("resumed at step" in m["message"] for _, m in recording.messages["/event"])
    assert main(["replay", str(path)]) == 0


class Listener:
    """A Zenoh peer of the test: uploads and sends by hand, and hears a session id's
    events."""

    def __init__(self, session: zenoh.Session, sid: str) -> None:
        self.session, self.sid = session, sid
        self.inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
        self.pump = Pump(session, protocol.key(sid, "event"), "event", self.inbox)
        self.outbox = Outbox(session)

    def close(self) -> None:
        self.pump.close()
        self.outbox.close()

    def answer(self, fields: dict) -> dict:
        """Send a ``prior`` message (re-sent until answered) and return the answer."""
        while True:
            self.outbox.send("prior", self.sid, fields)
            try:
                received = self.inbox.get(timeout=1.0)
            except queue.Empty:
                continue  # the service's subscriber not matched yet: send again
            event = protocol.decode(received.data, key_expr=received.key_expr).fields
            if event.get("prior") == fields["sha256"]:
                return event


def rejection(session: zenoh.Session, sid: str, config: dict) -> str:
    """The message of the ``session_rejected`` answering ``config``."""

    class Nobody:
        def on_move(self, move: protocol.Message) -> None:
            raise AssertionError(f"session {sid!r} started: {move}")

        def poll(self) -> float:
            return float("inf")

    with Client(session, sid, LOG, TIMEOUT) as client, pytest.raises(RuntimeError) as caught:
        client.run(config, Nobody())
    return str(caught.value)


def config_of(seed: int, prior: list[str]) -> dict:
    """A grid config as `cfbci source` sends it (synthetic epochs) naming ``prior``."""
    settings = SourceSettings("x", seed=seed, steps=STEPS, grid=GRID)
    return session_config(settings) | {"prior": prior}


def gaussian_day(path: Path, dims: int) -> None:
    """A session of Gaussian feature vectors recorded as the service records one."""
    data = generate_gaussian_features(300, n_classes=2, n_dims=dims, accuracy=0.9, seed=1)
    data = replace(data, features=data.features.astype(np.float32).astype(np.float64))
    config = SessionConfig(steps=120, grid=GRID, learner=LearnerConfig(power_prior=False))
    fields = recorded_config(1, config, data, "gaussian test signals")
    with SessionRecorder(path, "feat/day1", fields) as recorder:
        run_session(1, config, data, on_move=DayOneTape(recorder, fields, data))


def test_a_wrong_missing_oversized_or_mismatched_prior_is_refused(
    record_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each refusal says what is wrong; the service goes on, and runs a session with the
    user's prior afterwards; a prior deleted with `cfbci priors delete` is gone."""
    day_one = record_dir / "lab" / "day1.mcap"
    sha256 = file_sha256(day_one)
    store = tmp_path / "store"
    features = tmp_path / "features.mcap"
    gaussian_day(features, dims=2)
    endpoint = free_tcp_endpoint()
    limits = ServiceLimits(user_prior_mb=1.0)  # day 1 is about 0.7 MiB
    with spawned(serve, [endpoint], [], tmp_path / "records", limits=limits,
                 prior_dir=store), zenoh.open(peer_config((), [endpoint])) as session:
        # A config naming a prior the store lacks.
        unknown = hashlib.sha256(b"no such prior").hexdigest()
        message = rejection(session, "lab/s1", config_of(1, [unknown]))
        assert f"prior {unknown[:12]} is not in user 'lab''s prior store" in message
        # The user's own prior, uploaded: another user may not use it.
        assert upload_priors(session, "lab/up", [day_one], TIMEOUT, 1.0) == [sha256]
        message = rejection(session, "other/s1", config_of(1, [sha256]))
        assert f"prior {sha256[:12]} is not in user 'other''s prior store" in message
        assert not (store / "other").exists()
        # An upload over the user's room: nothing of it is kept.
        big = tmp_path / "big.bin"
        big.write_bytes(np.random.default_rng(0).bytes(600_000))
        with pytest.raises(RuntimeError, match=r"would take user 'lab''s prior store to "
                           r"1\.3 MiB, over its limit of 1 MiB"):
            upload_priors(session, "lab/up", [big], TIMEOUT, 1.0)
        # Bytes that are not what the upload declared: discarded.
        listener = Listener(session, "lab/up")
        try:
            content = b"twelve bytes"
            declared = hashlib.sha256(b"other bytes!").hexdigest()
            answer = listener.answer({"sha256": declared, "size": 12, "offset": 0,
                                      "data": base64.b64encode(content).decode()})
        finally:
            listener.close()
        assert answer["event"] == "prior_rejected"
        assert f"have SHA-256 {hashlib.sha256(content).hexdigest()}, not the declared one" in (
            answer["message"])
        assert sorted(p.name for p in (store / "lab").iterdir()) == [f"{sha256}.mcap"]
        # A prior of feature vectors for a session of raw epochs: refused at the config.
        (features_sha,) = upload_priors(session, "feat/up", [features], TIMEOUT, 1.0)
        message = rejection(session, "feat/s1", config_of(1, [features_sha]))
        assert "prior refused" in message and "another feature space" in message
        assert "sfreq: None vs 256.0" in message
        # Feature vectors of another size: refused at the first epoch.
        four = DataSpec(synthetic="gaussian", dims=4)
        settings = SourceSettings("feat/s2", data=four, seed=1, steps=STEPS, grid=GRID,
                                  prior=(features,))
        with pytest.raises(RuntimeError, match="its feature vectors have 2 values, this "
                           "session's 4"):
            run_source(settings, [], [endpoint])
        # The service goes on: a session with the user's prior runs.
        settings = SourceSettings("lab/after", seed=2, steps=5, grid=GRID, prior=(day_one,))
        assert run_source(settings, [], [endpoint]).steps == 5
        # Published again (`cfbci replay --publish`), with the prior its recording holds.
        again = publish_recording(session, tmp_path / "records" / "lab" / "after.mcap",
                                  session_id="lab/after-again")
        assert again.moves_divergence is None and again.states_divergence is None
        # Deleted, the prior is gone from the store, and a config naming it is refused.
        capsys.readouterr()
        assert main(["priors", "list", "--prior-dir", str(store), "--user", "lab"]) == 0
        assert sha256 in capsys.readouterr().out
        assert main(["priors", "delete", "--prior-dir", str(store), "--user", "lab",
                     sha256]) == 0
        assert not (store / "lab" / f"{sha256}.mcap").exists()
        assert f"deleted {store / 'lab' / sha256}.mcap" in capsys.readouterr().out
        assert main(["priors", "list", "--prior-dir", str(store), "--user", "lab"]) == 0
        assert sha256 not in capsys.readouterr().out
        message = rejection(session, "lab/s2", config_of(1, [sha256]))
        assert "is not in user 'lab''s prior store" in message


def next_event(listener: Listener) -> dict:
    """The next event of the listener's session id."""
    received = listener.inbox.get(timeout=TIMEOUT)
    return protocol.decode(received.data, key_expr=received.key_expr).fields


def test_a_prior_deleted_between_admission_and_start_refuses_the_session(
    record_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A config naming a stored prior is admitted (``session_pending``); the prior is
    deleted (`cfbci priors delete`) before the source answers the challenge: the answer
    is a ``session_rejected`` saying the prior is gone, no recording is left of the
    session, and the service runs the next session."""
    day_one = record_dir / "lab" / "day1.mcap"
    sha256 = file_sha256(day_one)
    store, records, sid = tmp_path / "store", tmp_path / "records", "lab/gone"
    endpoint = free_tcp_endpoint()
    with spawned(serve, [endpoint], [], records, prior_dir=store), zenoh.open(
        peer_config((), [endpoint])
    ) as session:
        listener = Listener(session, sid)  # subscribed before the upload's answers come
        try:
            assert upload_priors(session, "lab/up", [day_one], TIMEOUT, 1.0) == [sha256]
            config = listener.outbox.send("config", sid, config_of(1, [sha256]))
            pending = next_event(listener)
            assert pending["event"] == "session_pending", pending
            assert main(["priors", "delete", "--prior-dir", str(store), "--user", "lab",
                         sha256]) == 0
            listener.outbox.send("ready", sid, {"config_t_ns": config.t_ns,
                                                "challenge": pending["challenge"]})
            answer = next_event(listener)
        finally:
            listener.close()
        assert answer["event"] == "session_rejected", answer
        assert answer["config_t_ns"] == config.t_ns
        assert "internal error" not in answer["message"]
        assert (f"prior {sha256[:12]} is not in user 'lab''s prior store any more"
                in answer["message"]), answer["message"]
        # The service goes on: a session uploading the prior again runs.
        settings = SourceSettings("lab/after", seed=2, steps=5, grid=GRID, prior=(day_one,))
        assert run_source(settings, [], [endpoint]).steps == 5
    capsys.readouterr()
    assert not (records / "lab" / "gone.mcap").exists()  # no empty recording
    assert sorted(p.name for p in (records / "lab").iterdir()) == ["after.mcap"]


def test_cfbci_session_with_a_prior(record_dir: Path, tmp_path: Path) -> None:
    """`cfbci session --prior`: the embedded service takes the prior, the session equals
    its simulation, its recording replays identically, and nothing of the service's own
    store is left beside the recording."""
    day_one = record_dir / "lab" / "day1.mcap"
    record, out = tmp_path / "runs" / "day2.mcap", tmp_path / "day2.json"
    assert main(["session", "--seed", str(DAY_TWO_SEED), "--steps", str(STEPS), "--grid",
                 str(GRID), "--prior", str(day_one), "--record", str(record),
                 "--json", str(out)]) == 0
    trace = simulated(DAY_TWO_SEED, day_one)
    first = next(r.step for r in trace if r.event is not None)
    summary = json.loads(out.read_text())
    assert summary["first_target_step"] == first
    assert summary["correct_targets"] == sum(r.event == "correct_target" for r in trace)
    moves = [m for _, m in read_recording(record).messages["/move"]]
    assert [(m["from_state"], m["action"]) for m in moves] == [
        (r.state, r.action) for r in trace]
    assert main(["replay", str(record)]) == 0
    assert sorted(p.name for p in record.parent.iterdir()) == ["day2.mcap"]


def test_priors_add_copies_a_users_recording_into_its_store(
    record_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`cfbci priors add`: a recording copied into a user's folder under its SHA-256 (the
    digest printed, which a config names); a file that is no prior is refused, saying why,
    and nothing is copied."""
    day_one, store = record_dir / "lab" / "day1.mcap", tmp_path / "priors"
    capsys.readouterr()
    assert main(["priors", "add", "--prior-dir", str(store), "--user", "lab",
                 str(day_one)]) == 0
    sha256 = file_sha256(day_one)
    assert capsys.readouterr().out.startswith(sha256)
    assert (store / "lab" / f"{sha256}.mcap").read_bytes() == day_one.read_bytes()
    other = tmp_path / "not-a-recording.mcap"
    other.write_bytes(b"no mcap")
    assert main(["priors", "add", "--prior-dir", str(store), "--user", "lab-x",
                 str(other)]) == 2
    assert str(other) in capsys.readouterr().err
    assert main(["priors", "add", "--prior-dir", str(store), "--user", "a/b",
                 str(day_one)]) == 2
    assert "user 'a/b' is not a name" in capsys.readouterr().err
    assert sorted(p.name for p in store.iterdir()) == ["lab"]


def test_a_bad_prior_file_is_refused_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`cfbci session --prior`: a missing file, or a prior of another feature space than
    the session's, is refused with exit status 2 before any process starts."""
    record = tmp_path / "runs" / "s.mcap"
    missing = tmp_path / "nothing.mcap"
    assert main(["session", "--steps", "5", "--prior", str(missing), "--record",
                 str(record)]) == 2
    assert f"{missing}: no such file" in capsys.readouterr().err
    features = tmp_path / "features.mcap"
    gaussian_day(features, dims=2)
    assert main(["session", "--steps", "5", "--prior", str(features), "--record",
                 str(record)]) == 2
    err = capsys.readouterr().err
    assert "another feature space" in err and "sfreq: None vs 256.0" in err
    assert not record.parent.exists()


def test_behind_the_router_a_user_uploads_and_uses_only_its_own_priors(
    deployment: Deployment,  # noqa: F811  (the fixture)
) -> None:
    """With the shipped policy (deploy/router.json5): ``lab`` uploads its day 1 and runs
    day 2 with it; ``lab-x`` cannot upload into ``lab``'s key space (the router drops it:
    shown by an upload of its own, answered after, while the forged one left no trace in
    the store) and cannot use ``lab``'s prior."""
    grid = ("--grid", str(GRID))
    with router(deployment), service(deployment) as records:
        day_one = cfbci(deployment, *deployment.source_args(
            "lab", "lab/day1", "--steps", str(STEPS), "--seed", str(DAY_ONE_SEED), *grid))
        assert day_one.returncode == 0, day_one.stderr
        day_two = cfbci(deployment, *deployment.source_args(
            "lab", "lab/day2", "--steps", "10", *grid, "--prior",
            str(records / "lab" / "day1.mcap")))
        assert day_two.returncode == 0, day_two.stderr
        (sha256,) = read_recording(records / "lab" / "day2.mcap").config["prior"]
        store = records / "priors"
        assert sorted(p.name for p in store.iterdir()) == ["lab"]
        assert (store / "lab" / f"{sha256}.mcap").is_file()
        with zenoh.open(deployment.client_config("lab-x")) as session:
            forged = hashlib.sha256(b"forged").hexdigest()
            outbox = Outbox(session)
            outbox.send("prior", "lab/forged", {"sha256": forged, "size": 6, "offset": 0,
                                                "data": ""})
            outbox.close()
            own = Listener(session, "lab-x/probe")
            try:
                probe = hashlib.sha256(b"probe").hexdigest()
                answer = own.answer({"sha256": probe, "size": 5, "offset": 0, "data": ""})
            finally:
                own.close()
            assert answer["event"] == "prior_received" and answer["received"] == 0
            assert (store / "lab-x" / f"{probe}.part").exists()  # what an upload leaves
            assert sorted(p.name for p in (store / "lab").iterdir()) == [f"{sha256}.mcap"]
            message = rejection(session, "lab-x/s1", config_of(1, [sha256]))
            assert f"prior {sha256[:12]} is not in user 'lab-x''s prior store" in message


def test_an_lsl_bridge_session_with_a_prior(record_dir: Path, tmp_path: Path) -> None:
    """`cfbci lsl-bridge --prior`: a session bridged from LSL with day 1 (recorded by the
    service from `cfbci source`: the same feature space) as its prior, uploaded by the
    bridge, makes the decisions of `cfbci simulate --prior` and replays identically."""
    day_one, steps = record_dir / "lab" / "day1.mcap", 30
    endpoint = free_tcp_endpoint()
    with spawned(serve, [endpoint], [], tmp_path), lsl_clients(
        tmp_path, steps, DAY_TWO_SEED, endpoint, ["--onset-delay", "0.3"],
        ["--prior", str(day_one)],
    ) as finish:
        recording_path = finish().recording
    recording = read_recording(recording_path)
    assert recording.config["prior"] == [file_sha256(day_one)]
    moves = [(m["from_state"], m["action"]) for _, m in recording.messages["/move"]]
    trace = simulated(DAY_TWO_SEED, day_one, steps=steps, grid=5)
    assert moves == [(r.state, r.action) for r in trace]
    assert trace != simulated(DAY_TWO_SEED, None, steps=steps, grid=5)
    assert main(["replay", str(recording_path)]) == 0
