"""Epochs in the lab's own file formats: MNE epochs files (``-epo.fif``) and XDF recordings.

`acquisition.loaders` reads both through these functions and checks the result as it
checks an epochs ``.npz``. Both need optional packages: ``mne`` (``pip install
'cfbci[mne]'``) and ``pyxdf`` (``pip install 'cfbci[xdf]'``); without them the error says
which to install.

**Class names.** A label is named as in `CLASS_NAMES`: feedback ``correct`` (0),
``error`` (1); guidance ``up``, ``down``, ``left``, ``right`` (0..3, the grid's moves). An
MNE event name or an XDF marker value carries a class when one of its ``/``-separated tags
(MNE's tag convention, case-insensitive) is a class name: ``error``, ``feedback/error``
and ``Error/visual`` all mean error. Guidance in another world names its classes by that
world's guidance actions, tagged with the world (`class_names`): ``line/right``,
``line/left``, ``line/no-move``; ``pick-and-place/right``, ``pick-and-place/left``,
``pick-and-place/grasp``, ``pick-and-place/release`` (0..K-1, in action order). The world
tag is needed: ``right`` is class 3 on the grid but 0 in pick-and-place; a name tagged
with a world reads with that world's names (MNE's ``epochs["grasp"]`` still selects by the
action alone).

**MNE epochs** (`read_fif_epochs`): the EEG channels not marked bad, volts turned
into microvolts, with the file's ``sfreq``, ``tmin`` and channel names. Labels come from the
event names (each must name one class), or, when every event name is a number (MNE's
names for an ``event_id`` it was not given), from the event codes in the ``.mat``
convention: feedback 1 = correct, 2 = error; guidance 1..4.

**XDF recordings** (`read_xdf_epochs`): exactly one stream of type ``EEG`` (numeric,
regular rate, channel labels in its metadata, ``desc/channels/channel/label``; units from
``.../unit``: microvolts when absent, as XDF's EEG convention says, or millivolts or volts,
by name or as a power of ten of volts as mne-lsl writes them, converted) and one of type
``Markers`` (strings). Each marker whose value names a class (see above) is an action
onset: the epoch is cut around it exactly as ``cfbci lsl-bridge`` cuts a live stream
(`acquisition.lsl_epochs.SampleBuffer.cut`, MNE's way): from the sample nearest
the marker's time, ``round(tmin * sfreq)`` to ``round(tmax * sfreq)`` samples
around it (both included; ``tmin``, ``tmax`` `XDF_EPOCH_WINDOW`), so its ``tmin`` is
``round(tmin * sfreq) / sfreq``; samples as float32 (the wire format), then scaled to
microvolts. Other markers (trial starts, comments, the bridge's ``onset <step>``, which
carry no label) are ignored. A marker whose window is not entirely inside the EEG stream,
or spans a discontinuity in it, gives no epoch; how many were left out, and why the first
was, is said in a warning. Timestamps are pyxdf's: clocks synchronised and the EEG's jitter
removed.

**A session recorded in XDF** (`read_xdf_session`): a LabRecorder file of an
``cfbci lsl-bridge`` session, read back with the streams named: every onset marker
``onset <step>`` of the marker stream (the bridge's rule, with its correction of mne-lsl's
``PlayerLSL`` annotations, one sample early) and its epoch, cut as the bridge cuts it (the
samples scaled to microvolts in float64, then float32: the bridge's own arithmetic), to
compare with the session's recording. `write_xdf` writes an XDF file (the
specification's FileHeader, StreamHeader, Samples, ClockOffset and StreamFooter chunks)
from streams recorded off LSL, as LabRecorder does.
"""

from __future__ import annotations

import functools
import struct
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.lsl_epochs import (
    Epoch,
    SampleBuffer,
    microvolts_per_unit,
    parse_onset_marker,
    player_annotation_shift,
)
from calibration_free.frames import Frame
from calibration_free.world import MOVES, GridWorld, World
from calibration_free.worlds import WORLDS, make_world

#: Class names per frame, in label order (a grid world's: guidance classes are its moves).
CLASS_NAMES: dict[str, tuple[str, ...]] = {"feedback": ("correct", "error"), "guidance": MOVES}
#: Worlds whose guidance classes are named with their world's tag (`class_names`).
TAGGED_WORLDS: tuple[str, ...] = tuple(kind for kind in WORLDS if kind != "grid")

