"""Tests of the synthetic ErrP EEG generator."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
from sklearn.model_selection import StratifiedKFold, cross_val_score

from acquisition.labelled import LabelledEpochs
from acquisition.synthetic import generate_errp_epochs
from decoding.features import ErrPFeatures


def features_of(data: LabelledEpochs) -> np.ndarray:
    """Default ErrP features (Fz, FCz, Cz; 57 at 256 Hz) of generated epochs."""
    return ErrPFeatures(data.sfreq, data.tmin, data.ch_names).fit_transform(data.epochs)


def lda_balanced_accuracy(data: LabelledEpochs) -> float:
    """The nominal accuracy's definition: shrinkage LDA, 10-fold stratified CV."""
    lda = LinearDiscriminantAnalysis(solver="lsqr", shrinkage=0.5, priors=[0.5, 0.5])
    scores = cross_val_score(
        lda, features_of(data), data.labels, cv=StratifiedKFold(10), scoring="balanced_accuracy"
    )
    return float(scores.mean())


def test_default_conventions() -> None:
    data = generate_errp_epochs(80, 20, accuracy=0.78, seed=0)
    assert data.epochs.shape == (100, 4, 308)
    assert data.epochs.dtype == np.float64
    assert np.all(np.isfinite(data.epochs))
    assert data.sfreq == 256.0
    assert data.tmin == -51 / 256  # -0.2 s rounded to a sample, so the onset is sample 51
    assert data.ch_names == ("Fz", "FCz", "Cz", "Pz")
    assert data.n_classes == 2
    assert data.labels.dtype.kind == "i"
    np.testing.assert_array_equal(np.bincount(data.labels), [80, 20])
    assert not np.all(np.diff(data.labels) >= 0)  # shuffled, not sorted by class
    assert "accuracy=0.780" in data.source
    assert "seed=0" in data.source


def test_custom_sampling_and_channels() -> None:
    data = generate_errp_epochs(
        5, 5, seed=1, sfreq=512.0, tmin=-0.1, tmax=0.9, ch_names=["FCz", "Cz", "C3"]
    )
    assert data.epochs.shape == (10, 3, 513)  # samples -51 .. 461 at 512 Hz
    assert data.tmin == -51 / 512
    assert data.sfreq == 512.0
    assert data.ch_names == ("FCz", "Cz", "C3")


def test_same_seed_same_data_and_different_seed_different_data() -> None:
    first = generate_errp_epochs(30, 10, seed=7)
    again = generate_errp_epochs(30, 10, seed=7)
    other = generate_errp_epochs(30, 10, seed=8)
    np.testing.assert_array_equal(first.epochs, again.epochs)
    np.testing.assert_array_equal(first.labels, again.labels)
    assert not np.allclose(first.epochs, other.epochs)
    sequence = generate_errp_epochs(30, 10, seed=np.random.SeedSequence(7))
    generator = generate_errp_epochs(30, 10, seed=np.random.default_rng(7))
    np.testing.assert_array_equal(sequence.epochs, generator.epochs)


def test_accuracy_changes_the_responses_not_the_draws() -> None:
    easy = generate_errp_epochs(30, 10, accuracy=0.95, seed=2)
    hard = generate_errp_epochs(30, 10, accuracy=0.6, seed=2)
    np.testing.assert_array_equal(easy.labels, hard.labels)
    assert not np.allclose(easy.epochs, hard.epochs)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"accuracy": 0.5}, ValueError, r"accuracy must be in \[0.55, 0.97\]"),
        ({"accuracy": 0.98}, ValueError, r"accuracy must be in \[0.55, 0.97\]"),
        ({"n_correct": -1}, ValueError, "n_correct must be >= 0"),
        ({"n_error": 2.5}, TypeError, "n_error must be an integer"),
        ({"n_correct": 0, "n_error": 0}, ValueError, "at least 1"),
        ({"ch_names": ("Fz", "EOG1")}, ValueError, "unknown channel 'EOG1'"),
        ({"ch_names": ("Fz", "Fz")}, ValueError, "duplicate"),
        ({"tmin": 0.5, "tmax": 0.5}, ValueError, "tmax"),
        ({"sfreq": 0.0}, ValueError, "sfreq must be in"),
    ],
)
def test_bad_arguments_are_rejected(kwargs: dict, error: type, message: str) -> None:
    arguments = {"n_correct": 8, "n_error": 2} | kwargs
    with pytest.raises(error, match=message):
        generate_errp_epochs(**arguments)


