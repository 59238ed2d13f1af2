"""A session recording used as a labelled dataset: its epochs, labelled by its truth.

The recordings are made by a real service (a spawned process) answering real replay sources
over Zenoh on loopback TCP, multicast off, and read once the service has stopped (complete).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from live import TIMEOUT, rewrite, service_process

from acquisition.labelled import LabelledEpochs, LabelledFeatures
from acquisition.loaders import load_epochs, load_labelled, load_recording_dataset
from acquisition.simulated_source import SourceSettings, run_source
from acquisition.sources import DEFAULT_SYNTHETIC_ACCURACY, DataSpec, synthetic_features
from calibration_free.streams import StepRecord
from cfbci.cli import main
from cfbci.offline.simulation import SessionConfig, run_session
from replay.recording import Recording, decode_array, read_recording
from replay.rerun import replay_check
from wire.zenoh_config import free_tcp_endpoint

STEPS, GRID = 60, 3
REPLAY_SEED = 1  # a session on the raw recording's 60 epochs that reaches targets


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two recorded live sessions: synthetic raw epochs ("raw") and synthetic feature vectors
    from a features ``.npz`` file ("feat"; 34 features, as ``s4.mat``'s)."""
    directory = tmp_path_factory.mktemp("recordings")
    features = synthetic_features(DEFAULT_SYNTHETIC_ACCURACY, np.random.default_rng(4))
    features_file = directory / "features.npz"
    np.savez(features_file, features=features.features, labels=features.labels)
    endpoint = free_tcp_endpoint()
    with service_process(endpoint, directory):
        for session, data in (("raw", DataSpec()), ("feat", DataSpec(features_file))):
            settings = SourceSettings(
                session, data=data, seed=1, steps=STEPS, grid=GRID, timeout=TIMEOUT
            )
            run_source(settings, [], [endpoint])
    return {session: directory / f"{session}.mcap" for session in ("raw", "feat")}


def _truth_labels(recording: Recording) -> list[int]:
    return [m["label"] for _, m in recording.messages["/truth"]]


def _payloads(recording: Recording, topic: str) -> np.ndarray:
    return np.stack([decode_array(m) for _, m in recording.messages[topic]])


def test_a_recording_of_raw_epochs_gives_its_epochs_and_truth_labels(
    recordings: dict[str, Path],
) -> None:
    path = recordings["raw"]
    recording = read_recording(path)
    data = load_recording_dataset(path, frame="feedback")
    assert isinstance(data, LabelledEpochs)
    assert data.epochs.dtype == np.float32 and data.epochs.shape[0] == STEPS
    assert np.array_equal(data.epochs, _payloads(recording, "/epoch"))  # bit for bit
    assert data.labels.tolist() == _truth_labels(recording)
    assert set(data.labels.tolist()) == {0, 1} and data.n_classes == 2
    config = recording.config
    assert (data.sfreq, data.tmin, list(data.ch_names)) == (
        config["sfreq"], config["tmin"], config["ch_names"],
    )
    assert data.source == str(path)
    assert np.array_equal(load_epochs(path).epochs, data.epochs)
    # As features (what `cfbci simulate` uses): the service's own features, bit for bit.
    features = load_labelled(path)
    assert np.array_equal(features.features.astype(np.float32), _payloads(recording, "/features"))
    assert features.labels.tolist() == _truth_labels(recording)


def test_a_recording_of_features_gives_its_feature_vectors(recordings: dict[str, Path]) -> None:
    path = recordings["feat"]
    recording = read_recording(path)
    data = load_recording_dataset(path)
    assert isinstance(data, LabelledFeatures)
    assert data.features.shape == (STEPS, 57)
    assert np.array_equal(data.features, _payloads(recording, "/epoch").astype(np.float64))
    assert data.labels.tolist() == _truth_labels(recording)
    assert np.array_equal(load_labelled(path).features, data.features)
    with pytest.raises(ValueError, match="sent feature vectors, not raw epochs"):
        load_epochs(path)


