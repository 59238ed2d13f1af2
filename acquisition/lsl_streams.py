"""Lab Streaming Layer plumbing shared by the LSL bridge and the LSL simulator.

Three streams connect a stimulus program (or ``cfbci lsl-simulator``) and the bridge:

* the **EEG** stream: regularly sampled, numeric, one channel per electrode; its channel
  labels (``desc/channels/channel/label``) and nominal rate are the epochs' ``ch_names``
  and ``sfreq``; its units (``desc/channels/channel/unit``) microvolts, millivolts or
  volts, by name or as mne-lsl writes them, a power of ten of volts (``"0"``, ``"-6"``;
  `acquisition.lsl_epochs.microvolts_per_unit`), scaled to microvolts (none
  declared: microvolts);
* the **marker** stream of the stimulus program: one string channel, irregular; the
  marker ``"onset <step>"`` (or just ``"onset"``; the word is configurable) stamps the
  moment the subject saw the action of that step (mne-lsl's ``PlayerLSL`` annotations,
  string-encoded, are such a stream, one sample early: `marker_stream_shift`);
* the **move** stream of the bridge: one string channel, irregular; every move of the
  service as a JSON object (`move_marker`), which the stimulus program shows.

Discovery is liblsl's: multicast on the LAN by default. `loopback_config` gives an
``lsl_api.cfg`` that keeps it on 127.0.0.1 (machine scope, the loopback host as the only
known peer, IPv6 off, resolve waves of at most 0.5 s) under a session id of its own, for
tests and demos; a process reads it from the file named by the ``LSLAPICFG`` environment
variable, set before it starts.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pylsl

from acquisition.lsl_epochs import microvolts_per_unit, player_annotation_shift
from acquisition.lsl_epochs import parse_onset_marker as parse_onset_marker  # re-exported

#: Keys of a move marker: the service's move fields, and ``repeat``, how many times the
#: bridge has asked again for the epoch of that step (0 the first time).
MOVE_MARKER_KEYS = ("step", "action", "from_state", "to_state", "target_reached", "repeat")
def loopback_config(session_id: str) -> str:
    """The text of an ``lsl_api.cfg`` keeping LSL discovery on this machine's loopback.

    Parameters
    ----------
    session_id : str
        liblsl's ``SessionID``: only processes with the same one see each other's streams.
    """
    return (
        "[ports]\nIPv6 = disable\n"
        "[multicast]\nResolveScope = machine\nMachineAddresses = {127.0.0.1}\n"
        f"[lab]\nKnownPeers = {{127.0.0.1}}\nSessionID = {session_id}\n"
        # Loopback answers in microseconds: give up on a resolve wave after 0.5 s, not 5.
        "[tuning]\nUnicastMinRTT = 0.1\nUnicastMaxRTT = 0.5\nMulticastMinRTT = 0.1\n"
        "MulticastMaxRTT = 0.5\n"
        "[log]\nlevel = -2\n"
    )


def eeg_outlet(
    name: str, ch_names: Sequence[str], sfreq: float, source_id: str
) -> pylsl.StreamOutlet:
    """A float32 EEG outlet in microvolts with channel labels (``type`` "EEG")."""
    info = pylsl.StreamInfo(name, "EEG", len(ch_names), sfreq, pylsl.cf_float32, source_id)
    info.set_channel_labels(list(ch_names))
    info.set_channel_units("microvolts")
    info.set_channel_types("EEG")
    return pylsl.StreamOutlet(info)


def marker_outlet(name: str, source_id: str) -> pylsl.StreamOutlet:
    """A one-channel string outlet at irregular rate (``type`` "Markers")."""
    info = pylsl.StreamInfo(name, "Markers", 1, pylsl.IRREGULAR_RATE, pylsl.cf_string, source_id)
    return pylsl.StreamOutlet(info)


def resolve_inlet(
    name: str, timeout: float, *, keep_running: Callable[[], bool] = lambda: True
) -> pylsl.StreamInlet:
    """An open inlet of the stream called ``name`` (the first one found).

    The inlet does not recover a lost stream by itself (``recover=False``): reading a lost
    stream raises `LostError`, and the caller resolves it again, which also finds a
    restarted source with a new uid.

    Parameters
    ----------
    name : str
        The stream's name.
    timeout : float
        Seconds to keep looking.
    keep_running : callable
        Polled about every 0.5 s; False stops the search (a TimeoutError).

    Raises
    ------
    TimeoutError
        If no stream of that name is found within ``timeout`` seconds, or its inlet does
        not open.
    """
    deadline = time.monotonic() + timeout
    while keep_running() and (left := deadline - time.monotonic()) > 0:
        found = pylsl.resolve_byprop("name", name, minimum=1, timeout=min(left, 0.5))
        if found:
            inlet = pylsl.StreamInlet(found[0], max_buflen=60, recover=False)
            try:
                inlet.open_stream(max(deadline - time.monotonic(), 1.0))
            except pylsl.util.TimeoutError:
                break
            return inlet
    raise TimeoutError(f"no LSL stream named {name!r} found within {timeout:g} s")


@dataclass(frozen=True)
class StreamMeta:
    """What an EEG stream's metadata says about its samples.

    Attributes
    ----------
    sfreq : float
        Nominal sampling rate, Hz.
    ch_names : tuple of str
        Channel labels, in sample order.
    scale : float
        Microvolts per unit of the stream's values.
    """

    sfreq: float
    ch_names: tuple[str, ...]
    scale: float


def eeg_stream_meta(info: pylsl.StreamInfo) -> StreamMeta:
    """The sampling rate, channel names and scale of an EEG stream, checked.

    Raises
    ------
    ValueError
        Naming the stream: an irregular rate, a string format, missing or duplicate
        channel labels, or units other than one voltage unit for every channel.
    """
    where = f"LSL stream {info.name()!r}"
    if info.nominal_srate() <= 0:
        raise ValueError(f"{where} has an irregular rate; EEG needs a nominal sampling rate")
    if info.channel_format() == pylsl.cf_string:
        raise ValueError(f"{where} carries strings; EEG needs a numeric channel format")
    labels = info.get_channel_labels()
    if labels is None or any(not label for label in labels):
        raise ValueError(
            f"{where} does not name every channel in its metadata (desc/channels/channel/"
            f"label); got {labels}"
        )
    if len(set(labels)) != len(labels):
        raise ValueError(f"{where} has duplicate channel labels: {labels}")
    units = info.get_channel_units() or [None]
    scales = {microvolts_per_unit(unit) for unit in units}
    if None in scales or len(scales) > 1:
        raise ValueError(
            f"{where}: channel units {sorted({str(unit) for unit in units})}; expected the "
            "same voltage for every channel: microvolts, millivolts or volts, by name or as "
            "a power of ten of volts (mne-lsl's '0' for volts, '-6' for microvolts)"
        )
    return StreamMeta(
        float(info.nominal_srate()), tuple(str(label) for label in labels), scales.pop()
    )


def marker_stream_shift(info: pylsl.StreamInfo) -> int:
    """Samples of the EEG to add to a marker stream's timestamps, checked: 1 for mne-lsl's
    ``PlayerLSL`` annotations (`acquisition.lsl_epochs.player_annotation_shift`), 0
    otherwise.

    Raises
    ------
    ValueError
        Naming the stream, if its channel format is not string (a ``PlayerLSL`` plays its
        annotations as strings only with ``annotations_encoding="string"``).
    """
    if info.channel_format() != pylsl.cf_string:
        raise ValueError(
            f"LSL stream {info.name()!r} (type {info.type()!r}) does not carry strings; the "
            "markers must be text such as 'onset 3' (an mne-lsl PlayerLSL: "
            "annotations_encoding='string')"
        )
    return player_annotation_shift(
        info.type(), "string", info.get_channel_labels(), info.get_channel_types()
    )


#: Seconds a program keeps its outlets open after a session's end, for their consumers to
#: close their inlets first (a stream closed under an inlet makes liblsl print "Stream
#: transmission broke off" there, as for a real fault).
END_GRACE = 2.0


def let_consumers_leave(*outlets: pylsl.StreamOutlet, grace: float = END_GRACE) -> None:
    """Return when no outlet has a consumer left, or after ``grace`` seconds."""
    deadline = time.monotonic() + grace
    while any(o.have_consumers() for o in outlets) and time.monotonic() < deadline:
        time.sleep(0.01)


def move_marker(move: dict[str, Any], repeat: int) -> str:
    """The move stream's marker of a service ``move`` (its fields) and its repeat count."""
    return json.dumps({key: move[key] for key in MOVE_MARKER_KEYS[:-1]} | {"repeat": repeat})


def parse_move_marker(text: str) -> dict[str, Any]:
    """The fields of a move marker (`move_marker`).

    Raises
    ------
    ValueError
        If ``text`` is not a JSON object with exactly `MOVE_MARKER_KEYS`.
    """
    try:
        move = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"move marker {text[:80]!r} is not JSON: {exc}") from None
    if not isinstance(move, dict) or sorted(move) != sorted(MOVE_MARKER_KEYS):
        raise ValueError(f"move marker {text[:80]!r} must hold exactly {list(MOVE_MARKER_KEYS)}")
    return move


def as_float32(samples: np.ndarray, scale: float) -> np.ndarray:
    """EEG samples in microvolts, float32 (bit-exact for float32 microvolt streams)."""
    if scale == 1.0:
        return np.asarray(samples, dtype=np.float32)
    return (np.asarray(samples, dtype=np.float64) * scale).astype(np.float32)