#: Epoch window around an XDF marker (tmin, tmax), seconds: that of the synthetic epochs.
XDF_EPOCH_WINDOW = (-0.2, 1.0)

_VOLTS_TO_MICROVOLTS = 1e6

Arrays = dict[str, Any]


def class_names(frame: str, world: World | None = None) -> tuple[str, ...]:
    """The names of a frame's classes in ``world``, in label order (see the module
    docstring): `CLASS_NAMES`, except guidance outside the grid, whose classes are the
    world's guidance actions tagged with the world (``pick-and-place/grasp``).

    Parameters
    ----------
    frame : {"feedback", "guidance"}
    world : World, optional
        The session's world; None: a grid.
    """
    if frame != "guidance" or world is None or isinstance(world, GridWorld):
        return CLASS_NAMES[frame]
    return tuple(f"{world.name}/{action}" for action in Frame(world, frame).class_names())


@functools.cache
def _guidance_actions(kind: str) -> tuple[str, ...]:
    """The guidance action names of a world kind (built once: pick-and-place takes 30 ms)."""
    return Frame(make_world(kind), "guidance").class_names()


def class_of(name: str, frame: str) -> int | None:
    """The class an event name or marker value names (see the module docstring), or None.

    Parameters
    ----------
    name : str
        E.g. ``"error"``, ``"feedback/correct"``, ``"left"``, ``"pick-and-place/grasp"``.
    frame : {"feedback", "guidance"}

    Returns
    -------
    int or None
        The 0-based label, or None when no tag, or more than one class, is named (or
        more than one world is).
    """
    tags = {tag.strip().lower() for tag in name.split("/")}
    names = CLASS_NAMES[frame]
    if frame == "guidance":
        worlds = tags.intersection(TAGGED_WORLDS)
        if len(worlds) > 1:
            return None
        if worlds:
            names = _guidance_actions(worlds.pop())
    named = [k for k, class_name in enumerate(names) if class_name in tags]
    return named[0] if len(named) == 1 else None


def _optional(module: str, extra: str, where: str, what: str) -> Any:
    """Import an optional package, or say which extra to install."""
    import importlib

    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        raise ValueError(
            f"{where}: {what} needs the optional package {module!r}: "
            f"pip install 'cfbci[{extra}]'"
        ) from exc


def read_fif_epochs(path: Path, frame: str) -> Arrays:
    """Read an MNE epochs file into epochs ``.npz`` arrays (see the module docstring).

    Returns
    -------
    dict
        ``epochs`` float64 (n_epochs, n_eeg_channels, n_times) microvolts, ``sfreq`` Hz,
        ``tmin`` s, ``ch_names`` str (n_eeg_channels,), ``labels`` int (n_epochs,), 0-based
        (not yet checked against the frame).

    Raises
    ------
    ValueError
        If MNE is missing, the file is not an MNE epochs file, it has no EEG channel, or an
        event names no class; the message names the file.
    """
    where = str(path)
    mne = _optional("mne", "mne", where, "reading MNE .fif epochs")
    try:
        epochs = mne.read_epochs(path, preload=True, verbose="error")
    except Exception as exc:  # MNE raises ValueError, OSError, KeyError, ... on bad files
        raise ValueError(f"{where}: could not be read as MNE epochs (-epo.fif): {exc}") from exc
    try:
        eeg = epochs.pick("eeg")
    except ValueError as exc:
        raise ValueError(f"{where}: holds no EEG channel (not marked bad): {exc}") from exc
    names = {code: name for name, code in eeg.event_id.items()}
    codes = eeg.events[:, 2]
    unnamed = sorted({int(c) for c in codes} - set(names))
    if unnamed:
        raise ValueError(f"{where}: event code(s) {unnamed} have no name in event_id")
    if all(name.isdigit() for name in names.values()):
        labels = codes.astype(np.int64) - 1  # the .mat convention: 1-based codes
    else:
        labels = np.array([class_of(names[c], frame) for c in codes], dtype=object)
        unknown = sorted({names[c] for c, label in zip(codes, labels, strict=True)
                          if label is None})
        if unknown:
            raise ValueError(
                f"{where}: event name(s) {unknown} name no {frame} class; name each event "
                f"with one of {list(CLASS_NAMES[frame])} (or a /-tag of it, e.g. "
                f"'feedback/{CLASS_NAMES[frame][-1]}'; another world's guidance: its action "
                f"tagged with the world, e.g. 'pick-and-place/grasp')"
            )
    return {
        "epochs": eeg.get_data() * _VOLTS_TO_MICROVOLTS,
        "sfreq": float(eeg.info["sfreq"]),
        "tmin": float(eeg.tmin),
        "ch_names": np.array(eeg.ch_names, dtype=str),
        "labels": labels.astype(np.int64),
    }


