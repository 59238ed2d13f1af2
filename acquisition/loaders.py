"""Read labelled BCI data from disk; `load_labelled` is the single entry point.

Six formats are read, chosen by the file extension and then checked against the content:

``.mat`` (MATLAB v4-v7, read with `scipy.io.loadmat`; the thesis data sets)
    Variable ``X``, shape (n_signals, n_features), real numbers (microvolts for ErrP
    features), and variable ``Y``, shape (n_signals, 1), (1, n_signals) or (n_signals,),
    1-based labels: feedback 1 = correct, 2 = error; guidance 1..4, one per move direction.
``.npz`` features (written by `save_features_npz`)
    ``features`` float, shape (n_signals, n_features); ``labels`` int, shape (n_signals,),
    0-based: feedback 0 = correct, 1 = error; guidance 0..3.
``.npz`` epochs (written by `save_epochs_npz`)
    ``epochs`` float, shape (n_epochs, n_channels, n_times), microvolts; ``sfreq`` scalar,
    Hz; ``tmin`` scalar, seconds (time of the first sample relative to action onset);
    ``ch_names`` str, shape (n_channels,); ``labels`` int, shape (n_epochs,), 0-based.
    `decoding.features.ErrPFeatures` turns the epochs into feature vectors.
``.mcap`` session recordings (written by `replay.recording.SessionRecorder`)
    The epochs the session's service accepted (``/epoch``), each labelled with the
    ``label`` of its step's ``/truth``: raw epochs (float32 microvolts, with the recorded
    ``sfreq``, ``tmin`` and ``ch_names``) when the session sent raw epochs, feature
    vectors otherwise; see `load_recording_dataset`.
``-epo.fif`` MNE epochs (``.fif``, ``.fif.gz``; optional package ``mne``)
    The EEG channels not marked bad, volts turned into microvolts, with the file's
    ``sfreq``, ``tmin`` and channel names; labels from the event names (``correct``,
    ``error``; guidance ``up``, ``down``, ``left``, ``right``; or MNE tags of them such as
    ``feedback/error``), or from the event codes in the ``.mat`` convention when every event
    name is a number; see `acquisition.lab_formats`.
``.xdf`` XDF recordings (``.xdfz``, ``.xdf.gz``; optional package ``pyxdf``)
    One ``EEG`` stream and one ``Markers`` stream; every marker whose value is a class name
    (as for MNE event names) is an action onset, and its epoch is cut MNE-style from
    -0.2 s to 1.0 s around it (`acquisition.lab_formats.XDF_EPOCH_WINDOW`); see
    `acquisition.lab_formats`.

Labels always come back 0-based. The *feedback* frame needs exactly 2 classes (correct,
error); the *guidance* frame exactly 4 (the four move directions). Every class needs at least
`MIN_SIGNALS_PER_CLASS` signals. A file holding anything else -- missing or unknown
keys, wrong shapes, NaN, non-integer or unknown labels -- is rejected with a ``ValueError``
that names the file and the problem; unknown keys are rejected rather than ignored, so a typo
(``label`` for ``labels``) or a stray array (``X_test``) never goes unnoticed. NumPy files are
always read with ``allow_pickle=False``.
"""

from __future__ import annotations

import os
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io

from acquisition.lab_formats import read_fif_epochs, read_xdf_epochs, write_fif_epochs
from acquisition.labelled import LabelledEpochs, LabelledFeatures
from calibration_free.world import World
from decoding.features import ErrPFeatures
from decoding.validation import check_array, check_option
from replay.recording import decode_array, read_recording

PathLike = str | os.PathLike[str]

#: Number of classes each frame needs: correct/error, or the four move directions.
N_CLASSES = {"feedback": 2, "guidance": 4}

#: Fewest signals a class may have: one signal gives a class mean but no spread.
MIN_SIGNALS_PER_CLASS = 2