def test_background_looks_like_eeg() -> None:
    data = generate_errp_epochs(200, 0, seed=3)
    epochs = data.epochs
    rms = epochs.std(axis=(0, 2))
    assert np.all((rms > 5) & (rms < 50))  # tens of µV
    # Spatially correlated, more so between neighbours (Fz-FCz) than far apart (Fz-Pz).
    correlation = np.corrcoef(epochs.transpose(1, 0, 2).reshape(4, -1))
    assert correlation[0, 1] > 0.6
    assert correlation[0, 1] > correlation[0, 3] > 0.1
    # Spectrum (Hann window, 0.83 Hz resolution): 1/f decay and an alpha peak at Pz.
    spectrum = np.mean(np.abs(np.fft.rfft(epochs * np.hanning(308), axis=-1)) ** 2, axis=0)
    freqs = np.fft.rfftfreq(308, 1 / data.sfreq)

    def band(channel: int, low: float, high: float) -> float:
        return float(spectrum[channel, (freqs >= low) & (freqs <= high)].mean())

    assert band(0, 1.5, 3) > 3 * band(0, 15, 20) > 3 * band(0, 40, 60)
    alpha = band(3, 9, 11)
    assert alpha > 1.5 * band(3, 6, 7.5)
    assert alpha > 1.5 * band(3, 13, 15)


def test_nominal_accuracy_is_achieved_and_monotonic() -> None:
    achieved = []
    for nominal in (0.65, 0.78, 0.90):
        scores = [
            lda_balanced_accuracy(generate_errp_epochs(800, 200, accuracy=nominal, seed=seed))
            for seed in range(100, 108)
        ]
        achieved.append(np.mean(scores))
        assert abs(achieved[-1] - nominal) <= 0.03, (nominal, scores)
    assert achieved[0] < achieved[1] < achieved[2]


def test_error_epochs_carry_more_power() -> None:
    ratios = []
    for seed in (200, 201):
        data = generate_errp_epochs(800, 200, accuracy=0.78, seed=seed)
        power = np.sum(features_of(data) ** 2, axis=1)
        ratios.append(power[data.labels == 1].mean() / power[data.labels == 0].mean())
    assert 1.3 < np.mean(ratios) < 1.7


def test_classes_differ_in_the_errp_window_not_by_an_offset() -> None:
    data = generate_errp_epochs(1500, 1500, accuracy=0.9, seed=4)
    is_error = data.labels == 1
    features = ErrPFeatures(data.sfreq, data.tmin, data.ch_names).fit(data.epochs)
    values = features.transform(data.epochs)
    difference = values[is_error].mean(axis=0) - values[~is_error].mean(axis=0)
    peak = np.abs(difference).max()
    assert abs(difference.mean()) < 0.1 * peak
    peak_time = np.tile(features.times_, 3)[np.argmax(np.abs(difference))]
    assert 0.2 <= peak_time <= 0.6
    # Raw epochs: no class difference before the onset, nor on average over the epoch.
    raw = data.epochs[is_error].mean(axis=0) - data.epochs[~is_error].mean(axis=0)
    times = data.tmin + np.arange(raw.shape[-1]) / data.sfreq
    assert np.abs(raw[:, times < 0]).max() < 0.15 * peak
    assert abs(raw.mean()) < 0.1 * peak