def write_fif_epochs(
    path: Path, arrays: Arrays, frame: str, world: World | None = None
) -> None:
    """Write epochs ``.npz`` arrays as an MNE epochs file (float64, EEG channels).

    ``epochs`` microvolts become volts; events are ``[i, 0, label + 1]`` for epoch ``i``
    (the epochs' order; no continuous recording lies behind them) with ``event_id``
    ``{class name: label + 1}`` for the classes present, named as in ``world``
    (`class_names`; None: a grid).

    Raises
    ------
    ValueError
        If a label is not one of the frame's classes in ``world``.
    """
    where = str(path)
    mne = _optional("mne", "mne", where, "writing MNE .fif epochs")
    labels = np.asarray(arrays["labels"], dtype=np.int64)
    names = class_names(frame, world)
    outside = sorted({int(k) for k in labels} - set(range(len(names))))
    if outside:
        raise ValueError(
            f"{where}: label(s) {outside} are no {frame} class of this world ({len(names)} "
            f"classes: {list(names)})"
        )
    info = mne.create_info(list(arrays["ch_names"]), float(arrays["sfreq"]), ch_types="eeg")
    events = np.column_stack([np.arange(len(labels)), np.zeros_like(labels), labels + 1])
    event_id = {name: k + 1 for k, name in enumerate(names) if k in set(labels.tolist())}
    epochs = mne.EpochsArray(
        np.asarray(arrays["epochs"], dtype=np.float64) / _VOLTS_TO_MICROVOLTS, info,
        events=events, tmin=float(arrays["tmin"]), event_id=event_id, baseline=None,
        verbose="error",
    )
    epochs.save(path, fmt="double", overwrite=True, verbose="error")


def read_xdf_epochs(
    path: Path, frame: str, window: tuple[float, float] = XDF_EPOCH_WINDOW
) -> Arrays:
    """Cut labelled epochs out of an XDF recording (see the module docstring).

    Parameters
    ----------
    path : Path
        An ``.xdf`` (or gzip-compressed ``.xdfz``) file.
    frame : {"feedback", "guidance"}
        Which marker values name a class.
    window : (float, float)
        ``tmin``, ``tmax`` of the epochs around each marker, in s.

    Returns
    -------
    dict
        As `read_fif_epochs`: ``epochs`` (n_epochs, n_channels, n_times) microvolts
        with ``n_times = round(tmax * sfreq) - round(tmin * sfreq) + 1``, ``sfreq`` (the
        EEG stream's nominal rate), ``tmin``, ``ch_names``, ``labels``.

    Raises
    ------
    ValueError
        If pyxdf is missing, the file is not XDF, there is not exactly one EEG and one
        marker stream, the EEG stream lacks a regular rate, channel labels or a known
        unit, or no marker gives an epoch; the message names the file.
    """
    where = str(path)
    streams = _load_xdf(path)
    eeg = _only_stream(streams, "EEG", where)
    markers = _only_stream(streams, "Markers", where)
    sfreq = float(eeg["info"]["nominal_srate"][0])
    if sfreq <= 0 or eeg["info"]["channel_format"][0] == "string":
        raise ValueError(
            f"{where}: the EEG stream {_name(eeg)!r} must be numeric with a regular rate; it "
            f"has nominal_srate {sfreq:g} and format {eeg['info']['channel_format'][0]!r}"
        )
    if markers["info"]["channel_format"][0] != "string":
        raise ValueError(
            f"{where}: the marker stream {_name(markers)!r} must hold strings (the class "
            f"names); it has format {markers['info']['channel_format'][0]!r}"
        )
    ch_names, scale = _channels(eeg, where)
    stamps = np.asarray(eeg["time_stamps"], dtype=np.float64)
    buffer = SampleBuffer(len(ch_names), sfreq, seconds=len(stamps) / sfreq + 1.0)
    buffer.append(np.asarray(eeg["time_series"], dtype=np.float32), stamps, arrival_ns=0)
    onsets = [(t, class_of(str(value[0]), frame))
              for t, value in zip(markers["time_stamps"], markers["time_series"], strict=True)]
    onsets = [(t, label) for t, label in onsets if label is not None]
    if not onsets:
        values = sorted({str(v[0]) for v in markers["time_series"]})[:10]
        raise ValueError(
            f"{where}: no marker of {_name(markers)!r} names a {frame} class "
            f"{list(CLASS_NAMES[frame])}; its values include {values}"
        )
    first, last = round(window[0] * sfreq), round(window[1] * sfreq)
    epochs, labels, refused = [], [], []
    for time, label in onsets:
        cut = buffer.cut(float(time), first, last)
        if isinstance(cut, Epoch):
            epochs.append(cut.data.astype(np.float64) * scale[:, None])
            labels.append(label)
        else:  # a Refusal, or None: the window runs past the last sample
            refused.append(f"marker at t={time:.4f} s: " + (
                "the window runs past the end of the EEG" if cut is None else cut.reason))
    if refused:
        warnings.warn(
            f"{where}: {len(refused)} of {len(onsets)} markers gave no epoch (window "
            f"{window[0]:g} to {window[1]:g} s); first: {refused[0]}",
            stacklevel=4,  # the caller of load_epochs or load_labelled
        )
    if not epochs:
        raise ValueError(f"{where}: no marker's epoch window lies inside the EEG stream")
    return {
        "epochs": np.stack(epochs),
        "sfreq": sfreq,
        "tmin": first / sfreq,
        "ch_names": np.array(ch_names, dtype=str),
        "labels": np.array(labels, dtype=np.int64),
    }