def test_simulate_and_a_live_source_answer_from_the_recording(
    recordings: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = recordings["raw"]
    report_path, trace_path = tmp_path / "report.json", tmp_path / "trace.jsonl"
    assert main([
        "simulate", "--dataset", str(path), "--seeds", "1", "--first-seed", str(REPLAY_SEED),
        "--steps", str(STEPS), "--grid", str(GRID), "--jobs", "1",
        "--json", str(report_path), "--trace", str(trace_path),
    ]) == 0
    (session,) = json.loads(report_path.read_text())["sessions"]
    assert session["first_target_step"] is not None and session["correct_targets"] >= 1
    trace = [StepRecord(**json.loads(line)) for line in trace_path.read_text().splitlines()]
    assert len(trace) == STEPS
    expected: list[StepRecord] = []
    run_session(REPLAY_SEED, SessionConfig(steps=STEPS, grid=GRID), load_labelled(path),
                expected.append)
    assert trace == expected

    # `cfbci source` sends the recording's raw epochs (its sfreq, tmin, ch_names): the
    # service decides as the simulation did.
    endpoint = free_tcp_endpoint()
    record_dir = tmp_path / "service"
    with service_process(endpoint, record_dir):
        assert main([
            "source", "--session", "again", "--dataset", str(path), "--seed", str(REPLAY_SEED),
            "--steps", str(STEPS), "--grid", str(GRID), "--connect", endpoint,
        ]) == 0
    assert (
        f"first target {session['first_target_step']}, correct {session['correct_targets']}, "
        f"wrong {session['wrong_targets']}"
    ) in capsys.readouterr().out
    again = read_recording(record_dir / "again.mcap")
    original = read_recording(path).config
    assert again.config["signal"] == "epochs"
    assert [again.config[k] for k in ("sfreq", "tmin", "ch_names")] == [
        original[k] for k in ("sfreq", "tmin", "ch_names")
    ]
    moves = [m for _, m in again.messages["/move"]]
    assert [(m["from_state"], m["action"]) for m in moves] == [(r.state, r.action) for r in trace]
    # Every epoch it sent is one of the recording's, with the recorded label of that epoch.
    data = load_recording_dataset(path)
    by_bytes = {epoch.tobytes(): int(label) for epoch, label in zip(data.epochs, data.labels,
                                                                   strict=True)}
    sent = [decode_array(m).tobytes() for _, m in again.messages["/epoch"]]
    assert [by_bytes[epoch] for epoch in sent] == _truth_labels(again)


def test_unusable_recordings_are_clear_errors_naming_the_file(
    recordings: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recording = read_recording(recordings["raw"])
    with pytest.raises(ValueError, match=r"raw\.mcap: a recording of a 'feedback'-frame"):
        load_recording_dataset(recordings["raw"], frame="guidance")

    no_truth = tmp_path / "no-truth.mcap"
    recording.messages["/truth"] = []
    rewrite(recording, no_truth)
    with pytest.raises(ValueError, match=r"no-truth\.mcap: the recording holds no /truth"):
        load_recording_dataset(no_truth)
    assert main(["simulate", "--dataset", str(no_truth), "--seeds", "1", "--steps", "5"]) == 2
    err = "".join(capsys.readouterr().err.split())  # rich may fold a long path anywhere
    assert f"{no_truth}:therecordingholdsno/truthmessages" in err

    recording = read_recording(recordings["raw"])
    truths = [m for _, m in recording.messages["/truth"]]
    for i, truth in enumerate(truths):
        truth["label"] = int(i == 7)  # one error epoch only
    scarce = tmp_path / "scarce.mcap"
    rewrite(recording, scarce)
    with pytest.raises(ValueError, match=r"scarce\.mcap: truth labels has too few signals"):
        load_recording_dataset(scarce)
    truths[7]["label"] = 0
    single = tmp_path / "single.mcap"
    rewrite(recording, single)
    with pytest.raises(ValueError, match=r"single\.mcap: truth labels has a single class"):
        load_labelled(single)

    text = tmp_path / "text.mcap"
    text.write_text("not a recording")
    with pytest.raises(ValueError, match=r"text\.mcap: not an MCAP file"):
        load_recording_dataset(text)
    with pytest.raises(FileNotFoundError, match=r"nope\.mcap"):
        load_recording_dataset(tmp_path / "nope.mcap")


def test_rejected_epochs_are_left_out(recordings: dict[str, Path], tmp_path: Path) -> None:
    """``/epoch`` holds rejected epochs too (no ``/features`` of their seq): neither the
    dataset nor the re-run uses them."""
    path = recordings["raw"]
    recording = read_recording(path)
    epochs = recording.messages["/epoch"]
    log_time, tenth = epochs[9]
    rejected = {**tenth, "seq": 10_000, "step": 99}  # e.g. an epoch of a wrong step
    epochs.insert(10, (log_time + 1, rejected))
    with_rejected = tmp_path / "with-rejected.mcap"
    rewrite(recording, with_rejected)
    assert len(read_recording(with_rejected).messages["/epoch"]) == STEPS + 1

    data = load_recording_dataset(with_rejected)
    assert isinstance(data, LabelledEpochs)
    assert np.array_equal(data.epochs, load_recording_dataset(path).epochs)
    assert replay_check(with_rejected).divergence is None
