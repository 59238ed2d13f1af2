"""Tests of the ErrP feature extractor (method.md section 8)."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
from sklearn.exceptions import NotFittedError
from sklearn.model_selection import cross_val_score
from sklearn.pipeline import Pipeline

from acquisition.synthetic import generate_errp_epochs
from decoding.features import ErrPFeatures

SFREQ = 256.0
TMIN = -51 / SFREQ  # the onset falls on sample 51
N_TIMES = 308  # -0.2 s to 1.0 s
CH_NAMES = ("Fz", "FCz", "Cz", "Pz")


def random_epochs(n_epochs: int = 6, n_channels: int = 4, seed: int = 0) -> np.ndarray:
    """White noise epochs in µV, shape (n_epochs, n_channels, N_TIMES)."""
    return 10 * np.random.default_rng(seed).standard_normal((n_epochs, n_channels, N_TIMES))


def test_published_feature_set_has_57_features() -> None:
    features = ErrPFeatures(SFREQ, TMIN, CH_NAMES).fit(random_epochs())
    out = features.transform(random_epochs(seed=1))
    assert out.shape == (6, 57)
    assert out.dtype == np.float64
    assert features.selected_channels_ == ("Fz", "FCz", "Cz")
    assert features.n_features_out_ == 57
    # 19 samples every 1/32 s, the first at or after 0.2 s, all inside [0.2, 0.8] s.
    assert len(features.times_) == 19
    np.testing.assert_allclose(np.diff(features.times_), 1 / 32)
    assert 0.2 <= features.times_[0] < 0.2 + 1 / SFREQ
    assert features.times_[-1] + 1 / 32 <= 0.8
    np.testing.assert_array_equal(np.diff(features.sample_indices_), 8)


def test_feature_names_are_channel_major() -> None:
    features = ErrPFeatures(SFREQ, TMIN, CH_NAMES).fit(random_epochs())
    names = features.get_feature_names_out()
    assert names.shape == (57,)
    assert [name.split("_")[0] for name in names[::19]] == ["Fz", "FCz", "Cz"]
    assert names[0] == "Fz_203.1ms"


def test_channel_subset_follows_wanted_order() -> None:
    epochs = random_epochs()
    full = ErrPFeatures(SFREQ, TMIN, CH_NAMES).fit_transform(epochs)
    # Only FCz and Cz present, stored in reverse order with an extra channel.
    reordered = epochs[:, [3, 2, 1], :]
    subset = ErrPFeatures(SFREQ, TMIN, ["Pz", "Cz", "FCz"])
    out = subset.fit_transform(reordered)
    assert out.shape == (6, 38)
    assert subset.selected_channels_ == ("FCz", "Cz")
    np.testing.assert_array_equal(subset.picks_, [2, 1])
    np.testing.assert_allclose(out, full[:, 19:], rtol=1e-12, atol=1e-12)


def test_custom_channel_list() -> None:
    out = ErrPFeatures(SFREQ, TMIN, CH_NAMES, channels=("Pz", "Fz")).fit_transform(random_epochs())
    assert out.shape == (6, 38)


def test_no_wanted_channel_is_a_clear_error() -> None:
    features = ErrPFeatures(SFREQ, TMIN, ["O1", "O2"])
    with pytest.raises(ValueError, match=r"none of the wanted channels.*Fz.*available.*O1"):
        features.fit(random_epochs(n_channels=2))


@pytest.mark.parametrize(
    ("epochs", "message"),
    [
        (np.zeros((4, N_TIMES)), "must have 3 dimensions"),
        (np.zeros((2, 3, N_TIMES)), "size 3 on axis 1; expected 4"),
        (np.zeros((2, 4, 200)), "too short"),
    ],
)
def test_bad_epochs_are_rejected(epochs: np.ndarray, message: str) -> None:
    features = ErrPFeatures(SFREQ, TMIN, CH_NAMES).fit(random_epochs())
    with pytest.raises(ValueError, match=message):
        features.transform(epochs)
    with pytest.raises(ValueError, match=message):
        clone(features).fit(epochs)


def test_nan_is_rejected() -> None:
    epochs = random_epochs()
    epochs[1, 2, 100] = np.nan
    features = ErrPFeatures(SFREQ, TMIN, CH_NAMES).fit(random_epochs())
    with pytest.raises(ValueError, match=r"NaN or infinite values \(first at index \(1, 2, 100\)"):
        features.transform(epochs)


def test_window_before_epoch_start_is_rejected() -> None:
    with pytest.raises(ValueError, match="before the first sample"):
        ErrPFeatures(SFREQ, 0.3, CH_NAMES).fit(random_epochs())


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"sfreq": 250.0}, "integer multiple of decimate_to"),
        ({"decimate_to": 0.0}, "decimate_to must be in"),
        ({"l_freq": 12.0}, "h_freq must be in"),
        ({"h_freq": 200.0}, "h_freq must be in"),
        ({"window": (0.5, 0.51)}, "shorter than one sample"),
    ],
)
def test_bad_parameters_are_rejected(params: dict, message: str) -> None:
    kwargs = {"sfreq": SFREQ, "tmin": TMIN, "ch_names": CH_NAMES} | params
    with pytest.raises(ValueError, match=message):
        ErrPFeatures(**kwargs).fit(random_epochs())


def test_transform_before_fit_or_after_failed_fit_raises() -> None:
    features = ErrPFeatures(SFREQ, TMIN, CH_NAMES)
    with pytest.raises(NotFittedError):
        features.transform(random_epochs())
    with pytest.raises(ValueError, match="too short"):
        features.fit(random_epochs()[:, :, :100])
    with pytest.raises(NotFittedError):
        features.transform(random_epochs())


def test_float32_input_gives_float64_features() -> None:
    epochs = random_epochs(n_epochs=20)
    features = ErrPFeatures(SFREQ, TMIN, CH_NAMES).fit(epochs)
    out64 = features.transform(epochs)
    out32 = features.transform(epochs.astype(np.float32))
    assert out32.dtype == np.float64
    np.testing.assert_allclose(out32, out64, rtol=1e-5, atol=1e-5 * np.abs(out64).max())


def test_epochs_are_processed_independently_of_the_batch() -> None:
    epochs = random_epochs(n_epochs=10)
    features = ErrPFeatures(SFREQ, TMIN, CH_NAMES).fit(epochs)
    batch = features.transform(epochs)
    order = np.random.default_rng(0).permutation(10)
    np.testing.assert_allclose(features.transform(epochs[order]), batch[order], rtol=1e-12)
    for i in (0, 7):
        np.testing.assert_allclose(features.transform(epochs[i : i + 1])[0], batch[i], rtol=1e-12)


def test_band_pass_is_zero_phase_and_removes_offsets() -> None:
    times = TMIN + np.arange(N_TIMES) / SFREQ
    in_band = np.sin(2 * np.pi * 5.0 * times + 1.0)
    out_of_band = 50.0 + 3 * np.sin(2 * np.pi * 40.0 * times)  # DC offset + line-noise-like
    epochs = np.stack([in_band, out_of_band])[:, None, :].repeat(4, axis=1)
    features = ErrPFeatures(SFREQ, TMIN, CH_NAMES).fit(epochs)
    out = features.transform(epochs)
    # In band: unchanged amplitude and no phase shift, up to edge transients.
    expected = np.tile(np.sin(2 * np.pi * 5.0 * features.times_ + 1.0), 3)
    np.testing.assert_allclose(out[0], expected, atol=0.15)
    assert np.corrcoef(out[0], expected)[0, 1] > 0.99
    # Out of band: a 50 µV offset and a 3 µV 40 Hz wave leave less than 0.1 µV.
    assert np.abs(out[1]).max() < 0.1


def test_clone_and_get_params_round_trip() -> None:
    ch_names = list(CH_NAMES)
    features = ErrPFeatures(SFREQ, TMIN, ch_names, window=(0.2, 0.7), decimate_to=64.0)
    params = features.get_params()
    assert params["ch_names"] is ch_names  # stored unchanged
    assert params["window"] == (0.2, 0.7)
    copy = clone(features)
    assert copy.get_params() == params
    assert not hasattr(copy, "sos_")
    copy.set_params(channels=("Cz",))
    assert copy.fit_transform(random_epochs()).shape == (6, 32)


def test_inside_a_pipeline_with_cross_validation() -> None:
    data = generate_errp_epochs(160, 40, accuracy=0.9, seed=3)
    pipeline = Pipeline(
        [
            ("features", ErrPFeatures(data.sfreq, data.tmin, data.ch_names)),
            ("lda", LinearDiscriminantAnalysis(solver="lsqr", shrinkage=0.5, priors=[0.5, 0.5])),
        ]
    )
    scores = cross_val_score(pipeline, data.epochs, data.labels, cv=5, scoring="balanced_accuracy")
    assert scores.mean() > 0.7
    pipeline.fit(data.epochs, data.labels)
    assert pipeline.predict(data.epochs[:3]).shape == (3,)
    assert len(pipeline[:-1].get_feature_names_out()) == 57