def _name(stream: dict[str, Any]) -> str:
    return str(stream["info"]["name"][0])


def _only_stream(streams: list[dict[str, Any]], kind: str, where: str) -> dict[str, Any]:
    """The one stream whose type is ``kind`` (case-insensitive)."""
    found = [s for s in streams if str(s["info"]["type"][0]).lower() == kind.lower()]
    if len(found) != 1:
        listing = [f"{_name(s)} ({s['info']['type'][0]})" for s in streams]
        raise ValueError(
            f"{where}: needs exactly one stream of type {kind!r}; found {len(found)} among "
            f"{listing or 'no streams'}"
        )
    return found[0]


def _channels(eeg: dict[str, Any], where: str) -> tuple[list[str], np.ndarray]:
    """Channel labels and the factor of each channel to microvolts."""
    n_channels = int(eeg["info"]["channel_count"][0])
    try:
        channels = eeg["info"]["desc"][0]["channels"][0]["channel"]
        names = [str(channel["label"][0]) for channel in channels]
    except (KeyError, IndexError, TypeError) as exc:
        raise ValueError(
            f"{where}: the EEG stream {_name(eeg)!r} has no channel labels in its metadata "
            "(desc/channels/channel/label)"
        ) from exc
    if len(names) != n_channels:
        raise ValueError(f"{where}: the EEG stream {_name(eeg)!r} has {n_channels} channels "
                         f"but {len(names)} channel labels")
    units = [channel.get("unit", [None])[0] for channel in channels]
    scales = [microvolts_per_unit(unit) for unit in units]
    unknown = sorted({str(unit) for unit, scale in zip(units, scales, strict=True)
                      if scale is None})
    if unknown:
        raise ValueError(f"{where}: the EEG stream {_name(eeg)!r} has unknown unit(s) "
                         f"{unknown}; expected microvolts, millivolts or volts (by name, or "
                         "as a power of ten of volts: '0', '-3', '-6')")
    return names, np.array(scales, dtype=np.float64)



def _load_xdf(path: Path) -> list[dict[str, Any]]:
    """pyxdf's streams of an XDF file (clocks synchronised, jitter removed)."""
    where = str(path)
    pyxdf = _optional("pyxdf", "xdf", where, "reading XDF recordings")
    try:
        streams, _ = pyxdf.load_xdf(str(path))
    except Exception as exc:  # pyxdf raises OSError, struct.error, ParseError, ...
        raise ValueError(f"{where}: could not be read as an XDF file: {exc}") from exc
    return streams


def _named_stream(streams: list[dict[str, Any]], name: str, where: str) -> dict[str, Any]:
    """The one stream called ``name``."""
    found = [s for s in streams if _name(s) == name]
    if len(found) != 1:
        raise ValueError(f"{where}: needs exactly one stream named {name!r}; found "
                         f"{len(found)} among {[_name(s) for s in streams]}")
    return found[0]