_MAT_VARIABLES = ("X", "Y")
_FEATURE_KEYS = ("features", "labels")
_EPOCH_KEYS = ("epochs", "sfreq", "tmin", "ch_names", "labels")
#: File-name endings of the formats read by `acquisition.lab_formats`.
_LAB_FORMATS = {".fif": "fif", ".fif.gz": "fif", ".xdf": "xdf", ".xdfz": "xdf", ".xdf.gz": "xdf"}
#: The endings MNE expects of an epochs file's name.
_FIF_EPOCHS_ENDINGS = ("-epo.fif", "_epo.fif", "-epo.fif.gz", "_epo.fif.gz")


def load_labelled(path: PathLike, *, frame: str = "feedback") -> LabelledFeatures:
    """Load feature vectors and 0-based labels from a file of one of the six formats.

    Parameters
    ----------
    path : str or path-like
        A ``.mat`` file (``X``, ``Y``), a features ``.npz``, an epochs ``.npz``, a session
        recording ``.mcap`` (see the module docstring and `load_recording_dataset`),
        MNE epochs (``-epo.fif``) or an XDF recording (``.xdf``).
        Epochs are turned into features with `decoding.features.ErrPFeatures` and
        its default channels.
    frame : {"feedback", "guidance"}
        "feedback": exactly 2 classes, 0 = correct, 1 = error (1 and 2 in a ``.mat``).
        "guidance": exactly 4 classes, one per move direction, 0..3 (1..4 in a ``.mat``).

    Returns
    -------
    LabelledFeatures
        ``features`` float64, shape (n_signals, n_features) (microvolts for ErrP data);
        ``labels`` int64, shape (n_signals,), 0..n_classes-1; ``source`` the path.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If the file cannot be read or its content breaks the format; the message names the
        file and the problem.
    """
    check_option("frame", frame, N_CLASSES)
    path = _existing_file(path)
    where = str(path)
    suffix = path.suffix.lower()
    if suffix == ".mat":
        return _load_mat(path, frame)
    if suffix == ".mcap":
        data = load_recording_dataset(path, frame=frame)
        return features_from_epochs(data) if isinstance(data, LabelledEpochs) else data
    if _lab_format(path) is not None:
        return features_from_epochs(_lab_epochs(path, frame))
    if suffix != ".npz":
        raise ValueError(
            f"{where}: unknown file extension {path.suffix!r}; expected .mat (MATLAB X and Y), "
            ".mcap (a session recording), -epo.fif (MNE epochs), .xdf (an XDF recording) or "
            ".npz (features or epochs)"
        )
    arrays = _read_npz(path)
    if _npz_format(arrays, where) == "epochs":
        return features_from_epochs(_epochs_from_arrays(arrays, where, frame))
    features, labels = _parse_features(arrays, where)
    return LabelledFeatures(
        features=features,
        labels=_check_classes(labels, frame, offset=0, name="labels", where=where),
        n_classes=N_CLASSES[frame],
        source=where,
    )


def load_epochs(path: PathLike, *, frame: str = "feedback") -> LabelledEpochs:
    """Load raw labelled epochs from a file that holds them (see the module docstring).

    Parameters
    ----------
    path : str or path-like
        An epochs ``.npz`` as written by `save_epochs_npz`, a session recording of
        raw epochs (``.mcap``), MNE epochs (``-epo.fif``) or an XDF recording (``.xdf``).
    frame : {"feedback", "guidance"}
        Which labels are valid, as in `load_labelled`.

    Returns
    -------
    LabelledEpochs
        ``epochs`` float64, shape (n_epochs, n_channels, n_times), microvolts; ``sfreq`` Hz;
        ``tmin`` s; ``ch_names`` tuple of n_channels str; ``labels`` int64, shape
        (n_epochs,), 0..n_classes-1.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If the file holds no epochs (e.g. a features ``.npz``) or breaks its format.
    """
    check_option("frame", frame, N_CLASSES)
    path = _existing_file(path)
    where = str(path)
    if path.suffix.lower() == ".mcap":
        data = load_recording_dataset(path, frame=frame)
        if not isinstance(data, LabelledEpochs):
            raise ValueError(f"{where}: the session sent feature vectors, not raw epochs")
        return data
    if _lab_format(path) is not None:
        return _lab_epochs(path, frame)
    if path.suffix.lower() != ".npz":
        raise ValueError(
            f"{where}: epochs are stored in .npz files; got extension {path.suffix!r} (session "
            "recordings of raw epochs, .mcap, MNE epochs, -epo.fif, and XDF recordings, .xdf, "
            "hold them too)"
        )
    arrays = _read_npz(path)
    if _npz_format(arrays, where) != "epochs":
        raise ValueError(
            f"{where}: holds feature vectors, not epochs; read it with load_labelled()"
        )
    return _epochs_from_arrays(arrays, where, frame)


