"""The Bhattacharyya overlap likelihood and the signal-space uncertainty (method-extensions §1)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration_free import signal_space
from calibration_free.bhattacharyya import (
    bhattacharyya_coefficient,
    overlap_log_factor,
    overlap_per_task,
)
from calibration_free.signal_space import signal_space_uncertainty


def test_equal_gaussians_overlap_fully() -> None:
    means = np.zeros((2, 3))
    covariances = np.stack([np.diag([1.0, 2.0, 3.0])] * 2)
    assert bhattacharyya_coefficient(means, covariances) == pytest.approx(1.0)


@pytest.mark.parametrize("gap", [0.5, 1.0, 3.0])
def test_one_dimensional_unit_gaussians_follow_the_closed_form(gap: float) -> None:
    means = np.array([[0.0], [gap]])
    covariances = np.ones((2, 1, 1))
    assert bhattacharyya_coefficient(means, covariances) == pytest.approx(np.exp(-gap**2 / 8))
    # Swapping the two classes changes nothing.
    assert bhattacharyya_coefficient(means[::-1], covariances[::-1]) == pytest.approx(
        np.exp(-gap**2 / 8)
    )


def test_unequal_variances_add_the_determinant_term() -> None:
    means = np.zeros((2, 1))
    covariances = np.array([[[1.0]], [[4.0]]])
    # D_B = ln(2.5 / sqrt(4)) / 2 for N(0, 1) against N(0, 4).
    assert bhattacharyya_coefficient(means, covariances) == pytest.approx(
        np.exp(-0.5 * np.log(2.5 / 2.0))
    )


def test_the_true_labelling_overlaps_far_less_than_a_mixed_one() -> None:
    rng = np.random.default_rng(0)
    truth = np.repeat([0, 1], 100)
    signals = rng.normal(size=(200, 4)) + 3.0 * truth[:, None]
    mixed = rng.permutation(truth)
    weights = np.stack([np.eye(2)[truth], np.eye(2)[mixed], np.eye(2)[1 - truth]])
    rho = overlap_per_task(signals, weights, shrinkage=0.5)
    assert rho[0] < 0.2 < 0.9 < rho[1]
    # A symmetric labelling (classes swapped) has the same overlap: no symmetry is broken.
    assert rho[2] == pytest.approx(rho[0])
    assert np.all(overlap_log_factor(rho) <= 0.0)


def test_a_task_with_an_empty_class_gets_no_information() -> None:
    signals = np.random.default_rng(1).normal(size=(10, 3))
    weights = np.zeros((1, 10, 2))
    weights[0, :, 0] = 1.0
    assert overlap_per_task(signals, weights, 0.5).tolist() == [1.0]


def _reference_uncertainty(means: np.ndarray, labels: np.ndarray, w: np.ndarray) -> np.ndarray:
    n_tasks, n_states, n_actions = labels.shape
    result = np.zeros((n_states, n_actions))
    for s in range(n_states):
        for a in range(n_actions):
            expected = np.array([means[t, labels[t, s, a]] for t in range(n_tasks)])
            pairwise = ((expected[:, None] - expected[None]) ** 2).sum(axis=-1)
            result[s, a] = 0.5 * w @ pairwise @ w
    return result


def test_the_signal_space_map_equals_half_the_weighted_pairwise_distances() -> None:
    rng = np.random.default_rng(2)
    means = rng.normal(size=(6, 3, 4))
    labels = rng.integers(3, size=(6, 5, 2))
    weights = rng.dirichlet(np.ones(6))
    assert signal_space_uncertainty(means, labels, weights) == pytest.approx(
        _reference_uncertainty(means, labels, weights)
    )


def test_the_signal_space_map_vanishes_for_one_hypothesis_or_shared_means() -> None:
    rng = np.random.default_rng(3)
    means = rng.normal(size=(4, 2, 3))
    labels = rng.integers(2, size=(4, 7, 5))
    assert np.allclose(signal_space_uncertainty(means, labels, np.eye(4)[1]), 0.0)
    shared = np.broadcast_to(means[:1], means.shape).copy()
    same_labels = np.broadcast_to(labels[:1], labels.shape).copy()
    assert np.allclose(signal_space_uncertainty(shared, same_labels, np.full(4, 0.25)), 0.0)
    # Permuting labels within a hypothesis (and its means with them) changes nothing.
    swapped = means.copy()
    swapped[0] = means[0, ::-1]
    relabelled = labels.copy()
    relabelled[0] = 1 - labels[0]
    w = rng.dirichlet(np.ones(4))
    assert signal_space_uncertainty(swapped, relabelled, w) == pytest.approx(
        signal_space_uncertainty(means, labels, w)
    )


def test_the_signal_space_map_is_the_same_computed_in_chunks(monkeypatch) -> None:
    rng = np.random.default_rng(4)
    means = rng.normal(size=(5, 2, 3))
    labels = rng.integers(2, size=(5, 9, 1))  # labels that do not depend on the action
    weights = rng.dirichlet(np.ones(5))
    whole = signal_space_uncertainty(means, labels, weights)
    monkeypatch.setattr(signal_space, "_CHUNK_ELEMENTS", 10)  # 2 columns per chunk
    chunked = signal_space_uncertainty(means, labels, weights)
    assert chunked.shape == (9, 1)
    np.testing.assert_allclose(chunked, whole, rtol=1e-12, atol=1e-12)
    assert chunked == pytest.approx(_reference_uncertainty(means, labels, weights))
