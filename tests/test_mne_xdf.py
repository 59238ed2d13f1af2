"""MNE epochs files (``-epo.fif``) and XDF recordings as datasets.

The ``.fif`` files are written by MNE itself; the XDF files by `write_xdf` below, from
the XDF specification (pyxdf only reads), and read by pyxdf.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import mne
import numpy as np
import pytest

from acquisition.lab_formats import (
    XDF_EPOCH_WINDOW,
    class_names,
    class_of,
    read_fif_epochs,
    write_fif_epochs,
)
from acquisition.loaders import features_from_epochs, load_epochs, load_labelled
from acquisition.synthetic import generate_errp_epochs
from calibration_free.world import GridWorld
from calibration_free.worlds import make_world
from cfbci.cli import main

SFREQ = 256.0
EEG_CHANNELS = ("Fz", "FCz", "Cz", "Pz")


# --- writing XDF (specification: chunks of [NumLengthBytes][Length][Tag][Content]) --------


def _varlen(n: int) -> bytes:
    """XDF's variable-length integer: a byte giving the width (1, 4 or 8), then the value."""
    if n < 1 << 8:
        return b"\x01" + struct.pack("<B", n)
    if n < 1 << 32:
        return b"\x04" + struct.pack("<I", n)
    return b"\x08" + struct.pack("<Q", n)


def _chunk(tag: int, content: bytes) -> bytes:
    body = struct.pack("<H", tag) + content
    return _varlen(len(body)) + body


def _header_xml(stream: dict[str, Any]) -> bytes:
    channels = "".join(
        f"<channel><label>{escape(label)}</label><unit>{escape(stream['unit'])}</unit>"
        f"<type>{escape(stream['type'])}</type></channel>"
        for label in stream.get("labels", ())
    )
    fmt = "string" if stream["format"] == "string" else "float32"
    return (
        f'<?xml version="1.0"?><info><name>{escape(stream["name"])}</name>'
        f"<type>{escape(stream['type'])}</type>"
        f"<channel_count>{stream['channels']}</channel_count>"
        f"<nominal_srate>{stream['srate']}</nominal_srate><channel_format>{fmt}</channel_format>"
        f"<source_id>{escape(stream['name'])}</source_id><created_at>0</created_at>"
        f"<desc><channels>{channels}</channels></desc></info>"
    ).encode()


def _samples(stream: dict[str, Any]) -> bytes:
    """A Samples chunk's content after the stream id: every sample with its time stamp."""
    out = bytearray(_varlen(len(stream["times"])))
    for time, value in zip(stream["times"], stream["values"], strict=True):
        out += b"\x08" + struct.pack("<d", time)
        if stream["format"] == "string":
            encoded = value.encode()
            out += _varlen(len(encoded)) + encoded
        else:
            out += np.asarray(value, dtype="<f4").tobytes()
    return bytes(out)


def write_xdf(path: Path, streams: list[dict[str, Any]]) -> Path:
    """Write streams (dicts: name, type, channels, srate, format "float32"/"string", times,
    values, and for EEG labels and unit) as an XDF file: file header, stream headers, one
    samples chunk per stream, a clock offset (0) per stream, stream footers."""
    data = bytearray(b"XDF:")
    data += _chunk(1, b'<?xml version="1.0"?><info><version>1.0</version></info>')
    for sid, stream in enumerate(streams, start=1):
        data += _chunk(2, struct.pack("<I", sid) + _header_xml(stream))
    for sid, stream in enumerate(streams, start=1):
        data += _chunk(3, struct.pack("<I", sid) + _samples(stream))
        data += _chunk(4, struct.pack("<Idd", sid, stream["times"][0], 0.0))
    for sid, stream in enumerate(streams, start=1):
        footer = (
            f'<?xml version="1.0"?><info><first_timestamp>{stream["times"][0]!r}'
            f"</first_timestamp><last_timestamp>{stream['times'][-1]!r}</last_timestamp>"
            f"<sample_count>{len(stream['times'])}</sample_count></info>"
        )
        data += _chunk(6, struct.pack("<I", sid) + footer.encode())
    path.write_bytes(bytes(data))
    return path


def eeg_stream(signal: np.ndarray, times: np.ndarray, unit: str = "microvolts",
               name: str = "amp", kind: str = "EEG") -> dict[str, Any]:
    return {"name": name, "type": kind, "channels": signal.shape[1], "srate": SFREQ,
            "format": "float32", "times": times, "values": signal, "labels": EEG_CHANNELS,
            "unit": unit}


def marker_stream(times: list[float], values: list[str]) -> dict[str, Any]:
    return {"name": "stimulus", "type": "Markers", "channels": 1, "srate": 0,
            "format": "string", "times": times, "values": values}