def _channel_field(stream: dict[str, Any], key: str) -> list[str] | None:
    """Every channel's ``key`` (``label``, ``type``) from a stream's header, or None."""
    try:
        channels = stream["info"]["desc"][0]["channels"][0]["channel"]
        return [str(channel[key][0]) for channel in channels]
    except (KeyError, IndexError, TypeError):
        return None


def read_xdf_session(
    path: Path, eeg: str, markers: str, window: tuple[float, float] = XDF_EPOCH_WINDOW,
    onset_marker: str = "onset", marker_shift: int | None = None,
) -> Arrays:
    """Read an ``cfbci lsl-bridge`` session back from an XDF recording (see the module
    docstring).

    Parameters
    ----------
    path : Path
        An ``.xdf`` file holding the two streams (others are ignored).
    eeg, markers : str
        Names of the EEG stream and of the stimulus program's marker stream.
    window : (float, float)
        ``tmin``, ``tmax`` of the epochs around each onset, s.
    onset_marker : str
        The onset marker's word (``"<word> <step>"``).
    marker_shift : int or None
        EEG sample periods added to every marker timestamp; None: from the marker stream's
        header, as the bridge decides (1 for mne-lsl's ``PlayerLSL`` annotations, else 0).

    Returns
    -------
    dict
        ``steps`` int (n,), the step each onset marker names (-1: none); ``onsets`` float64
        (n,), the timestamp of each onset's nearest EEG sample, s (NaN where no epoch);
        ``epochs`` float32 (n_cut, n_channels, n_times) microvolts of the onsets whose
        window is whole, in order, and ``cut`` int (n_cut,) their positions in ``steps``;
        ``sfreq``, ``tmin``, ``ch_names`` as `read_xdf_epochs`; ``marker_shift``
        int, the shift applied.

    Raises
    ------
    ValueError
        If pyxdf is missing, the file is not XDF, a named stream is missing or not
        unique, the EEG stream lacks a regular rate, channel labels or a known unit, or
        the marker stream does not hold strings; the message names the file.
    """
    where = str(path)
    streams = _load_xdf(path)
    signal, marks = _named_stream(streams, eeg, where), _named_stream(streams, markers, where)
    sfreq = float(signal["info"]["nominal_srate"][0])
    if sfreq <= 0 or signal["info"]["channel_format"][0] == "string":
        raise ValueError(f"{where}: the EEG stream {eeg!r} must be numeric with a regular "
                         "rate")
    marker_format = str(marks["info"]["channel_format"][0])
    if marker_format != "string":
        raise ValueError(f"{where}: the marker stream {markers!r} must hold strings; it has "
                         f"format {marker_format!r}")
    if marker_shift is None:
        marker_shift = player_annotation_shift(
            str(marks["info"]["type"][0]), marker_format, _channel_field(marks, "label"),
            _channel_field(marks, "type"),
        )
    ch_names, scale = _channels(signal, where)
    stamps = np.asarray(signal["time_stamps"], dtype=np.float64)
    buffer = SampleBuffer(len(ch_names), sfreq, seconds=len(stamps) / sfreq + 1.0)
    microvolts = np.asarray(signal["time_series"], dtype=np.float64) * scale
    buffer.append(microvolts.astype(np.float32), stamps, arrival_ns=0)
    first, last = round(window[0] * sfreq), round(window[1] * sfreq)
    steps, onsets, epochs, cut = [], [], [], []
    for stamp, value in zip(marks["time_stamps"], marks["time_series"], strict=True):
        is_onset, step = parse_onset_marker(str(value[0]), onset_marker)
        if not is_onset:
            continue
        epoch = buffer.cut(float(stamp) + marker_shift / sfreq, first, last)
        steps.append(-1 if step is None else step)
        onsets.append(epoch.onset_time if isinstance(epoch, Epoch) else np.nan)
        if isinstance(epoch, Epoch):
            epochs.append(epoch.data)
            cut.append(len(steps) - 1)
    n_times = last - first + 1
    return {
        "steps": np.array(steps, dtype=np.int64),
        "onsets": np.array(onsets, dtype=np.float64),
        "epochs": (np.stack(epochs) if epochs
                   else np.zeros((0, len(ch_names), n_times), dtype=np.float32)),
        "cut": np.array(cut, dtype=np.int64),
        "sfreq": sfreq, "tmin": first / sfreq, "ch_names": np.array(ch_names, dtype=str),
        "marker_shift": marker_shift,
    }


