"""Epochs in the lab's own file formats: MNE epochs files (``-epo.fif``) and XDF recordings.

:mod:`acquisition.loaders` reads both through these functions and checks the result as it
checks an epochs ``.npz``. Both need optional packages: ``mne`` (``pip install
'cfbci[mne]'``) and ``pyxdf`` (``pip install 'cfbci[xdf]'``); without them the error says
which to install.

**Class names.** A label is named as in :data:`CLASS_NAMES`: feedback ``correct`` (0),
``error`` (1); guidance ``up``, ``down``, ``left``, ``right`` (0..3, the grid's moves). An
MNE event name or an XDF marker value carries a class when one of its ``/``-separated tags
(MNE's tag convention, case-insensitive) is a class name: ``error``, ``feedback/error``
and ``Error/visual`` all mean error. Guidance in another world names its classes by that
world's guidance actions, tagged with the world (:func:`class_names`): ``line/right``,
``line/left``, ``line/no-move``; ``pick-and-place/right``, ``pick-and-place/left``,
``pick-and-place/grasp``, ``pick-and-place/release`` (0..K-1, in action order). The world
tag is needed: ``right`` is class 3 on the grid but 0 in pick-and-place; a name tagged
with a world reads with that world's names (MNE's ``epochs["grasp"]`` still selects by the
action alone).

**MNE epochs** (:func:`read_fif_epochs`): the EEG channels not marked bad, volts turned
into microvolts, with the file's ``sfreq``, ``tmin`` and channel names. Labels come from the
event names (each must name one class), or, when every event name is a number (MNE's
names for an ``event_id`` it was not given), from the event codes in the ``.mat``
convention: feedback 1 = correct, 2 = error; guidance 1..4.

**XDF recordings** (:func:`read_xdf_epochs`): exactly one stream of type ``EEG`` (numeric,
regular rate, channel labels in its metadata, ``desc/channels/channel/label``; units from
``.../unit``: microvolts when absent, as XDF's EEG convention says, or millivolts or volts,
converted) and one of type ``Markers`` (strings). Each marker whose value names a class (see
above) is an action onset: the epoch is cut around it exactly as ``cfbci lsl-bridge`` cuts
a live stream (:meth:`acquisition.lsl_epochs.SampleBuffer.cut`, MNE's way): from the sample
nearest the marker's time, ``round(tmin * sfreq)`` to ``round(tmax * sfreq)`` samples
around it (both included; ``tmin``, ``tmax`` :data:`XDF_EPOCH_WINDOW`), so its ``tmin`` is
``round(tmin * sfreq) / sfreq``; samples as float32 (the wire format), then scaled to
microvolts. Other markers (trial starts, comments, the bridge's ``onset <step>``, which
carry no label) are ignored. A marker whose window is not entirely inside the EEG stream,
or spans a discontinuity in it, gives no epoch; how many were left out, and why the first
was, is said in a warning. Timestamps are pyxdf's: clocks synchronised and the EEG's jitter
removed.
"""

from __future__ import annotations

import functools
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.lsl_epochs import Epoch, SampleBuffer
from calibration_free.frames import Frame
from calibration_free.world import MOVES, GridWorld, World
from calibration_free.worlds import WORLDS, make_world

#: Class names per frame, in label order (a grid world's: guidance classes are its moves).
CLASS_NAMES: dict[str, tuple[str, ...]] = {"feedback": ("correct", "error"), "guidance": MOVES}
#: Worlds whose guidance classes are named with their world's tag (:func:`class_names`).
TAGGED_WORLDS: tuple[str, ...] = tuple(kind for kind in WORLDS if kind != "grid")

#: Epoch window around an XDF marker (tmin, tmax), seconds: that of the synthetic epochs.
XDF_EPOCH_WINDOW = (-0.2, 1.0)

#: Factor from each accepted XDF channel unit to microvolts.
_TO_MICROVOLTS = {
    "microvolts": 1.0, "microvolt": 1.0, "uv": 1.0, "µv": 1.0, "μv": 1.0,
    "millivolts": 1e3, "millivolt": 1e3, "mv": 1e3,
    "volts": 1e6, "volt": 1e6, "v": 1e6,
}
_VOLTS_TO_MICROVOLTS = 1e6

Arrays = dict[str, Any]


def class_names(frame: str, world: World | None = None) -> tuple[str, ...]:
    """The names of a frame's classes in ``world``, in label order (see the module
    docstring): :data:`CLASS_NAMES`, except guidance outside the grid, whose classes are the
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
    (:func:`class_names`; None: a grid).

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
        As :func:`read_fif_epochs`: ``epochs`` (n_epochs, n_channels, n_times) microvolts
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
    pyxdf = _optional("pyxdf", "xdf", where, "reading XDF recordings")
    try:
        streams, _ = pyxdf.load_xdf(str(path))
    except Exception as exc:  # pyxdf raises OSError, struct.error, ParseError, ...
        raise ValueError(f"{where}: could not be read as an XDF file: {exc}") from exc
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
    units = [str(channel.get("unit", ["microvolts"])[0]).strip().lower() for channel in channels]
    unknown = sorted(set(units) - set(_TO_MICROVOLTS))
    if unknown:
        raise ValueError(f"{where}: the EEG stream {_name(eeg)!r} has unknown unit(s) "
                         f"{unknown}; expected microvolts, millivolts or volts")
    return names, np.array([_TO_MICROVOLTS[unit] for unit in units])