@pytest.fixture
def recording() -> dict[str, Any]:
    """60 s of 4-channel EEG (float32 µV) at 256 Hz from t = 1000 s, with a 2 s gap at
    30 s, and markers: 40 labelled onsets, comments, one onset whose window crosses the gap
    and one whose window runs past the end."""
    rng = np.random.default_rng(0)
    n = int(60 * SFREQ)
    times = 1000.0 + np.arange(n) / SFREQ
    times[int(30 * SFREQ):] += 2.0  # samples lost: nothing between 1030 and 1032 s
    signal = rng.normal(scale=10.0, size=(n, len(EEG_CHANNELS))).astype(np.float32)
    onsets = 1000.0 + np.array([1.0 + 0.7 * k for k in range(40)])  # 1 s .. 28.3 s
    onsets += rng.uniform(-0.4, 0.4, size=40) / SFREQ  # between samples
    labels = rng.permutation([0] * 25 + [1] * 15)
    names = ["feedback/correct" if label == 0 else "Error" for label in labels]
    marker_times = [*onsets, 1000.5, 1029.5, times[-1] - 0.5]
    marker_values = [*names, "trial start", "correct", "error"]  # the last two: no epoch
    return {"times": times, "signal": signal, "onsets": onsets, "labels": labels,
            "markers": (marker_times, marker_values)}


def _nearest(times: np.ndarray, t: float) -> int:
    return int(np.argmin(np.abs(times - t)))


def test_an_xdf_recording_gives_epochs_cut_around_its_markers(
    recording: dict[str, Any], tmp_path: Path
) -> None:
    path = write_xdf(tmp_path / "session.xdf", [
        marker_stream(*recording["markers"]),
        eeg_stream(recording["signal"], recording["times"]),
    ])
    refused = (r"session\.xdf: 2 of 42 markers gave no epoch .*; first: marker at "
               r"t=1029\.5000 s: the window .* spans the gap")
    with pytest.warns(UserWarning, match=refused):
        data = load_epochs(path)
    first, last = round(XDF_EPOCH_WINDOW[0] * SFREQ), round(XDF_EPOCH_WINDOW[1] * SFREQ)
    assert data.epochs.shape == (40, 4, last - first + 1) == (40, 4, 308)
    assert (data.sfreq, data.tmin, data.ch_names) == (SFREQ, first / SFREQ, EEG_CHANNELS)
    assert data.labels.tolist() == recording["labels"].tolist()
    for epoch, onset in zip(data.epochs, recording["onsets"], strict=True):
        at = _nearest(recording["times"], onset)
        expected = recording["signal"][at + first:at + last + 1].T
        assert np.array_equal(epoch, expected)  # sample for sample, exactly
    with pytest.warns(UserWarning, match="2 of 42"):
        features = load_labelled(path)  # as `cfbci simulate --dataset` reads it
    assert np.array_equal(features.features, features_from_epochs(data).features)


def test_xdf_units_are_converted_to_microvolts(recording: dict[str, Any], tmp_path: Path) -> None:
    volts = (recording["signal"].astype(np.float64) * 1e-6).astype(np.float32)
    path = write_xdf(tmp_path / "volts.xdf", [
        eeg_stream(volts, recording["times"], unit="V"), marker_stream(*recording["markers"]),
    ])
    with pytest.warns(UserWarning):
        data = load_epochs(path)
    at = _nearest(recording["times"], recording["onsets"][0])
    expected = volts[at - 51:at + 257].T.astype(np.float64) * 1e6
    np.testing.assert_allclose(data.epochs[0], expected, rtol=1e-12)


def test_bad_xdf_files_are_clear_errors(recording: dict[str, Any], tmp_path: Path) -> None:
    eeg = eeg_stream(recording["signal"], recording["times"])
    markers = marker_stream(*recording["markers"])
    cases = {
        "two-eeg": ([eeg, eeg_stream(recording["signal"], recording["times"], name="b"),
                     markers], r"exactly one stream of type 'EEG'; found 2"),
        "no-markers": ([eeg], r"exactly one stream of type 'Markers'; found 0"),
        "unlabelled": ([eeg, marker_stream([1001.0, 1002.0], ["start", "stop"])],
                       r"no marker of 'stimulus' names a feedback class .* \['start', 'stop'\]"),
        "unit": ([{**eeg, "unit": "furlongs"}, markers], r"unknown unit\(s\) \['furlongs'\]"),
    }
    for name, (streams, message) in cases.items():
        path = write_xdf(tmp_path / f"{name}.xdf", streams)
        with pytest.raises(ValueError, match=rf"{name}\.xdf: .*{message}"):
            load_epochs(path)
    text = tmp_path / "text.xdf"
    text.write_text("not XDF at all")
    with pytest.raises(ValueError, match=r"text\.xdf: could not be read as an XDF file"):
        load_labelled(text)


