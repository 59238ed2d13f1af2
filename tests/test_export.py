"""``cfbci export``: a recording's raw epochs as MNE Epochs, read back with MNE.

The recordings are those of :mod:`test_recording_dataset` (a real service over loopback
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
from replay.recording import read_recording


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
