"""``cfbci export FILE.mcap --format fif``: a recording's epochs as MNE ``Epochs``.

The exported epochs are those a recording gives as a dataset
(`acquisition.loaders.load_recording_dataset`: every accepted epoch with a ``/truth``
of its step, in step order), with their truth labels as events (see
`acquisition.loaders.save_epochs_fif`) named by the recorded world's classes
(`acquisition.lab_formats.class_names`: ``correct``/``error``; guidance ``up``,
``down``, ``left``, ``right`` on a grid, the world's guidance actions elsewhere, e.g.
``pick-and-place/grasp``). Only raw epochs can be exported: a recording of feature vectors
is refused.

A truncated recording gives the epochs it holds; a damaged one those of its intact chunks
(read as `replay.recording.recover` reads it: the file is salvaged into a temporary
clean copy, the input only read), and the command says where the file is cut or damaged
(exit 3 when damaged records were dropped; see ``docs/recordings.md``).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from acquisition.labelled import LabelledEpochs
from acquisition.loaders import load_recording_dataset, save_epochs_fif
from replay.recording import Recording, read_recording, recover
from session.config import config_world

#: ``--format`` choices.
FORMATS = ("fif",)


def export_fif(recording: Path, out: Path) -> LabelledEpochs:
    """Write the raw epochs of ``recording`` and their truth labels to ``out`` (-epo.fif);
    return the epochs written.

    Raises
    ------
    FileNotFoundError
        If ``recording`` does not exist.
    ValueError
        If it is not a recording usable as a dataset (see
        `load_recording_dataset`), holds feature vectors, or
        ``out`` is not an MNE epochs file name.
    """
    read = read_recording(recording, salvage=True)
    if Path(out).resolve() == Path(recording).resolve():
        raise ValueError(f"{out} is the input recording; give another output path")
    if read.data_damage() or read.dropped:  # the intact chunks, through a clean copy
        with tempfile.TemporaryDirectory(prefix="cfbci-export-") as tmp:
            clean = Path(tmp) / Path(recording).name
            recover(recording, clean)
            try:
                data = load_recording_dataset(clean, frame=None)
            except ValueError as error:
                raise ValueError(str(error).replace(str(clean), str(recording))) from None
    else:
        data = load_recording_dataset(recording, frame=None)
    if not isinstance(data, LabelledEpochs):
        raise ValueError(
            f"{recording}: the session sent feature vectors, not raw epochs, so there are no "
            "epochs to export as MNE Epochs (record a session whose source sends raw epochs)"
        )
    save_epochs_fif(out, data, config_world(read.config))
    return data


def damage_lines(recording: Recording) -> list[str]:
    """What a reading of ``recording`` said about where it is cut or damaged (empty when
    it is complete)."""
    lines = []
    if recording.truncated:
        lines.append(f"input truncated: {recording.warning}")
    if recording.damage:
        lost = sum(d.messages for d in recording.damage)
        lines.append(f"input damaged: {len(recording.damage)} region"
                     f"{'s' * (len(recording.damage) != 1)} not read ({lost} message"
                     f"{'s' * (lost != 1)} apparently lost); exported from every intact chunk")
        lines += [f"damaged: {d.describe()}" for d in recording.damage[:10]]
    return lines