def mne_epochs(event_id: dict[str, int], *, seed: int = 0) -> tuple[mne.EpochsArray, Any]:
    """Synthetic ErrP epochs (volts) with an extra EOG channel, as MNE ``EpochsArray``."""
    source = generate_errp_epochs(30, 20, accuracy=0.8, seed=seed)
    n = len(source.labels)
    eog = np.random.default_rng(seed).normal(scale=50e-6, size=(n, 1, source.epochs.shape[2]))
    info = mne.create_info([*source.ch_names, "EOG"], source.sfreq, [*["eeg"] * 4, "eog"])
    codes = np.array(list(event_id.values()))[source.labels]
    events = np.column_stack([np.arange(n) * 400, np.zeros(n, int), codes])
    epochs = mne.EpochsArray(np.concatenate([source.epochs * 1e-6, eog], axis=1), info,
                             events=events, tmin=source.tmin, event_id=event_id,
                             baseline=None, verbose="error")
    return epochs, source


@pytest.mark.parametrize(
    "event_id",
    [{"feedback/correct": 10, "feedback/error": 20}, {"1": 1, "2": 2}],
    ids=["named", "numbered"],
)
def test_mne_epochs_load_as_a_dataset(
    event_id: dict[str, int], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    epochs, source = mne_epochs(event_id)
    path = tmp_path / "subject-epo.fif"
    epochs.save(path, fmt="double", verbose="error")
    data = load_epochs(path)
    assert data.ch_names == source.ch_names  # the EOG channel is left out
    assert (data.sfreq, data.tmin) == (source.sfreq, source.tmin)
    assert data.labels.tolist() == source.labels.tolist()
    np.testing.assert_allclose(data.epochs, source.epochs, rtol=1e-12, atol=1e-9)  # µV
    assert np.allclose(load_labelled(path).features, features_from_epochs(source).features)

    report = tmp_path / "report.json"
    assert main(["simulate", "--dataset", str(path), "--seeds", "1", "--steps", "20",
                 "--grid", "3", "--jobs", "1", "--json", str(report)]) == 0
    assert json.loads(report.read_text())["config"]["dataset"] == str(path)


def test_mne_epochs_with_events_that_name_no_class_are_refused(tmp_path: Path) -> None:
    epochs, _ = mne_epochs({"stimulus": 1, "error": 2})
    path = tmp_path / "odd-epo.fif"
    epochs.save(path, verbose="error")
    with pytest.raises(ValueError, match=r"odd-epo\.fif: event name\(s\) \['stimulus'\] name "
                                         r"no feedback class"):
        load_labelled(path)
    junk = tmp_path / "junk-epo.fif"
    junk.write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match=r"junk-epo\.fif: could not be read as MNE epochs"):
        load_epochs(junk)


def test_class_names_follow_mne_tags() -> None:
    assert class_of("error", "feedback") == 1
    assert class_of("Feedback/Correct", "feedback") == 0
    assert class_of("correct/error", "feedback") is None
    assert class_of("left", "guidance") == 2
    assert class_of("errors", "feedback") is None


def test_guidance_classes_outside_the_grid_carry_their_worlds_tag(tmp_path: Path) -> None:
    line, pick = make_world("line"), make_world("pick-and-place")
    assert class_names("guidance", GridWorld(3)) == class_names("guidance") == (
        "up", "down", "left", "right")
    assert class_names("guidance", line) == ("line/right", "line/left", "line/no-move")
    assert class_names("feedback", pick) == ("correct", "error")
    assert class_of("right", "guidance") == 3  # the grid's
    assert class_of("pick-and-place/right", "guidance") == 0
    assert class_of("Pick-and-Place/Release", "guidance") == 3
    assert class_of("line/no-move", "guidance") == 2
    assert class_of("line/grasp", "guidance") is None  # no such class in the line world
    assert class_of("line/pick-and-place/right", "guidance") is None  # two worlds

    # A line-world guidance file (3 classes) written and read back with its names.
    labels = np.array([0, 1, 2, 2, 0, 1])
    arrays = {"epochs": np.ones((6, 1, 8)), "sfreq": 64.0, "tmin": 0.0,
              "ch_names": np.array(["Cz"]), "labels": labels}
    path = tmp_path / "line-epo.fif"
    write_fif_epochs(path, arrays, "guidance", line)
    assert mne.read_epochs(path, verbose="error").event_id == {
        "line/right": 1, "line/left": 2, "line/no-move": 3}
    assert read_fif_epochs(path, "guidance")["labels"].tolist() == labels.tolist()
    with pytest.raises(ValueError, match=r"label\(s\) \[3\] are no guidance class of this world"):
        write_fif_epochs(path, {**arrays, "labels": np.array([0, 3])}, "guidance", line)