def load_recording_dataset(
    path: PathLike, *, frame: str | None = "feedback"
) -> LabelledEpochs | LabelledFeatures:
    """A session recording as a labelled dataset: its epochs, labelled by its truth.

    Every epoch the recorded service accepted (its ``/features`` was recorded; all of
    ``/epoch`` in a recording without ``/features``) whose step has a ``/truth`` message is
    kept, in step order, with that truth's ``label`` (feedback 0 = correct, 1 = error;
    guidance 0..3, one per move direction). Epochs without a truth (the last ones of a cut
    recording) are left out.

    Parameters
    ----------
    path : str or path-like
        An ``.mcap`` recording (`replay.recording.SessionRecorder`), complete or cut.
    frame : {"feedback", "guidance"} or None
        Must be the recorded session's frame; None: the recorded session's frame.

    Returns
    -------
    LabelledEpochs or LabelledFeatures
        Raw epochs when the session sent them (``signal`` "epochs"): ``epochs`` float32
        microvolts exactly as received, shape (n, n_channels, n_times), with the recorded
        ``sfreq``, ``tmin`` and ``ch_names``. Otherwise the feature vectors sent, float64
        (exact copies of the float32 values), shape (n, n_features). ``labels`` int64,
        ``source`` the path.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If the file is not a recording, holds no configuration, was recorded in another
        frame, holds no truth, or too few signals of a class; the message names the file.
    """
    if frame is not None:
        check_option("frame", frame, N_CLASSES)
    path = _existing_file(path)
    where = str(path)
    recording = read_recording(path)  # a ValueError naming the file if it is not MCAP
    config = recording.config
    if not config:
        raise ValueError(f"{where}: the recording holds no session configuration")
    if frame is None and config.get("frame") in N_CLASSES:
        frame = config["frame"]
    if config.get("frame") != frame:
        raise ValueError(
            f"{where}: a recording of a {config.get('frame')!r}-frame session; its labels do "
            f"not suit the {frame!r} frame"
        )
    truth = {m["step"]: m["label"] for _, m in recording.messages.get("/truth", [])}
    if not truth:
        raise ValueError(
            f"{where}: the recording holds no /truth messages, so its epochs have no labels "
            "(record a session whose source publishes truth, such as `cfbci session`)"
        )
    epochs = [m for m in recording.accepted_epochs() if m.get("step") in truth]
    if not epochs:
        raise ValueError(f"{where}: no recorded epoch has a truth message of its step")
    labels = _check_classes(
        np.array([truth[m["step"]] for m in epochs], dtype=np.int64),
        frame, offset=0, name="truth labels", where=where,
    )
    signals = np.stack([decode_array(m) for m in epochs])
    if config.get("signal") == "epochs":
        return LabelledEpochs(
            epochs=signals,
            sfreq=float(config["sfreq"]),
            tmin=float(config["tmin"]),
            ch_names=tuple(config["ch_names"]),
            labels=labels,
            n_classes=N_CLASSES[frame],
            source=where,
        )
    return LabelledFeatures(
        features=signals.astype(np.float64),
        labels=labels,
        n_classes=N_CLASSES[frame],
        source=where,
    )


