"""Containers for labelled data: feature vectors or raw epochs with their class labels.

Labels are integers 0..n_classes-1. For the feedback frame 0 = correct and 1 = error; for
the guidance frame class k is one of the four move directions (see
`acquisition.user` for the fixed, documented mapping the simulated user applies).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LabelledFeatures:
    """Feature vectors with labels.

    Attributes
    ----------
    features : ndarray, shape (n_signals, n_features), float64
        One feature vector per device action (microvolts for ErrP features).
    labels : ndarray, shape (n_signals,), int
        Class of each signal, 0..n_classes-1.
    n_classes : int
        Number of classes (2 for ErrP correct/error, 4 for guidance directions).
    source : str
        Where the data came from (a file path or a generator description).
    """

    features: np.ndarray
    labels: np.ndarray
    n_classes: int
    source: str


@dataclass(frozen=True)
class LabelledEpochs:
    """Raw EEG epochs with labels, in MNE conventions.

    Attributes
    ----------
    epochs : ndarray, shape (n_epochs, n_channels, n_times), float
        EEG in microvolts.
    sfreq : float
        Sampling frequency in Hz.
    tmin : float
        Time of the first sample relative to action onset, in seconds (e.g. -0.2).
    ch_names : tuple of str, length n_channels
        Channel names (10-20 system, e.g. "Fz", "FCz", "Cz").
    labels : ndarray, shape (n_epochs,), int
        Class of each epoch, 0..n_classes-1 (0 = correct, 1 = error for ErrPs).
    n_classes : int
        Number of classes.
    source : str
        Where the data came from.
    """

    epochs: np.ndarray
    sfreq: float
    tmin: float
    ch_names: tuple[str, ...]
    labels: np.ndarray
    n_classes: int
    source: str
