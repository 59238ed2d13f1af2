"""A session as a continuous raw ``.fif``, played on LSL by mne-lsl's ``PlayerLSL``.

An amplifier stream the project did not write: `session_raw` lays the epochs a
simulated user answers with (`user_epochs`, for a seed and the moves the service
will make) out in time as an `mne.io.RawArray` in volts, between stretches of
continuous background (`acquisition.lsl_simulator.Background`), each epoch's onset
an annotation ``onset <step>``. `play_and_record` (``python -m
acquisition.fif_stream``) is then the lab: mne-lsl's ``PlayerLSL`` plays the file as an
amplifier (stream ``<name>``, float64 volts, units as mne-lsl writes them) and its
annotations as the stimulus program's markers (stream ``<name>-annotations``, strings),
and a recorder in the manner of LabRecorder takes the EEG, the annotations and the
bridge's moves off LSL into an XDF file (`acquisition.lab_formats.write_xdf`).

The file is played as recorded, whatever the moves: each onset must come after the move
of its step, so the first onset comes ``lead_in`` s after the start, and onsets follow
each other ``gap`` s apart, more than the epoch's ``tmax`` plus the loop's latency (the
epoch cut, the service's answer, the move forwarded). Needs mne and mne-lsl
(``pip install mne-lsl``); mne-lsl bundles its own liblsl, which reads the same
``LSLAPICFG`` as pylsl's.
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.lab_formats import XdfStream, write_xdf
from acquisition.labelled import LabelledEpochs
from acquisition.sources import DataSpec
from acquisition.user import SimulatedUser
from calibration_free.streams import session_streams
from calibration_free.world import ACTIONS, GridWorld

log = logging.getLogger("cfbci.fif_stream")

#: Samples the player pushes per chunk (31 ms at 256 Hz).
CHUNK = 8
#: Seconds of background after the last epoch.
TAIL = 1.0


def user_epochs(
    seed: int, moves: Sequence[tuple[int, str, bool]], frame: str = "feedback", grid: int = 5
) -> tuple[LabelledEpochs, list[int]]:
    """The synthetic epochs of a session seed and the ones its user answers the moves with.

    The data and user streams are the session's (`session_streams`), as in
    ``cfbci lsl-simulator``: with the moves the service makes for that seed, these are the
    epochs of ``cfbci session --seed``.

    Parameters
    ----------
    seed : int
    moves : sequence of (int, str, bool)
        Every move: the state it leaves, its action's name, whether it declares a target.
    frame : {"feedback", "guidance"}
    grid : int
        Grid side.

    Returns
    -------
    LabelledEpochs, list of int
        The epochs (float32 µV) and the index of the one answering each move.
    """
    from acquisition.lsl_simulator import raw_epochs  # pylsl's liblsl: see _background

    data_rng, user_rng, _ = session_streams(seed)
    signals = raw_epochs(DataSpec(), frame, data_rng)
    user = SimulatedUser(GridWorld(grid), frame, signals.labels, user_rng)
    answers = []
    for state, action, target_reached in moves:
        answers.append(user.answer(state, ACTIONS.index(action))[0])
        if target_reached:
            user.new_target()
    return signals, answers


def session_raw(
    epochs: np.ndarray, ch_names: Sequence[str], sfreq: float, tmin: float,
    lead_in: float, gap: float, seed: int = 0,
) -> Any:
    """The epochs laid out in a continuous recording, onsets annotated ``onset <step>``.

    Parameters
    ----------
    epochs : ndarray, shape (n_steps, n_channels, n_times), µV
        Step k's epoch (k from 1) starts ``round(tmin * sfreq)`` samples from its onset.
    ch_names : sequence of str
    sfreq : float
        Hz.
    tmin : float
        The epochs' start relative to their onset, s (<= 0).
    lead_in, gap : float
        The first onset's time, s, and the time from one onset to the next, s; an
        epoch's window must not reach into the next one's.
    seed : int
        Seed of the background between the epochs.

    Returns
    -------
    mne.io.RawArray
        EEG channels in volts (float64: a float32 µV value survives ``/ 1e6`` then
        ``* 1e6``), ``n_times`` the last window's end plus `TAIL`, one annotation of
        duration 0 per onset.

    Raises
    ------
    ValueError
        If the first window starts before the recording or the windows overlap.
    """
    import mne

    n_steps, n_channels, n_times = epochs.shape
    first = round(tmin * sfreq)
    start, spacing = round(lead_in * sfreq), round(gap * sfreq)
    if start + first < 0 or spacing < n_times:
        raise ValueError(
            f"the epochs ({n_times} samples from {first} around the onset) must start after "
            f"the lead-in's beginning ({lead_in:g} s) and be at most {gap:g} s apart"
        )
    onsets = start + spacing * np.arange(n_steps)
    length = int(onsets[-1]) + first + n_times + round(TAIL * sfreq)
    microvolts = _background(n_channels, sfreq, seed, length)
    for onset, epoch in zip(onsets, epochs, strict=True):
        microvolts[:, onset + first:onset + first + n_times] = epoch
    info = mne.create_info(list(ch_names), sfreq, ch_types="eeg")
    raw = mne.io.RawArray(microvolts / 1e6, info, verbose="error")
    raw.set_annotations(mne.Annotations(
        onsets / sfreq, np.zeros(n_steps), [f"onset {k}" for k in range(1, n_steps + 1)]
    ))
    return raw


def _background(n_channels: int, sfreq: float, seed: int, n: int) -> np.ndarray:
    """``n`` samples of `acquisition.lsl_simulator.Background`, shape (n_channels,
    n), float64 µV.

    Imported here: `acquisition.lsl_simulator` loads pylsl's liblsl, which the
    player's process (mne-lsl's own liblsl) does not load.
    """
    from acquisition.lsl_simulator import Background

    background = Background(n_channels, sfreq, np.random.default_rng(seed))
    return background.next(n).T.astype(np.float64)


def play_and_record(
    fif: Path, name: str, moves: str, xdf: Path, timeout: float = 60.0
) -> Path:
    """Play ``fif`` on LSL with ``PlayerLSL`` (once) and record the session into ``xdf``.

    The player's streams are ``name`` (EEG) and ``name-annotations`` (markers, strings);
    the recorder takes them and the bridge's move stream ``moves`` (the stimulus program
    subscribes to it) from the moment it finds them until the file has been played.

    Raises
    ------
    TimeoutError
        If a stream is not found within ``timeout`` s.
    """
    from mne_lsl.lsl import StreamInlet, local_clock, resolve_streams
    from mne_lsl.player import PlayerLSL

    player = PlayerLSL(fif, chunk_size=CHUNK, n_repeat=1, name=name,
                       source_id=f"{name}-player", annotations=True,
                       annotations_encoding="string")
    player.start()
    recorded = []
    for stream in (name, f"{name}-annotations", moves):
        found = resolve_streams(timeout=timeout, name=stream)
        if not found:
            raise TimeoutError(f"no LSL stream named {stream!r} found within {timeout:g} s")
        inlet = StreamInlet(found[0])
        inlet.open_stream(timeout=timeout)
        header = inlet.get_sinfo().as_xml
        fmt = ET.fromstring(header).findtext("channel_format") or "string"
        offset = (local_clock(), inlet.time_correction(timeout=timeout))
        recorded.append((inlet, XdfStream(header, fmt, np.zeros(0), [], [offset])))
    log.info("recording %s", [inlet.name for inlet, _ in recorded])
    chunks: list[list[tuple[Any, np.ndarray]]] = [[] for _ in recorded]
    while player.running or any(inlet.samples_available for inlet, _ in recorded):
        for k, (inlet, _) in enumerate(recorded):
            values, times = inlet.pull_chunk(timeout=0.05 if k == 0 else 0.0)
            if len(times):  # copies: mne-lsl's arrays view the inlet's reused buffers
                chunks[k].append((np.array(values) if isinstance(values, np.ndarray)
                                  else values, np.array(times)))
    for (inlet, stream), pulled in zip(recorded, chunks, strict=True):
        stream.clock_offsets.append((local_clock(), inlet.time_correction(timeout=timeout)))
        stream.times = np.concatenate([times for _, times in pulled] or [np.zeros(0)])
        if stream.channel_format == "string":
            stream.values = [row for values, _ in pulled for row in values]
        else:
            stream.values = np.concatenate([values for values, _ in pulled])
    return write_xdf(xdf, [stream for _, stream in recorded])

