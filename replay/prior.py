"""Earlier sessions' recordings as a prior (`calibration_free.prior`).

A recording (docs/protocol.md, "Recordings") holds what the learner saw and did: the
session's config, every accepted epoch (``/epoch``, and the learner's input on
``/features``), every move (``/move``: state, action, whether it declared a target) and
every state (``/state``: the best task the move was chosen under). From them
`read_prior_session` takes the learner's signals (as the re-run computes them,
`replay.rerun.recorded_signals`) and the labels the learner adopted at its declared
targets (`calibration_free.prior.adopted_labels`: every declared target's segment
under the task it declared, the segment before the first target and the open last one
unlabelled). It never reads ``/truth``: a lab has no truth of its users' targets.

The feature space of a recording (`recording_space`): the size of its feature
vectors, its frame and classes, and, for a session of raw epochs, their sampling frequency,
first sample time and channels and the feature extractor's settings
(`decoding.features.ErrPFeatures`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from calibration_free.frames import Frame
from calibration_free.prior import (
    DEFAULT_RECENCY,
    FeatureSpace,
    Prior,
    PriorSession,
    adopted_labels,
)
from decoding.features import ErrPFeatures
from replay.recording import read_recording
from replay.signals import recorded_signals
from session.config import config_world
from session.plane import is_plane


class NoLabelledSignals(ValueError):
    """A recording that gives a prior nothing: it declared fewer than two targets."""


#: The extractor's parameters that describe the epochs rather than the features.
_EPOCH_PARAMETERS = ("sfreq", "tmin", "ch_names")


def epochs_space(
    n_features: int,
    frame: str,
    n_classes: int,
    sfreq: float,
    tmin: float,
    ch_names: Sequence[str],
) -> FeatureSpace:
    """The feature space of features extracted from raw epochs of ``sfreq`` Hz starting
    at ``tmin`` s on channels ``ch_names`` by today's
    `decoding.features.ErrPFeatures` (its settings recorded in the space)."""
    extractor = ErrPFeatures(sfreq, tmin, list(ch_names)).get_params()
    settings = tuple(
        (name, tuple(value) if isinstance(value, list | tuple) else value)
        for name, value in sorted(extractor.items())
        if name not in _EPOCH_PARAMETERS
    )
    return FeatureSpace(
        n_features, frame, n_classes, float(sfreq), float(tmin), tuple(ch_names), settings
    )


def recording_space(config: dict[str, Any], n_features: int, n_classes: int) -> FeatureSpace:
    """The feature space of a recorded session's config whose features have
    ``n_features`` values and whose frame ``n_classes`` classes."""
    if config.get("signal") == "epochs":
        return epochs_space(
            n_features, config["frame"], n_classes,
            config["sfreq"], config["tmin"], config["ch_names"],
        )
    return FeatureSpace(n_features, config["frame"], n_classes)


def read_prior_session(path: str | os.PathLike[str]) -> tuple[PriorSession, FeatureSpace, int]:
    """One recording's labelled signals, their feature space and when it started.

    Returns
    -------
    session : PriorSession
    space : FeatureSpace
    started_ns : int
        The log time of the recording's config (wall clock, ns): its recency.

    Raises
    ------
    FileNotFoundError, ValueError
        On a file that cannot be read as a recording, a recording of a world in the plane,
        or one without labelled signals; the message names the file.
    """
    recording = read_recording(path)
    config = recording.config
    if not config:
        raise ValueError(f"{path}: the recording holds no session configuration")
    if is_plane(config):
        raise ValueError(
            f"{path}: a prior is read from sessions of the grid, line or pick-and-place "
            f"worlds; this one is of the {config['world']} world"
        )
    world = config_world(config)
    frame = Frame(world, config["frame"])
    signals = np.array(recorded_signals(recording), dtype=np.float32)
    # A state accompanies every move: the one chosen after n signals is move n + 1's.
    best_task = {
        message["n_signals"]: message["best_task"] for _, message in recording.messages["/state"]
    }
    moves, declared = [], {}
    for _, move in recording.messages["/move"][: len(signals)]:
        index = move["step"] - 1
        moves.append((move["from_state"], world.action_names.index(move["action"])))
        if move["target_reached"]:
            declared[index] = best_task[index]
    indices, labels = adopted_labels(frame, moves, declared)
    if len(indices) == 0:
        raise NoLabelledSignals(
            f"{path}: no labelled signal: a prior takes the segments between a session's "
            f"first and last declared targets, and this one declared {len(declared)}"
        )
    space = recording_space(config, signals.shape[1], frame.n_classes)
    session = PriorSession(signals[indices], labels, str(path))
    return session, space, recording.messages["/config"][0][0]


def read_prior(
    paths: Sequence[str | os.PathLike[str]],
    recency: float = DEFAULT_RECENCY,
    weight: float = 1.0,
) -> Prior:
    """A prior of one or more recordings of a user, the most recent (by the recordings'
    start) weighing most (`calibration_free.prior.Prior`).

    Raises
    ------
    FileNotFoundError, ValueError
        As `read_prior_session`, and on recordings of different feature spaces
        (naming the files and what differs).
    """
    if not paths:
        raise ValueError("a prior needs at least one recording")
    read = [read_prior_session(path) for path in paths]
    first = read[0]
    for session, space, _ in read[1:]:
        differences = first[1].differences(space)
        if differences:
            raise ValueError(
                f"prior recordings {first[0].source} and {session.source} are of different "
                f"feature spaces: {'; '.join(differences)}"
            )
    recent_first = sorted(read, key=lambda item: -item[2])
    return Prior(tuple(session for session, _, _ in recent_first), first[1], recency, weight)
