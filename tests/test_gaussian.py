"""The K-class Gaussian generator: geometry of the class means and its nominal accuracy."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.gaussian import class_directions, class_spacing, generate_gaussian_features
from acquisition.sources import DataSpec


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
