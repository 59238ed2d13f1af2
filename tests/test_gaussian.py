"""The K-class Gaussian generator: geometry of the class means and its nominal accuracy."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.gaussian import (
    class_directions,
    class_spacing,
    generate_gaussian_features,
    mixing_matrix,
)
from acquisition.sources import DataSpec
from decoding.lda import ShrinkageLDA


@pytest.mark.parametrize(("n_classes", "n_dims"), [(2, 1), (2, 2), (3, 2), (4, 2), (6, 20)])
def test_class_directions_are_unit_and_equally_spaced(n_classes: int, n_dims: int) -> None:
    directions = class_directions(n_classes, n_dims)
    assert directions.shape == (n_classes, n_dims)
    assert np.allclose(np.linalg.norm(directions, axis=1), 1.0)
    gaps = np.linalg.norm(directions[:, None] - directions[None], axis=2)
    nearest = np.sort(gaps, axis=1)[:, 1]
    assert np.allclose(nearest, nearest[0])  # every class has the same nearest distance


def test_one_dimension_holds_only_two_classes() -> None:
    with pytest.raises(ValueError, match="1-D holds only 2 classes"):
        class_directions(3, 1)


@pytest.mark.parametrize(("accuracy", "n_classes", "n_dims"), [(0.65, 2, 2), (0.95, 2, 2),
                                                                (0.95, 4, 2), (0.8, 6, 20)])
def test_the_bayes_classifier_reaches_the_nominal_accuracy_on_fresh_draws(
    accuracy: float, n_classes: int, n_dims: int
) -> None:
    data = generate_gaussian_features(5000, n_classes, n_dims, accuracy, seed=3)
    means = class_spacing(accuracy, n_classes, n_dims) * class_directions(n_classes, n_dims)
    distances = ((data.features[:, None, :] - means[None]) ** 2).sum(axis=2)
    recalls = [np.mean(distances[data.labels == k].argmin(axis=1) == k) for k in range(n_classes)]
    # 5000 draws per class: the standard error of the balanced accuracy is below 0.005.
    assert np.mean(recalls) == pytest.approx(accuracy, abs=0.015)


def test_a_gaussian_data_spec_gives_as_many_classes_as_the_frame_needs() -> None:
    for frame, n_classes in (("feedback", 2), ("guidance", 4)):
        data = DataSpec(synthetic="gaussian", synthetic_accuracy=0.9, dims=3).resolve(frame)
        drawn = data(np.random.default_rng(0))
        assert drawn.n_classes == n_classes and drawn.features.shape[1] == 3
        assert sorted(set(drawn.labels.tolist())) == list(range(n_classes))


@pytest.mark.parametrize("decay", [0.0, 1.0, 2.5])
def test_the_mixing_has_the_decaying_spectrum_and_is_fixed(decay: float) -> None:
    mixing = mixing_matrix(12, decay)
    spectrum = np.sort(np.linalg.eigvalsh(mixing @ mixing.T))[::-1]
    expected = np.arange(1, 13, dtype=float) ** -decay
    np.testing.assert_allclose(spectrum, expected / expected.mean(), rtol=1e-10)
    np.testing.assert_array_equal(mixing, mixing_matrix(12, decay))  # whatever the session


def test_mixed_signals_keep_the_nominal_accuracy_and_penalise_shrinkage() -> None:
    accuracy, n_dims, decay = 0.8, 20, 2.0
    plain = generate_gaussian_features(4000, 2, n_dims, accuracy, seed=5)
    mixed = generate_gaussian_features(4000, 2, n_dims, accuracy, seed=5, mixing_decay=decay)
    mixing = mixing_matrix(n_dims, decay)
    np.testing.assert_allclose(mixed.features, plain.features @ mixing.T, atol=1e-12)
    assert "mixed with decay 2" in mixed.source
    # The Bayes classifier of the mixed signals (known means, covariance A A^T).
    means = class_spacing(accuracy, 2, n_dims) * class_directions(2, n_dims) @ mixing.T
    weights = np.linalg.solve(mixing @ mixing.T, means[1] - means[0])
    decision = (mixed.features - means.mean(axis=0)) @ weights > 0
    bayes = np.mean([np.mean(decision[mixed.labels == k] == k) for k in (0, 1)])
    assert bayes == pytest.approx(accuracy, abs=0.015)
    # A shrunk LDA learned from 300 signals loses accuracy to the mixing: heavy shrinkage
    # cannot undo it (unmixed, it costs nothing).
    train = np.random.default_rng(0).choice(len(mixed.labels), 300, replace=False)
    test = np.setdiff1d(np.arange(len(mixed.labels)), train)

    def shrunk_accuracy(data, shrinkage):
        model = ShrinkageLDA(shrinkage).fit(data.features[train], data.labels[train])
        predicted = model.predict(data.features[test])
        return np.mean([np.mean(predicted[data.labels[test] == k] == k) for k in (0, 1)])

    assert shrunk_accuracy(mixed, 0.05) > shrunk_accuracy(mixed, 0.5) + 0.03  # 0.044
    assert abs(shrunk_accuracy(plain, 0.05) - shrunk_accuracy(plain, 0.5)) < 0.02  # 0.003


def test_a_mixing_decay_reaches_the_gaussian_data_spec() -> None:
    spec = DataSpec(synthetic="gaussian", dims=6, mixing_decay=1.5)
    data = spec.resolve("feedback")(np.random.default_rng(2))
    plain = DataSpec(synthetic="gaussian", dims=6).resolve("feedback")(np.random.default_rng(2))
    np.testing.assert_allclose(data.features, plain.features @ mixing_matrix(6, 1.5).T)
    assert "mixed with decay 1.5" in spec.describe()


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ({"mixing_decay": 2.0}, "needs --synthetic gaussian and no dataset"),
        ({"synthetic": "gaussian", "mixing_decay": -1.0}, "mixing decay must be in"),
    ],
)
def test_a_mixing_decay_that_would_be_ignored_or_is_out_of_range_is_refused(spec, message):
    with pytest.raises(ValueError, match=message):
        DataSpec(**spec)
