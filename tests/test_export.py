"""``cfbci export``: a recording's raw epochs as MNE Epochs, read back with MNE.

The recordings are those of `test_recording_dataset` (a real service over loopback
Zenoh recording real replay sources): raw synthetic epochs, and feature vectors.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import mne
import numpy as np
import pytest
from test_recording_dataset import STEPS, recordings  # noqa: F401 (a fixture)

from acquisition.labelled import LabelledEpochs
from acquisition.loaders import load_epochs, load_recording_dataset
from cfbci.cli import main
from replay.recording import SessionRecorder, read_recording


def printed_error(capsys: pytest.CaptureFixture[str]) -> str:
    """What the command wrote to stderr, with rich's line folding undone."""
    return " ".join(capsys.readouterr().err.split())


def test_a_recording_of_raw_epochs_exports_to_mne_and_reads_back_equal(
    recordings: dict[str, Path],  # noqa: F811
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    recorded = load_recording_dataset(recordings["raw"])
    assert isinstance(recorded, LabelledEpochs)
    config = read_recording(recordings["raw"]).config
    out = tmp_path / "raw-epo.fif"
    assert main(["export", str(recordings["raw"]), "--format", "fif", "--out", str(out)]) == 0
    assert f"exported {STEPS} epochs" in capsys.readouterr().out

    epochs = mne.read_epochs(out, preload=True, verbose="error")
    volts = epochs.get_data()
    assert volts.shape == recorded.epochs.shape
    # µV -> V exactly within float64 rounding; back to float32 µV bit for bit.
    np.testing.assert_allclose(volts, recorded.epochs.astype(np.float64) * 1e-6, rtol=1e-15)
    assert np.array_equal((volts * 1e6).astype(np.float32), recorded.epochs)
    assert epochs.ch_names == list(config["ch_names"])
    assert set(epochs.get_channel_types()) == {"eeg"}
    assert (epochs.info["sfreq"], epochs.tmin) == (config["sfreq"], config["tmin"])
    assert epochs.event_id == {"correct": 1, "error": 2}
    assert epochs.events[:, 2].tolist() == (recorded.labels + 1).tolist()  # truth labels
    assert epochs.events[:, 0].tolist() == list(range(STEPS))
    assert len(epochs["error"]) == int(recorded.labels.sum()) > 0

    again = load_epochs(out)  # the exported file is a dataset too
    assert again.labels.tolist() == recorded.labels.tolist()
    np.testing.assert_allclose(again.epochs, recorded.epochs, rtol=1e-12)


def test_export_writes_beside_the_recording_by_default(
    recordings: dict[str, Path],  # noqa: F811
    tmp_path: Path,
) -> None:
    copy = tmp_path / "session.mcap"
    shutil.copy(recordings["raw"], copy)
    assert main(["export", str(copy)]) == 0
    assert len(mne.read_epochs(tmp_path / "session-epo.fif", verbose="error")) == STEPS


def test_a_recording_of_features_or_a_bad_name_is_refused(
    recordings: dict[str, Path],  # noqa: F811
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "feat-epo.fif"
    assert main(["export", str(recordings["feat"]), "--out", str(out)]) == 2
    err = printed_error(capsys)
    assert "feat.mcap: the session sent feature vectors, not raw epochs" in err
    assert "no epochs to export as MNE Epochs" in err
    assert not out.exists()

    assert main(["export", str(recordings["raw"]), "--out", str(tmp_path / "raw.fif")]) == 2
    assert "raw.fif: an MNE epochs file name must end in -epo.fif" in printed_error(capsys)
    assert main(["export", str(tmp_path / "missing.mcap")]) == 2
    assert "missing.mcap: no such file" in printed_error(capsys)


def _guidance_recording(
    path: Path, world: dict[str, object], labels: list[int]
) -> np.ndarray:
    """A recording of a guidance session of raw epochs in ``world`` (a real MCAP file by the
    service's recorder), one epoch and truth per label; returns the epochs (float32 µV).
    ``world``: the config's world fields."""
    rng = np.random.default_rng(0)
    epochs = rng.normal(0.0, 5.0, size=(len(labels), 2, 16)).astype(np.float32)
    config = {
        "seed": 0, **world, "frame": "guidance", "steps": len(labels), "learner": {},
        "dataset": {}, "signal": "epochs", "sfreq": 64.0, "tmin": -0.25, "ch_names": ["Fz", "Cz"],
    }
    with SessionRecorder(path, "guided", config) as recorder:
        for step, (epoch, label) in enumerate(zip(epochs, labels, strict=True), start=1):
            header = {"seq": step - 1, "t_ns": step, "step": step, "units": "uV"}
            recorder.record_array("/epoch", header, epoch, step)
            truth = {"seq": step - 1, "t_ns": step, "step": step, "target": 0, "label": label}
            recorder.record("/truth", truth, step)
    return epochs


def test_guidance_classes_are_named_by_the_recorded_worlds_actions(tmp_path: Path) -> None:
    labels = [0, 1, 2, 3, 2, 1, 0, 3, 3, 2]
    recording = tmp_path / "pick.mcap"
    epochs = _guidance_recording(recording, {"world": "pick-and-place"}, labels)
    out = tmp_path / "pick-epo.fif"
    assert main(["export", str(recording), "--out", str(out)]) == 0

    written = mne.read_epochs(out, preload=True, verbose="error")
    assert written.event_id == {
        "pick-and-place/right": 1, "pick-and-place/left": 2, "pick-and-place/grasp": 3,
        "pick-and-place/release": 4,
    }
    assert written.events[:, 2].tolist() == [k + 1 for k in labels]
    assert len(written["grasp"]) == labels.count(2)  # MNE selects by the action's tag
    again = load_epochs(out, frame="guidance")  # read back with the world's names
    assert again.labels.tolist() == labels
    assert np.array_equal((written.get_data() * 1e6).astype(np.float32), epochs)

    grid = tmp_path / "grid.mcap"
    _guidance_recording(grid, {"world": "grid", "grid": 4}, [0, 1, 2, 3] * 2)
    assert main(["export", str(grid), "--out", str(tmp_path / "grid-epo.fif")]) == 0
    assert mne.read_epochs(tmp_path / "grid-epo.fif", verbose="error").event_id == {
        "up": 1, "down": 2, "left": 3, "right": 4,
    }
