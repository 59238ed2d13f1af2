"""What ``cfbci lsl-simulator`` wrote into its EEG stream, saved and checked against a
recording (``cfbci lsl-check``): `save_written` and `check_recording`."""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from replay.recording import decode_array, read_recording

if TYPE_CHECKING:
    from acquisition.lsl_simulator import Simulation


def save_written(path: Path, simulation: Simulation) -> None:
    """The epochs written, to an ``.npz``: ``steps``, ``repeats``, ``onsets`` and ``starts``
    (sample indices), ``epochs`` float32 (n, n_channels, n_times) µV, ``dropped`` int
    (k, 3) rows ``(write index, first sample, count)``, ``t0`` the timestamp of sample 0 (s,
    so sample n is stamped ``t0 + n / sfreq``)."""
    written = simulation.written
    dropped = [(i, first, count) for i, w in enumerate(written) for first, count in w.dropped]
    np.savez(
        path,
        steps=np.array([w.step for w in written], dtype=np.int64),
        repeats=np.array([w.repeat for w in written], dtype=np.int64),
        onsets=np.array([w.onset for w in written], dtype=np.int64),
        starts=np.array([w.start for w in written], dtype=np.int64),
        epochs=np.stack([w.epoch for w in written]) if written else np.zeros((0, 0, 0)),
        dropped=np.array(dropped, dtype=np.int64).reshape(-1, 3),
        t0=np.float64(simulation.t0),
    )


@dataclass(frozen=True)
class Comparison:
    """A recording's epochs against the epochs the simulator wrote.

    Attributes
    ----------
    recorded : int
        Epochs in the recording.
    equal : int
        Of those, the ones equal sample for sample (float32) to the last epoch written
        for their step.
    mismatches : list of str
        What differs, per step.
    """

    recorded: int
    equal: int
    mismatches: list[str]


def check_recording(written_path: Path, recording_path: Path) -> Comparison:
    """Compare every ``/epoch`` of a recording with what the simulator wrote for its step.

    Raises
    ------
    ValueError
        If ``written_path`` is not the simulator's written epochs (``--written``: an
        ``.npz`` of ``steps`` and ``epochs``).
    """
    try:
        with np.load(written_path, allow_pickle=False) as arrays:
            last = {int(step): arrays["epochs"][i] for i, step in enumerate(arrays["steps"])}
    except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile) as error:
        raise ValueError(
            f"{written_path}: not the simulator's written epochs (the .npz of "
            f"`cfbci lsl-simulator --written`, with 'steps' and 'epochs'): {error}"
        ) from None
    recording = read_recording(recording_path)
    mismatches, equal = [], 0
    epochs = recording.accepted_epochs()
    for message in epochs:
        step, data = message["step"], decode_array(message)
        if step not in last:
            mismatches.append(f"step {step}: recorded, never written")
        elif data.shape != last[step].shape:
            mismatches.append(f"step {step}: shape {data.shape}, written {last[step].shape}")
        elif not np.array_equal(data, last[step]):
            differ = int((data != last[step]).sum())
            mismatches.append(f"step {step}: {differ} of {data.size} samples differ")
        else:
            equal += 1
    return Comparison(len(epochs), equal, mismatches)
