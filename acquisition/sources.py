"""Where a session's signals come from: a dataset file, or the synthetic generator.

Synthetic data are generated per session from the session's data stream, as raw epochs
converted to float32 (the wire format) and then to ErrP features, so every path sees
the same numbers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from acquisition.gaussian import generate_gaussian_features
from acquisition.labelled import LabelledEpochs, LabelledFeatures
from acquisition.loaders import (
    N_CLASSES,
    features_from_epochs,
    load_labelled,
    load_recording_dataset,
)
from acquisition.synthetic import generate_errp_epochs
from decoding.validation import check_range

#: Epochs of each class in a synthetic session's pools (the user draws without
#: replacement per class and reshuffles a pool when it runs out).
SYNTHETIC_EPOCHS_PER_CLASS = 600
DEFAULT_SYNTHETIC_ACCURACY = 0.78
#: The synthetic generators: ErrP EEG epochs (feedback only), or K-class Gaussian signals.
SYNTHETIC_KINDS = ("errp", "gaussian")

DataFactory = Callable[[np.random.Generator], LabelledFeatures]


@dataclass(frozen=True)
class DataSpec:
    """A dataset file, or synthetic data of a given nominal balanced accuracy.

    Attributes
    ----------
    path : Path or None
        A dataset file (see `acquisition.loaders.load_labelled`; a ``.mcap`` session
        recording answers with its epochs and their truth labels); None: synthetic.
    synthetic_accuracy : float
        Nominal balanced accuracy of the synthetic generator (ignored with a path).
    synthetic : {"errp", "gaussian"}
        The generator: ErrP EEG epochs (`acquisition.synthetic`, feedback frame), or
        Gaussian signals with as many classes as the frame needs
        (`acquisition.gaussian`).
    dims : int
        Dimensions of a Gaussian signal.
    mixing_decay : float
        The Gaussian signals' fixed linear mixing, gamma of
        `acquisition.gaussian.mixing_matrix` (0: none).
    """

    path: Path | None = None
    synthetic_accuracy: float = DEFAULT_SYNTHETIC_ACCURACY
    synthetic: str = "errp"
    dims: int = 2
    mixing_decay: float = 0.0

    def __post_init__(self) -> None:
        if self.mixing_decay and (self.path is not None or self.synthetic != "gaussian"):
            raise ValueError(
                "--mixing-decay mixes the Gaussian signals: it needs --synthetic gaussian "
                f"and no dataset; got mixing decay {self.mixing_decay:g} with "
                f"{self.path or self.synthetic + ' signals'}"
            )
        check_range("mixing decay", self.mixing_decay, 0.0, 10.0)

    def describe(self) -> str:
        if self.path is not None:
            return str(self.path)
        kind = "" if self.synthetic == "errp" else f" {self.dims}-D Gaussian"
        if self.synthetic == "gaussian" and self.mixing_decay:
            kind += f" mixed with decay {self.mixing_decay:g}"
        return f"synthetic{kind} (nominal balanced accuracy {self.synthetic_accuracy:g})"

    def resolve(self, frame: str) -> LabelledFeatures | DataFactory:
        """Loaded features, or a function generating a session's synthetic features."""
        if self.path is not None:
            return load_labelled(self.path, frame=frame)
        accuracy = self.synthetic_accuracy
        if self.synthetic == "gaussian":
            n_classes, dims, decay = N_CLASSES[frame], self.dims, self.mixing_decay
            return lambda rng: generate_gaussian_features(
                SYNTHETIC_EPOCHS_PER_CLASS, n_classes, dims, accuracy, rng, decay
            )
        if frame != "feedback":
            raise ValueError(
                "the synthetic generator makes ErrP (correct/error) data for the feedback "
                f"frame; the {frame} frame needs a 4-class dataset: pass --dataset PATH, or "
                "--synthetic gaussian"
            )
        return lambda rng: synthetic_features(accuracy, rng)

    def load_signals(self, frame: str) -> LabelledEpochs | LabelledFeatures:
        """The signals a live source sends from the dataset file: the raw epochs of a
        session recording that holds them (with its ``sfreq``, ``tmin`` and ``ch_names``),
        else the file's feature vectors (as `resolve`)."""
        if self.path is None:
            raise ValueError("load_signals needs a dataset file; synthetic data are generated")
        if self.path.suffix.lower() == ".mcap":
            return load_recording_dataset(self.path, frame=frame)
        return load_labelled(self.path, frame=frame)


def synthetic_epochs(accuracy: float, rng: np.random.Generator) -> LabelledEpochs:
    """A session's synthetic epochs, as float32 microvolts."""
    epochs = generate_errp_epochs(
        SYNTHETIC_EPOCHS_PER_CLASS, SYNTHETIC_EPOCHS_PER_CLASS, accuracy=accuracy, seed=rng
    )
    return replace(epochs, epochs=epochs.epochs.astype(np.float32))


def synthetic_features(accuracy: float, rng: np.random.Generator) -> LabelledFeatures:
    """ErrP features of `synthetic_epochs`."""
    return features_from_epochs(synthetic_epochs(accuracy, rng))
