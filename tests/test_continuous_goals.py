"""The continuous-goal world: cardinal frame, particles, sampled-classifier confidence."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from acquisition.gaussian import generate_gaussian_features
from calibration_free.cardinal import cardinal_guidance
from calibration_free.continuous_goals import (
    ContinuousConfig,
    ContinuousGoalLearner,
    map_uncertainty,
    resample,
)
from calibration_free.sampled_confidence import (
    normal_difference_confidence,
    pairwise_normal_difference,
    sample_classifiers,
    sampled_log_likelihoods,
    shrunk_class_moments,
    soft_class_statistics,
)
from cfbci.offline.continuous import run_continuous_session

CENTRE = np.array([[0.5, 0.5]])


def _goal_at(angle: float) -> np.ndarray:
    return CENTRE + 0.3 * np.array([[np.cos(angle), np.sin(angle)]])


def test_the_cardinal_frame_gives_the_pages_worked_example() -> None:
    # Bearing pi/11 north of east: phi_E = pi/11, phi_N = 9 pi/22 -> N 0.18, E 0.82.
    up, down, right, left = cardinal_guidance(CENTRE, _goal_at(np.pi / 11), 0.0)[0, 0]
    assert (up, down, right, left) == pytest.approx((2 / 11, 0.0, 9 / 11, 0.0))
    noisy = cardinal_guidance(CENTRE, _goal_at(np.pi / 11), 0.05)[0, 0]
    assert noisy == pytest.approx([0.95 * 2 / 11, 0.025, 0.95 * 9 / 11, 0.025])


def test_a_goal_due_east_takes_all_but_alpha_and_rows_sum_to_one() -> None:
    east = cardinal_guidance(CENTRE, np.array([[0.9, 0.5]]), 0.0)[0, 0]
    assert east.tolist() == [0.0, 0.0, 1.0, 0.0]
    noisy = cardinal_guidance(CENTRE, np.array([[0.9, 0.5]]), 0.3)[0, 0]
    assert noisy == pytest.approx([0.1, 0.1, 0.7, 0.1])
    rng = np.random.default_rng(0)
    many = cardinal_guidance(rng.uniform(size=(200, 2)), rng.uniform(size=(30, 2)), 0.01)
    assert np.allclose(many.sum(axis=-1), 1.0)
    assert cardinal_guidance(CENTRE, CENTRE, 0.01)[0, 0] == pytest.approx([0.25] * 4)


@pytest.mark.parametrize("sampling", ["random", "active"])
def test_resampling_keeps_the_best_particle_and_stays_in_the_square(sampling: str) -> None:
    rng = np.random.default_rng(1)
    particles = rng.uniform(size=(50, 2))
    weights = rng.dirichlet(np.ones(50))
    new = resample(particles, weights, sampling, rng)
    assert new.shape == (50, 2)
    assert np.array_equal(new[0], particles[np.argmax(weights)])
    assert np.all((new >= 0) & (new <= 1))


def test_active_resampling_draws_a_fifth_from_the_broad_component() -> None:
    # All the weight on one particle in a corner: draws farther than 0.3 from it can only
    # come from the broad component (the narrow one has sd 0.1: 3 sd).
    particles = np.full((50, 2), 0.05)
    weights = np.zeros(50)
    weights[0] = 1.0
    far = 0
    rng = np.random.default_rng(2)
    for _ in range(200):
        new = resample(particles, weights, "active", rng)
        far += np.sum(np.linalg.norm(new[1:] - 0.05, axis=1) > 0.3)
    fraction = far / (200 * 49)
    # 0.2 of the draws are broad; of those, about 0.86 land farther than 0.3 (measured
    # analytically is not needed: a broken mixture gives ~0 or ~1).
    assert 0.12 < fraction < 0.2


def test_the_normal_difference_confidence_of_the_thesis_example() -> None:
    confidence = pairwise_normal_difference(np.array([0.71, 0.23]), np.array([0.17, 0.16]) ** 2)
    assert 0.975 < confidence[0] < 0.99
    assert confidence[1] == pytest.approx(1 - confidence[0])
    tied = pairwise_normal_difference(np.array([0.5, 0.5, 0.2]), np.zeros(3))
    assert tied.tolist() == [0.5, 0.5, 0.0]


def test_at_most_one_hypothesis_is_above_one_half() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        confidence = normal_difference_confidence(rng.normal(size=(30, 20)) * 5)
        assert np.sum(confidence > 0.5) <= 1


def test_sampled_means_concentrate_like_one_over_n() -> None:
    rng = np.random.default_rng(4)
    spreads = []
    for n in (40, 400):
        data = generate_gaussian_features(n // 4, 4, 3, 0.9, seed=5)
        weights = np.eye(4)[data.labels][None]
        means, covariances = shrunk_class_moments(
            soft_class_statistics(data.features, weights), data.features, 0.5
        )
        sampled = sample_classifiers(means, covariances, n, 400, rng).means  # (d, K, H, J)
        spreads.append(sampled[:, 0, 0].var(axis=1).mean())
    assert spreads[0] / spreads[1] == pytest.approx(10.0, rel=0.3)


def test_sampled_log_likelihoods_equal_a_direct_computation() -> None:
    # Every classifier's class densities from scipy, its class probabilities (equal
    # priors), the batch matching with each hypothesis's labels, summed over the signals.
    rng = np.random.default_rng(10)
    data = generate_gaussian_features(10, 4, 3, 0.9, seed=11)
    signals = data.features + 5.0  # off-centre: the product centres them itself
    labels = rng.dirichlet(np.ones(4), size=(3, len(signals)))  # (H, n, K)
    means, covariances = shrunk_class_moments(
        soft_class_statistics(signals, labels), signals, 0.5
    )
    draws = sample_classifiers(means, covariances, len(signals), 2, rng)
    expected = np.empty((3, 2))
    for h, j in np.ndindex(3, 2):
        factors = [draws.factors[..., k, h, j] for k in range(4)]
        assert all(np.array_equal(f, np.tril(f)) for f in factors)
        log_density = np.stack([
            multivariate_normal(draws.means[:, k, h, j], np.linalg.inv(f @ f.T)).logpdf(signals)
            for k, f in enumerate(factors)
        ], axis=1)  # (n, K)
        assert np.allclose(  # the factors' log determinant is the precision's
            draws.log_det[:, h, j], [np.linalg.slogdet(f @ f.T)[1] for f in factors]
        )
        proba = np.exp(log_density - logsumexp(log_density, axis=1, keepdims=True))
        expected[h, j] = np.log((labels[h] * proba).sum(axis=1)).sum()
    assert sampled_log_likelihoods(signals, labels, draws) == pytest.approx(expected, rel=1e-4)


def test_too_few_signals_are_refused() -> None:
    means, covariances = np.zeros((1, 4, 11)), np.broadcast_to(np.eye(11), (1, 4, 11, 11))
    with pytest.raises(ValueError, match="more signals than dimensions"):
        sample_classifiers(means, covariances.copy(), 11, 5, np.random.default_rng(0))


def test_the_uncertainty_map_vanishes_when_one_particle_holds_all_the_weight() -> None:
    data = generate_gaussian_features(50, 4, 3, 0.95, seed=6)
    config = ContinuousConfig(n_hypotheses=10, n_initial=6)
    learner = ContinuousGoalLearner(config, np.random.default_rng(7))
    rng = np.random.default_rng(8)
    for index in rng.choice(len(data.labels), 20):
        learner.observe(rng.uniform(size=2), data.features[index])
    learner.confidence = np.eye(10)[3]
    _, uncertainty = learner.uncertainty_map()
    assert np.allclose(uncertainty, 0.0)
    learner.confidence = np.full(10, 0.1)
    _, uncertainty = learner.uncertainty_map()
    assert uncertainty.max() > 1e-3


def _final_distances(class_order: list[int] | None, probing: str) -> list[float]:
    data = generate_gaussian_features(100, 4, 4, 0.98, seed=9)
    config = ContinuousConfig(n_hypotheses=20, probing=probing, sampling="active",
                              n_candidates=200)
    return [
        run_continuous_session(seed, config, data, steps=60, class_order=class_order).final_distance
        for seed in range(4)
    ]


def test_the_learner_finds_the_goal_whatever_the_class_order() -> None:
    # 4-D Gaussian stand-in, 60 probes: the estimate is near the goal (a broken likelihood
    # leaves it at the distance of a random particle, about 0.4), in either class order.
    for order in (None, [2, 0, 3, 1]):
        distances = _final_distances(order, "uncertainty")
        assert np.median(distances) < 0.05, distances


def test_the_map_uncertainty_equals_the_weighted_variance_of_the_matches() -> None:
    # Direct: every particle's expected match at every candidate and signal, their
    # weighted variance over particles, summed over the signals.
    rng = np.random.default_rng(12)
    frame = rng.dirichlet(np.ones(4), size=(30, 6))  # (C, H, K)
    corrected = rng.dirichlet(np.ones(4), size=(6, 5))  # (H, S, K)
    weights = rng.dirichlet(np.ones(6))
    matches = np.einsum("chk,hsk->hcs", frame, corrected)
    mean = np.einsum("h,hcs->cs", weights, matches)
    expected = np.einsum("h,hcs->c", weights, (matches - mean) ** 2)
    assert map_uncertainty(frame, corrected, weights) == pytest.approx(expected, rel=1e-9)
    assert expected.min() > 1e-3  # a case where the variance is not trivially zero