def features_from_epochs(epochs: LabelledEpochs) -> LabelledFeatures:
    """Turn labelled epochs into ErrP feature vectors with `ErrPFeatures`.

    Parameters
    ----------
    epochs : LabelledEpochs
        Epochs, shape (n_epochs, n_channels, n_times), in microvolts.

    Returns
    -------
    LabelledFeatures
        ``features`` float64, shape (n_epochs, n_features); labels, ``n_classes`` and
        ``source`` are those of ``epochs``.

    Raises
    ------
    ValueError
        If the extractor rejects the epochs (e.g. a needed channel is missing); the message
        starts with ``epochs.source``.
    """
    try:
        extractor = ErrPFeatures(sfreq=epochs.sfreq, tmin=epochs.tmin, ch_names=epochs.ch_names)
        features = extractor.fit_transform(epochs.epochs)
    except ValueError as exc:
        raise ValueError(f"{epochs.source}: {exc}") from exc
    return LabelledFeatures(
        features=np.asarray(features, dtype=np.float64),
        labels=epochs.labels,
        n_classes=epochs.n_classes,
        source=epochs.source,
    )


def save_features_npz(path: PathLike, features: np.ndarray, labels: np.ndarray) -> None:
    """Write feature vectors and 0-based labels as a features ``.npz``.

    Parameters
    ----------
    path : str or path-like
        Destination; must end in ``.npz``.
    features : array, shape (n_signals, n_features)
        Finite real numbers (microvolts for ErrP features).
    labels : array of int, shape (n_signals,)
        0-based classes (feedback 0 = correct, 1 = error; guidance 0..3).

    Raises
    ------
    ValueError
        If ``path`` does not end in ``.npz`` or the arrays break the format.
    """
    path = _npz_destination(path)
    arrays = {"features": features, "labels": labels}
    features, labels = _parse_features(arrays, str(path))
    np.savez(path, features=features, labels=labels)


def save_epochs_npz(path: PathLike, epochs: LabelledEpochs) -> None:
    """Write labelled epochs as an epochs ``.npz`` that `load_epochs` reads back.

    Parameters
    ----------
    path : str or path-like
        Destination; must end in ``.npz``.
    epochs : LabelledEpochs
        Epochs, shape (n_epochs, n_channels, n_times), microvolts, with ``sfreq`` (Hz),
        ``tmin`` (s), ``ch_names`` and 0-based ``labels``.

    Raises
    ------
    ValueError
        If ``path`` does not end in ``.npz`` or the epochs break the format.
    """
    path = _npz_destination(path)
    arrays = {
        "epochs": epochs.epochs,
        "sfreq": np.float64(epochs.sfreq),
        "tmin": np.float64(epochs.tmin),
        "ch_names": np.array(epochs.ch_names, dtype=str),
        "labels": epochs.labels,
    }
    _parse_epochs(arrays, str(path))
    np.savez(path, **arrays)


def save_epochs_fif(path: PathLike, epochs: LabelledEpochs, world: World | None = None) -> None:
    """Write labelled epochs as an MNE epochs file that `load_epochs` reads back.

    Parameters
    ----------
    path : str or path-like
        Destination; must end in ``-epo.fif`` (or ``_epo.fif``, ``.gz`` optional), MNE's
        convention for epochs files. Overwritten if it exists.
    epochs : LabelledEpochs
        Epochs in microvolts (written in volts, float64), with ``sfreq``, ``tmin``,
        ``ch_names`` (EEG channels) and 0-based labels, which become events
        ``[i, 0, label + 1]`` named after their classes (``correct``, ``error``; guidance
        ``up``, ``down``, ``left``, ``right``, or ``world``'s guidance actions); see
        `acquisition.lab_formats.write_fif_epochs`.
    world : World, optional
        The world whose guidance classes name the events (None: a grid).

    Raises
    ------
    ValueError
        If the name does not end as MNE expects, the epochs break the format, ``mne`` is not
        installed, or ``epochs.n_classes`` is that of no frame.
    """
    path = Path(path)
    if not path.name.lower().endswith(_FIF_EPOCHS_ENDINGS):
        raise ValueError(f"{path}: an MNE epochs file name must end in -epo.fif")
    frames = {n: frame for frame, n in N_CLASSES.items()}
    if epochs.n_classes not in frames:
        raise ValueError(f"{path}: {epochs.n_classes} classes are those of no frame")
    arrays = {
        "epochs": epochs.epochs, "sfreq": epochs.sfreq, "tmin": epochs.tmin,
        "ch_names": np.array(epochs.ch_names, dtype=str), "labels": epochs.labels,
    }
    _parse_epochs(arrays, str(path))
    write_fif_epochs(path, arrays, frames[epochs.n_classes], world)


