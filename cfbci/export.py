"""``cfbci export FILE.mcap --format fif``: a recording's epochs as MNE ``Epochs``.

The exported epochs are those a recording gives as a dataset
(:func:`acquisition.loaders.load_recording_dataset`: every accepted epoch with a ``/truth``
of its step, in step order), with their truth labels as events (see
:func:`acquisition.loaders.save_epochs_fif`) named by the recorded world's classes
(:func:`acquisition.lab_formats.class_names`: ``correct``/``error``; guidance ``up``,
``down``, ``left``, ``right`` on a grid, the world's guidance actions elsewhere, e.g.
``pick-and-place/grasp``). Only raw epochs can be exported: a recording of feature vectors
is refused.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.console import Console

from acquisition.labelled import LabelledEpochs
from acquisition.loaders import load_recording_dataset, save_epochs_fif
from replay.recording import read_recording
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
        :func:`~acquisition.loaders.load_recording_dataset`), holds feature vectors, or
        ``out`` is not an MNE epochs file name.
    """
    data = load_recording_dataset(recording, frame=None)
    if not isinstance(data, LabelledEpochs):
        raise ValueError(
            f"{recording}: the session sent feature vectors, not raw epochs, so there are no "
            "epochs to export as MNE Epochs (record a session whose source sends raw epochs)"
        )
    save_epochs_fif(out, data, config_world(read_recording(recording).config))
    return data


def add_export_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci export``."""
    p = commands.add_parser(
        "export",
        help="write a recording's raw epochs and truth labels in another format (MNE .fif)",
        description="Export the raw epochs a session recording holds, labelled by its truth "
        "(events named correct/error, or by the world's guidance actions: up/down/left/right "
        "on a grid, e.g. pick-and-place/grasp elsewhere), as MNE Epochs "
        "(-epo.fif, EEG in volts). A recording of feature vectors cannot be exported.",
    )
    p.add_argument("file", type=Path, help="the recording (.mcap)")
    p.add_argument("--format", choices=FORMATS, default="fif", help="output format (fif)")
    p.add_argument("--out", type=Path, help="output file (default <stem>-epo.fif beside FILE)")
    p.set_defaults(run=_run_export)


def _run_export(args: argparse.Namespace, console: Console) -> int:
    out = args.out or args.file.with_name(f"{args.file.stem}-epo.fif")
    epochs = export_fif(args.file, out)
    console.print(
        f"exported {len(epochs.labels)} epochs ({len(epochs.ch_names)} channels, "
        f"{epochs.epochs.shape[2]} samples at {epochs.sfreq:g} Hz from {epochs.tmin:g} s) "
        f"to {out}"
    )
    return 0
