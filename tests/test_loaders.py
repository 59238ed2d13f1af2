"""Loading labelled data: the real thesis files, round trips, and every rejected input."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.io

from acquisition.labelled import LabelledEpochs
from acquisition.loaders import (
    features_from_epochs,
    load_epochs,
    load_labelled,
    save_epochs_npz,
    save_features_npz,
)
from decoding.features import ErrPFeatures

DATASETS = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"
S4 = DATASETS / "errp-features-s4" / "s4.mat"
FINGER = DATASETS / "finger-moves" / "move_finger.mat"

SFREQ, TMIN, N_TIMES = 256.0, -0.2, 308  # -0.2 s to 1.0 s after the action onset
CH_NAMES = ("Fz", "FCz", "Cz")
FEEDBACK_LABELS = np.array([0, 1] * 10)  # 20 signals, 10 per class
DROP = object()  # marks a key to leave out of a file


def need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data set {path} is absent (../shared/datasets is not in a fresh clone)")
    return path


def fails(path: Path, problem: str, error: type[Exception] = ValueError) -> Any:
    """Expect ``error`` whose message names the file, then the problem (a regex)."""
    return pytest.raises(error, match=f"{re.escape(path.name)}.*{problem}")


def features_arrays(**changes: Any) -> dict[str, Any]:
    rng = np.random.default_rng(0)
    arrays = {"features": rng.normal(size=(20, 5)), "labels": FEEDBACK_LABELS}
    arrays.update(changes)
    return {key: value for key, value in arrays.items() if value is not DROP}


def epochs_arrays(**changes: Any) -> dict[str, Any]:
    rng = np.random.default_rng(1)
    arrays = {
        "epochs": rng.normal(scale=10.0, size=(20, 3, N_TIMES)),
        "sfreq": np.float64(SFREQ),
        "tmin": np.float64(TMIN),
        "ch_names": np.array(CH_NAMES),
        "labels": FEEDBACK_LABELS,
    }
    arrays.update(changes)
    return {key: value for key, value in arrays.items() if value is not DROP}


def write_npz(path: Path, arrays: dict[str, Any]) -> Path:
    np.savez(path, **arrays)
    return path


def write_mat(path: Path, **variables: Any) -> Path:
    scipy.io.savemat(path, variables)
    return path


# --- the real recordings ------------------------------------------------------------------


def test_s4_loads_as_feedback_features() -> None:
    data = load_labelled(need(S4))
    assert data.features.shape == (1800, 34)
    assert data.features.dtype == np.float64
    assert data.n_classes == 2
    assert np.bincount(data.labels).tolist() == [1440, 360]  # 0 = correct, 1 = error
    assert data.source == str(S4)


def test_move_finger_loads_as_guidance_features() -> None:
    data = load_labelled(need(FINGER), frame="guidance")
    assert data.features.shape == (400, 11)
    assert data.n_classes == 4
    assert np.bincount(data.labels).tolist() == [100, 100, 100, 100]


def test_s4_is_not_guidance_data() -> None:
    with fails(S4, r"only 2 of the 4 classes.*frame='feedback'"):
        load_labelled(need(S4), frame="guidance")


def test_move_finger_is_not_feedback_data() -> None:
    with fails(FINGER, r"4 classes.*feedback frame needs exactly 2.*frame='guidance'"):
        load_labelled(need(FINGER), frame="feedback")


# --- round trips --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("frame", "labels"), [("feedback", FEEDBACK_LABELS), ("guidance", np.arange(20) % 4)]
)
def test_features_npz_round_trip(tmp_path: Path, frame: str, labels: np.ndarray) -> None:
    features = np.random.default_rng(2).normal(size=(20, 7))
    path = tmp_path / "features.npz"
    save_features_npz(path, features, labels)
    data = load_labelled(path, frame=frame)
    np.testing.assert_array_equal(data.features, features)
    np.testing.assert_array_equal(data.labels, labels)
    assert data.n_classes == len(np.unique(labels))
    assert data.source == str(path)


def test_epochs_npz_round_trip(tmp_path: Path) -> None:
    arrays = epochs_arrays()
    original = LabelledEpochs(
        epochs=arrays["epochs"],
        sfreq=SFREQ,
        tmin=TMIN,
        ch_names=CH_NAMES,
        labels=FEEDBACK_LABELS,
        n_classes=2,
        source="synthetic",
    )
    path = tmp_path / "epochs.npz"
    save_epochs_npz(path, original)
    loaded = load_epochs(path)
    np.testing.assert_array_equal(loaded.epochs, original.epochs)
    np.testing.assert_array_equal(loaded.labels, original.labels)
    assert (loaded.sfreq, loaded.tmin, loaded.ch_names) == (SFREQ, TMIN, CH_NAMES)
    assert (loaded.n_classes, loaded.source) == (2, str(path))


def test_epochs_npz_gives_errp_features(tmp_path: Path) -> None:
    path = write_npz(tmp_path / "epochs.npz", epochs_arrays())
    data = load_labelled(path)
    expected = ErrPFeatures(sfreq=SFREQ, tmin=TMIN, ch_names=CH_NAMES).fit_transform(
        epochs_arrays()["epochs"]
    )
    assert data.features.shape == (20, 57)  # 3 channels x 19 samples at 32 Hz
    np.testing.assert_allclose(data.features, expected)
    np.testing.assert_array_equal(data.labels, FEEDBACK_LABELS)
    assert data.source == str(path)
    np.testing.assert_allclose(features_from_epochs(load_epochs(path)).features, expected)


def test_mat_labels_become_zero_based(tmp_path: Path) -> None:
    # MATLAB saves doubles by default: whole-valued float labels are accepted.
    path = write_mat(tmp_path / "run.mat", X=np.ones((8, 3)), Y=np.arange(8.0)[:, None] % 4 + 1)
    data = load_labelled(path, frame="guidance")
    assert data.labels.tolist() == [0, 1, 2, 3, 0, 1, 2, 3]


# --- rejected files -----------------------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "absent.npz"
    with fails(path, "no such file", FileNotFoundError):
        load_labelled(path)


def test_directory(tmp_path: Path) -> None:
    path = tmp_path / "folder.npz"
    path.mkdir()
    with fails(path, "not a regular file"):
        load_labelled(path)


def test_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.mat"
    path.touch()
    with fails(path, r"empty \(0 bytes\)"):
        load_labelled(path)


def test_unknown_extension(tmp_path: Path) -> None:
    path = tmp_path / "data.csv"
    path.write_text("1,2,3\n")
    with fails(path, r"unknown file extension '\.csv'; expected \.mat .* or \.npz"):
        load_labelled(path)


def test_unknown_frame(tmp_path: Path) -> None:
    path = write_npz(tmp_path / "run.npz", features_arrays())
    with pytest.raises(ValueError, match="frame must be one of 'feedback', 'guidance'"):
        load_labelled(path, frame="errp")


def test_text_file_renamed_mat(tmp_path: Path) -> None:
    path = tmp_path / "notes.mat"
    path.write_text("these are notes, not MATLAB data\n" * 10)
    with fails(path, "could not be read as a MATLAB .mat file"):
        load_labelled(path)


def test_text_file_renamed_npz(tmp_path: Path) -> None:
    path = tmp_path / "notes.npz"
    path.write_text("these are notes, not NumPy data\n")
    with fails(path, r"not an \.npz archive \(no zip signature"):
        load_labelled(path)


def test_npy_file_renamed_npz(tmp_path: Path) -> None:
    path = tmp_path / "single.npz"
    with path.open("wb") as file:
        np.save(file, np.ones((4, 3)))
    with fails(path, r"single \.npy array, not an \.npz archive"):
        load_labelled(path)


def test_truncated_npz(tmp_path: Path) -> None:
    path = write_npz(tmp_path / "cut.npz", features_arrays())
    content = path.read_bytes()
    path.write_bytes(content[: len(content) // 2])
    with fails(path, r"could not be read as an \.npz archive \(corrupt or truncated\?\)"):
        load_labelled(path)


def test_truncated_mat(tmp_path: Path) -> None:
    path = write_mat(tmp_path / "cut.mat", X=np.ones((20, 3)), Y=FEEDBACK_LABELS + 1)
    content = path.read_bytes()
    path.write_bytes(content[: len(content) // 2])
    with fails(path, "could not be read as a MATLAB .mat file"):
        load_labelled(path)


def test_mat_v73_is_refused(tmp_path: Path) -> None:
    # A v7.3 file is HDF5 behind a MATLAB header whose version field reads 0x0200.
    header = b"MATLAB 7.3 MAT-file".ljust(116) + bytes(8) + b"\x00\x02IM"
    path = tmp_path / "hdf5.mat"
    path.write_bytes(header + bytes(512))
    with fails(path, r"v7\.3 \(HDF5\) files are not supported"):
        load_labelled(path)


def test_pickled_objects_are_not_loaded(tmp_path: Path) -> None:
    path = tmp_path / "objects.npz"
    np.savez(path, features=np.array([{"a": 1}, None], dtype=object), labels=[0, 1])
    with fails(path, "could not be read as an .npz archive.*allow_pickle=False"):
        load_labelled(path)


@pytest.mark.parametrize(
    ("variables", "problem"),
    [
        pytest.param(
            {"X": np.ones((20, 3))}, r"missing variable\(s\) 'Y'.*found 'X'", id="missing-Y"
        ),
        pytest.param(
            {"X": np.ones((20, 3)), "Y": FEEDBACK_LABELS + 1, "X_test": np.ones((2, 3))},
            r"unknown variable\(s\) 'X_test'.*exactly the variables 'X', 'Y'",
            id="unknown-variable",
        ),
        pytest.param(
            {"X": np.ones((20, 3, 2)), "Y": FEEDBACK_LABELS + 1},
            r"X must have 2 dimensions",
            id="X-rank",
        ),
        pytest.param(
            {"X": np.ones((20, 3)), "Y": np.ones((20, 2))},
            r"Y must be a vector.*\(20, 2\)",
            id="Y-shape",
        ),
        pytest.param(
            {"X": np.ones((20, 3)), "Y": FEEDBACK_LABELS[:19] + 1},
            "X has 20 signals but Y has 19",
            id="n-mismatch",
        ),
        pytest.param({"X": np.zeros((0, 0)), "Y": FEEDBACK_LABELS + 1}, "X is empty", id="empty"),
        pytest.param(
            {"X": "not numbers", "Y": FEEDBACK_LABELS + 1}, "X must hold real numbers", id="text-X"
        ),
        pytest.param(
            {"X": np.ones((20, 3)), "Y": np.where(FEEDBACK_LABELS, 3, 1)},
            r"unknown label\(s\) \[3\]",
            id="label-3",
        ),
        pytest.param(
            {"X": np.ones((20, 3)), "Y": FEEDBACK_LABELS},
            r"unknown label\(s\) \[0\].*1 = correct, 2 = error",
            id="zero-based",
        ),
    ],
)
def test_bad_mat_content(tmp_path: Path, variables: dict[str, Any], problem: str) -> None:
    path = write_mat(tmp_path / "bad.mat", **variables)
    with fails(path, problem):
        load_labelled(path)


NAN_FEATURES = np.ones((20, 5))
NAN_FEATURES[3, 2] = np.nan
INF_EPOCHS = np.ones((20, 3, N_TIMES))
INF_EPOCHS[0, 1, 5] = np.inf


@pytest.mark.parametrize(
    ("arrays", "frame", "problem"),
    [
        # keys
        pytest.param(
            features_arrays(labels=DROP),
            "feedback",
            r"missing key\(s\) 'labels'",
            id="missing-labels",
        ),
        pytest.param(
            features_arrays(labels=DROP, label=FEEDBACK_LABELS),
            "feedback",
            r"missing key\(s\) 'labels' and unknown key\(s\) 'label'.*found 'features', 'label'",
            id="typo-label",
        ),
        pytest.param(
            epochs_arrays(sfreq=DROP),
            "feedback",
            r"missing key\(s\) 'sfreq'.*an epochs \.npz",
            id="missing-sfreq",
        ),
        pytest.param(
            epochs_arrays(sfreq=DROP, tmin=DROP, ch_names=DROP),
            "feedback",
            r"missing key\(s\) 'sfreq', 'tmin', 'ch_names'.*found 'epochs', 'labels'",
            id="missing-several",
        ),
        pytest.param(
            epochs_arrays(montage=np.ones(3)),
            "feedback",
            r"unknown key\(s\) 'montage'",
            id="unknown-key",
        ),
        pytest.param(
            {**features_arrays(), "epochs": np.ones((20, 3, N_TIMES))},
            "feedback",
            r"holds both 'features' and 'epochs', so its format is unclear",
            id="both-formats",
        ),
        pytest.param(
            {"X": np.ones((20, 3)), "Y": FEEDBACK_LABELS},
            "feedback",
            r"holds neither 'features' nor 'epochs'.*found 'X', 'Y'",
            id="neither-format",
        ),
        # ranks, shapes, sizes
        pytest.param(
            features_arrays(features=np.ones(20)),
            "feedback",
            "features must have 2 dimensions",
            id="features-rank",
        ),
        pytest.param(
            features_arrays(labels=FEEDBACK_LABELS[:, None]),
            "feedback",
            "labels must have 1 dim",
            id="labels-rank",
        ),
        pytest.param(
            epochs_arrays(epochs=np.ones((20, 3))),
            "feedback",
            "epochs must have 3 dimensions",
            id="epochs-rank",
        ),
        pytest.param(
            epochs_arrays(sfreq=np.array([256.0, 512.0])),
            "feedback",
            "sfreq must be a single",
            id="sfreq-shape",
        ),
        pytest.param(
            features_arrays(labels=FEEDBACK_LABELS[:18]),
            "feedback",
            "20 signals but labels has 18",
            id="n-mismatch-features",
        ),
        pytest.param(
            epochs_arrays(labels=np.arange(22) % 2),
            "feedback",
            "20 signals but labels has 22",
            id="n-mismatch-epochs",
        ),
        pytest.param(
            epochs_arrays(ch_names=np.array(["Fz", "Cz"])),
            "feedback",
            "ch_names has 2 names but epochs has 3 channels",
            id="ch-names-length",
        ),
        pytest.param(
            epochs_arrays(ch_names=np.array(["Fz", "Fz", "Cz"])),
            "feedback",
            "ch_names must be distinct and non-empty",
            id="ch-names-duplicate",
        ),
        # empty arrays
        pytest.param(
            features_arrays(features=np.ones((0, 5)), labels=np.array([], dtype=int)),
            "feedback",
            r"features is empty \(shape \(0, 5\)\)",
            id="no-signals",
        ),
        pytest.param(
            features_arrays(features=np.ones((20, 0))),
            "feedback",
            "features is empty",
            id="no-features",
        ),
        pytest.param(
            epochs_arrays(epochs=np.ones((20, 3, 0))), "feedback", "epochs is empty", id="no-times"
        ),
        # values
        pytest.param(
            features_arrays(features=NAN_FEATURES),
            "feedback",
            "features holds NaN or infinite",
            id="nan-features",
        ),
        pytest.param(
            epochs_arrays(epochs=INF_EPOCHS),
            "feedback",
            "epochs holds NaN or infinite",
            id="inf-epochs",
        ),
        pytest.param(
            features_arrays(labels=np.where(FEEDBACK_LABELS, np.nan, 0)),
            "feedback",
            "labels holds NaN",
            id="nan-labels",
        ),
        pytest.param(
            epochs_arrays(sfreq=np.float64(0.0)),
            "feedback",
            r"sfreq must be positive \(Hz\)",
            id="zero-sfreq",
        ),
        pytest.param(
            epochs_arrays(sfreq=np.float64(-256.0)),
            "feedback",
            "sfreq must be positive",
            id="negative-sfreq",
        ),
        pytest.param(
            epochs_arrays(tmin=np.float64(np.inf)),
            "feedback",
            "tmin holds NaN or infinite",
            id="inf-tmin",
        ),
        # non-numeric data
        pytest.param(
            features_arrays(features=np.full((20, 5), "x")),
            "feedback",
            "features must hold real numbers; got dtype <U1",
            id="text-features",
        ),
        pytest.param(
            features_arrays(features=np.ones((20, 5), dtype=bool)),
            "feedback",
            "real numbers",
            id="bool-features",
        ),
        pytest.param(
            features_arrays(labels=np.array(["a", "b"] * 10)),
            "feedback",
            "labels must hold real",
            id="text-labels",
        ),
        pytest.param(
            epochs_arrays(sfreq=np.str_("256 Hz")),
            "feedback",
            "sfreq must hold real numbers",
            id="text-sfreq",
        ),
        pytest.param(
            epochs_arrays(ch_names=np.arange(3)),
            "feedback",
            "ch_names must hold strings",
            id="numeric-ch-names",
        ),
        # labels
        pytest.param(
            features_arrays(labels=FEEDBACK_LABELS + 0.5),
            "feedback",
            r"labels must be integers; got 0\.5 at index 0",
            id="fractional-labels",
        ),
        pytest.param(
            features_arrays(labels=np.where(FEEDBACK_LABELS, 1, -1)),
            "feedback",
            r"unknown label\(s\) \[-1\].*0 = correct, 1 = error",
            id="negative-label",
        ),
        pytest.param(
            features_arrays(labels=np.arange(20) % 4 * 2),
            "guidance",
            r"unknown label\(s\) \[4, 6\].*0\.\.3, one per move direction",
            id="guidance-unknown-labels",
        ),
        pytest.param(
            features_arrays(labels=np.array([0, 1, 3, 3] * 5)),
            "guidance",
            r"only 3 of the 4 classes.*no signal has label\(s\) \[2\]",
            id="guidance-gap",
        ),
        pytest.param(
            features_arrays(labels=np.zeros(20, dtype=int)),
            "feedback",
            r"single class \(every label is 0\)",
            id="single-class",
        ),
        pytest.param(
            features_arrays(labels=FEEDBACK_LABELS),
            "guidance",
            r"only 2 of the 4 classes.*this looks like feedback data",
            id="guidance-on-two-classes",
        ),
        pytest.param(
            epochs_arrays(labels=np.arange(20) % 4),
            "feedback",
            r"4 classes \[0, 1, 2, 3\]; the feedback frame needs exactly 2.*looks like guidance",
            id="feedback-on-four-classes",
        ),
        pytest.param(
            features_arrays(labels=np.array([1] + [0] * 19)),
            "feedback",
            r"too few signals for label\(s\) \[1\] \(counts \{0: 19, 1: 1\}\).*at least 2",
            id="one-signal-in-class",
        ),
        # the feature extractor's own checks
        pytest.param(
            epochs_arrays(ch_names=np.array(["O1", "Oz", "O2"])),
            "feedback",
            "none of the wanted channels",
            id="no-wanted-channel",
        ),
        pytest.param(
            epochs_arrays(epochs=np.ones((20, 3, 60))),
            "feedback",
            "too short",
            id="epochs-too-short",
        ),
    ],
)
def test_bad_npz_content(tmp_path: Path, arrays: dict[str, Any], frame: str, problem: str) -> None:
    path = write_npz(tmp_path / "bad.npz", arrays)
    with fails(path, problem):
        load_labelled(path, frame=frame)


def test_load_epochs_refuses_features_file(tmp_path: Path) -> None:
    path = write_npz(tmp_path / "features.npz", features_arrays())
    with fails(path, "holds feature vectors, not epochs; read it with load_labelled"):
        load_epochs(path)


def test_load_epochs_refuses_mat_file(tmp_path: Path) -> None:
    path = write_mat(tmp_path / "run.mat", X=np.ones((20, 3)), Y=FEEDBACK_LABELS + 1)
    with fails(path, r"epochs are stored in \.npz files; got extension '\.mat'"):
        load_epochs(path)


def test_load_epochs_checks_labels_for_frame(tmp_path: Path) -> None:
    path = write_npz(tmp_path / "epochs.npz", epochs_arrays())
    with fails(path, "only 2 of the 4 classes"):
        load_epochs(path, frame="guidance")


def test_writers_refuse_other_extensions(tmp_path: Path) -> None:
    path = tmp_path / "features.dat"
    with fails(path, r"must end in \.npz; got '\.dat'"):
        save_features_npz(path, np.ones((20, 5)), FEEDBACK_LABELS)
    assert not path.exists() and not path.with_name("features.dat.npz").exists()


def test_writers_refuse_bad_content(tmp_path: Path) -> None:
    path = tmp_path / "features.npz"
    with fails(path, "features has 20 signals but labels has 19"):
        save_features_npz(path, np.ones((20, 5)), FEEDBACK_LABELS[:19])
    epochs = LabelledEpochs(
        epochs=np.ones((20, 3, N_TIMES)),
        sfreq=-1.0,
        tmin=TMIN,
        ch_names=CH_NAMES,
        labels=FEEDBACK_LABELS,
        n_classes=2,
        source="synthetic",
    )
    with fails(path, "sfreq must be positive"):
        save_epochs_npz(path, epochs)
    assert not path.exists()