def _lab_format(path: Path) -> str | None:
    """"fif" or "xdf" for the file names of `acquisition.lab_formats`, else None."""
    name = path.name.lower()
    return next((kind for end, kind in _LAB_FORMATS.items() if name.endswith(end)), None)


def _lab_epochs(path: Path, frame: str) -> LabelledEpochs:
    """Epochs of an MNE or XDF file, checked as those of an epochs ``.npz``."""
    read = read_fif_epochs if _lab_format(path) == "fif" else read_xdf_epochs
    return _epochs_from_arrays(read(path, frame), str(path), frame)


def _existing_file(path: PathLike) -> Path:
    """Return ``path`` as a Path if it is a non-empty regular file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if not path.is_file():
        raise ValueError(f"{path}: is not a regular file (a directory?)")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: file is empty (0 bytes)")
    return path


def _npz_destination(path: PathLike) -> Path:
    """Return ``path`` as a Path, refusing names numpy would silently extend with .npz."""
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise ValueError(f"{path}: the file name must end in .npz; got {path.suffix!r}")
    return path


def _load_mat(path: Path, frame: str) -> LabelledFeatures:
    """Read ``X`` and 1-based ``Y`` from a MATLAB file; labels come back 0-based."""
    where = str(path)
    try:
        contents = scipy.io.loadmat(path)
    except NotImplementedError as exc:  # scipy's answer to v7.3 (HDF5) files
        raise ValueError(
            f"{where}: MATLAB v7.3 (HDF5) files are not supported; re-save it with save(..., '-v7')"
        ) from exc
    except Exception as exc:  # damaged files raise OSError, IndexError, ValueError, ...
        raise ValueError(
            f"{where}: could not be read as a MATLAB .mat file (corrupt, truncated or not a "
            f"MAT-file): {exc}"
        ) from exc
    variables = {key: value for key, value in contents.items() if not key.startswith("__")}
    _check_keys(variables, _MAT_VARIABLES, where, "variable", "a .mat file")
    features = _check_data("X", variables["X"], 2, where)
    y = np.asarray(variables["Y"])
    if y.ndim > 2 or (y.ndim == 2 and 1 not in y.shape):
        raise ValueError(
            f"{where}: Y must be a vector of shape (n, 1), (1, n) or (n,); got shape {y.shape}"
        )
    labels = _check_label_array("Y", y.ravel(), "X", features.shape[0], where)
    return LabelledFeatures(
        features=features,
        labels=_check_classes(labels, frame, offset=1, name="Y", where=where),
        n_classes=N_CLASSES[frame],
        source=where,
    )


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """Read every array of an ``.npz`` archive, without unpickling anything."""
    where = str(path)
    with path.open("rb") as file:
        head = file.read(6)
    if head == b"\x93NUMPY":
        raise ValueError(f"{where}: is a single .npy array, not an .npz archive of named arrays")
    if not head.startswith(b"PK"):
        raise ValueError(
            f"{where}: is not an .npz archive (no zip signature; a renamed text or other file?)"
        )
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    except Exception as exc:  # BadZipFile, zlib.error, EOFError, object arrays, ...
        raise ValueError(
            f"{where}: could not be read as an .npz archive (corrupt or truncated?): {exc}"
        ) from exc


def _npz_format(arrays: Mapping[str, Any], where: str) -> str:
    """Return "features" or "epochs" after checking the archive holds exactly those keys."""
    has_features, has_epochs = "features" in arrays, "epochs" in arrays
    if has_features == has_epochs:
        which = "both 'features' and" if has_features else "neither 'features' nor"
        raise ValueError(
            f"{where}: holds {which} 'epochs', so its format is unclear; a "
            f"features file has keys {_listing(_FEATURE_KEYS)}, an epochs file "
            f"{_listing(_EPOCH_KEYS)}; found {_listing(sorted(arrays))}"
        )
    if has_features:
        _check_keys(arrays, _FEATURE_KEYS, where, "key", "a features .npz")
        return "features"
    _check_keys(arrays, _EPOCH_KEYS, where, "key", "an epochs .npz")
    return "epochs"


def _check_keys(
    found: Collection[str], expected: tuple[str, ...], where: str, what: str, kind: str
) -> None:
    """Raise unless ``found`` holds exactly the names in ``expected``."""
    missing = [key for key in expected if key not in found]
    unknown = sorted(key for key in found if key not in expected)
    problems = []
    if missing:
        problems.append(f"missing {what}(s) {_listing(missing)}")
    if unknown:
        problems.append(f"unknown {what}(s) {_listing(unknown)}")
    if problems:
        raise ValueError(
            f"{where}: {' and '.join(problems)}; {kind} holds exactly the {what}s "
            f"{_listing(expected)}; found {_listing(sorted(found)) or 'none'}"
        )


def _listing(names: Collection[str]) -> str:
    return ", ".join(repr(name) for name in names)


def _parse_features(arrays: Mapping[str, Any], where: str) -> tuple[np.ndarray, np.ndarray]:
    """Check features [n, d] and integer labels [n]; labels are not yet checked per frame."""
    features = _check_data("features", arrays["features"], 2, where)
    labels = _check_label_array("labels", arrays["labels"], "features", features.shape[0], where)
    return features, labels


def _epochs_from_arrays(arrays: Mapping[str, Any], where: str, frame: str) -> LabelledEpochs:
    epochs, sfreq, tmin, ch_names, labels = _parse_epochs(arrays, where)
    return LabelledEpochs(
        epochs=epochs,
        sfreq=sfreq,
        tmin=tmin,
        ch_names=ch_names,
        labels=_check_classes(labels, frame, offset=0, name="labels", where=where),
        n_classes=N_CLASSES[frame],
        source=where,
    )


def _parse_epochs(
    arrays: Mapping[str, Any], where: str
) -> tuple[np.ndarray, float, float, tuple[str, ...], np.ndarray]:
    """Check the five arrays of an epochs file; labels are not yet checked per frame."""
    epochs = _check_data("epochs", arrays["epochs"], 3, where)
    sfreq = _check_scalar("sfreq", arrays["sfreq"], where)
    if sfreq <= 0:
        raise ValueError(f"{where}: sfreq must be positive (Hz); got {sfreq}")
    tmin = _check_scalar("tmin", arrays["tmin"], where)
    ch_names = _check_channel_names(arrays["ch_names"], epochs.shape[1], where)
    labels = _check_label_array("labels", arrays["labels"], "epochs", epochs.shape[0], where)
    return epochs, sfreq, tmin, ch_names, labels


def _check_real(name: str, value: Any, where: str) -> np.ndarray:
    """Return ``value`` as an array, refusing anything but integers and floats."""
    array = np.asarray(value)
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{where}: {name} must hold real numbers; got dtype {array.dtype}")
    return array


def _check_data(name: str, value: Any, ndim: int, where: str) -> np.ndarray:
    """Return finite, non-empty float64 data of rank ``ndim``."""
    data = check_array(name, _check_real(name, value, where), ndim=ndim, where=where)
    if data.size == 0:
        raise ValueError(f"{where}: {name} is empty (shape {data.shape})")
    return data


def _check_scalar(name: str, value: Any, where: str) -> float:
    array = check_array(name, _check_real(name, value, where), where=where)
    if array.size != 1:
        raise ValueError(f"{where}: {name} must be a single number; got shape {array.shape}")
    return float(array.item())


def _check_channel_names(value: Any, n_channels: int, where: str) -> tuple[str, ...]:
    names = np.asarray(value)
    if names.dtype.kind != "U":
        raise ValueError(f"{where}: ch_names must hold strings; got dtype {names.dtype}")
    if names.ndim != 1:
        raise ValueError(f"{where}: ch_names must be one-dimensional; got shape {names.shape}")
    if names.size != n_channels:
        raise ValueError(
            f"{where}: ch_names has {names.size} names but epochs has {n_channels} channels"
        )
    if len(set(names.tolist())) != names.size or not all(names):
        raise ValueError(f"{where}: ch_names must be distinct and non-empty; got {names.tolist()}")
    return tuple(names.tolist())


def _check_label_array(
    name: str, value: Any, data_name: str, n_signals: int, where: str
) -> np.ndarray:
    """Return ``value`` as int64 labels [n_signals].

    Whole numbers only: an integer dtype, or floats with whole values (MATLAB saves doubles).
    """
    labels = check_array(name, _check_real(name, value, where), ndim=1, dtype=None, where=where)
    if labels.shape[0] != n_signals:
        raise ValueError(
            f"{where}: {data_name} has {n_signals} signals but {name} has {labels.shape[0]} labels"
        )
    fractional = np.flatnonzero(labels != np.round(labels))
    if fractional.size:
        first = fractional[0]
        raise ValueError(f"{where}: {name} must be integers; got {labels[first]} at index {first}")
    return labels.astype(np.int64)


def _check_classes(
    labels: np.ndarray, frame: str, *, offset: int, name: str, where: str
) -> np.ndarray:
    """Check the file's labels (numbered from ``offset``) suit ``frame``; return them 0-based."""
    n_classes = N_CLASSES[frame]
    allowed = np.arange(n_classes) + offset
    if frame == "feedback":
        meaning = f"{offset} = correct, {offset + 1} = error"
    else:
        meaning = f"{offset}..{offset + n_classes - 1}, one per move direction"
    values, counts = np.unique(labels, return_counts=True)
    if values.size == 1:
        raise ValueError(
            f"{where}: {name} has a single class (every label is {values[0]}); the {frame} "
            f"frame needs {n_classes} classes ({meaning})"
        )
    if values.size > n_classes:
        hint = ""
        if frame == "feedback" and values.size == N_CLASSES["guidance"]:
            hint = "; this looks like guidance data: pass frame='guidance'"
        raise ValueError(
            f"{where}: {name} has {values.size} classes {values.tolist()}; the {frame} frame "
            f"needs exactly {n_classes} ({meaning}){hint}"
        )
    unknown = np.setdiff1d(values, allowed)
    if unknown.size:
        raise ValueError(
            f"{where}: {name} has unknown label(s) {unknown.tolist()}; the {frame} frame "
            f"uses {meaning}"
        )
    if values.size < n_classes:
        hint = ""
        if frame == "guidance" and values.size == N_CLASSES["feedback"]:
            hint = "; this looks like feedback data: pass frame='feedback'"
        raise ValueError(
            f"{where}: {name} has only {values.size} of the {n_classes} classes the {frame} "
            f"frame needs ({meaning}): no signal has label(s) "
            f"{np.setdiff1d(allowed, values).tolist()}{hint}"
        )
    scarce = values[counts < MIN_SIGNALS_PER_CLASS]
    if scarce.size:
        raise ValueError(
            f"{where}: {name} has too few signals for label(s) {scarce.tolist()} "
            f"(counts {dict(zip(values.tolist(), counts.tolist(), strict=True))}); each class "
            f"needs at least {MIN_SIGNALS_PER_CLASS}"
        )
    return labels - offset