#: XDF's little-endian sample formats, by the header's ``channel_format``.
_XDF_FORMATS = {"float32": "<f4", "double64": "<f8", "int8": "<i1", "int16": "<i2",
                "int32": "<i4", "int64": "<i8"}


@dataclass
class XdfStream:
    """One stream as recorded off LSL, for `write_xdf`.

    Attributes
    ----------
    header : str
        The stream's info as LSL gives it (an XML ``<info>`` document: name, type,
        channel_count, nominal_srate, channel_format, desc, ...).
    channel_format : str
        ``"string"`` or a numeric format of `_XDF_FORMATS` (the header's).
    times : ndarray, shape (n_samples,)
        Timestamps as received (the stream's clock), s.
    values : ndarray, shape (n_samples, n_channels), or list of list of str
    clock_offsets : list of (float, float)
        ``(collection time, offset)`` pairs, s: the recorder's clock minus the stream's
        (``time_correction()``) measured at that time of the recorder's clock.
    """

    header: str
    channel_format: str
    times: np.ndarray
    values: Any
    clock_offsets: list[tuple[float, float]] = field(default_factory=list)


def _varlen(n: int) -> bytes:
    """XDF's variable-length integer: the width (1, 4 or 8 bytes), then the value."""
    if n < 1 << 8:
        return b"\x01" + struct.pack("<B", n)
    if n < 1 << 32:
        return b"\x04" + struct.pack("<I", n)
    return b"\x08" + struct.pack("<Q", n)


def _chunk(tag: int, content: bytes) -> bytes:
    """A chunk: [NumLengthBytes][Length][Tag (uint16)][Content]."""
    body = struct.pack("<H", tag) + content
    return _varlen(len(body)) + body


def _samples_chunk(stream_id: int, stream: XdfStream) -> bytes:
    """A Samples chunk (tag 3): every sample with its timestamp."""
    out = bytearray(struct.pack("<I", stream_id) + _varlen(len(stream.times)))
    if stream.channel_format == "string":
        for time, value in zip(stream.times, stream.values, strict=True):
            out += b"\x08" + struct.pack("<d", time)
            for text in value:
                encoded = str(text).encode()
                out += _varlen(len(encoded)) + encoded
        return bytes(out)
    values = np.asarray(stream.values, dtype=_XDF_FORMATS[stream.channel_format])
    for time, row in zip(stream.times, values, strict=True):
        out += b"\x08" + struct.pack("<d", time) + row.tobytes()
    return bytes(out)


def write_xdf(path: Path, streams: Sequence[XdfStream]) -> Path:
    """Write streams recorded off LSL as an XDF file, as LabRecorder lays it out.

    The file holds the magic ``XDF:``, a FileHeader chunk (version 1.0), a StreamHeader
    per stream (ids from 1, in order), one Samples chunk per stream with every sample and
    its timestamp, the stream's ClockOffset chunks, and a StreamFooter per stream
    (first and last timestamp, sample count).

    Raises
    ------
    ValueError
        If a stream's channel format is not XDF's.
    """
    data = bytearray(b"XDF:")
    data += _chunk(1, b'<?xml version="1.0"?><info><version>1.0</version></info>')
    for sid, stream in enumerate(streams, start=1):
        if stream.channel_format != "string" and stream.channel_format not in _XDF_FORMATS:
            raise ValueError(f"{path}: stream {sid} has channel format "
                             f"{stream.channel_format!r}, not one of XDF's")
        data += _chunk(2, struct.pack("<I", sid) + stream.header.encode())
    for sid, stream in enumerate(streams, start=1):
        data += _chunk(3, _samples_chunk(sid, stream))
        for collected, offset in stream.clock_offsets:
            data += _chunk(4, struct.pack("<Idd", sid, collected, offset))
    for sid, stream in enumerate(streams, start=1):
        times = np.asarray(stream.times, dtype=np.float64)
        bounds = (f"<first_timestamp>{float(times[0])!r}</first_timestamp>"
                  f"<last_timestamp>{float(times[-1])!r}</last_timestamp>") if len(times) else ""
        footer = (f'<?xml version="1.0"?><info>{bounds}<sample_count>{len(times)}'
                  "</sample_count></info>")
        data += _chunk(6, struct.pack("<I", sid) + footer.encode())
    path.write_bytes(bytes(data))
    return path
