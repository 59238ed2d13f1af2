"""The Gaussian evidence of the tasks' labellings (calibration_free/gaussian_evidence.py)
and its use until the first target (``first_target_evidence="gaussian"``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import multigammaln
from test_learner_plugins import run_through_a_first_phase

from calibration_free.config import LearnerConfig
from calibration_free.gaussian_evidence import MEAN_PRIOR, PRIOR_STRENGTH, log_evidence
from calibration_free.likelihood import normalised_likelihood
from calibration_free.task_decoders import TaskHistory


def history_of(signals: np.ndarray, labels: np.ndarray) -> TaskHistory:
    """A history of ``signals`` (n, d) with every task's hard labels (n_tasks, n) in {0, 1}."""
    history = TaskHistory(labels.shape[0], 2, signals.shape[1])
    for signal, column in zip(signals, labels.T, strict=True):
        history.add(signal, np.eye(2)[column])
    return history


def normal_inverse_wishart_marginal(signals: np.ndarray, labels: np.ndarray) -> float:
    """log p(X | labels) in full, each class's mean and scatter computed from its own
    signals: the textbook conjugate update, none of the module's algebra."""
    n, d = signals.shape
    prior_mean = signals.mean(axis=0)
    variance = np.sum((signals - prior_mean) ** 2) / (n * d)
    nu_0, kappa_0 = PRIOR_STRENGTH * d, MEAN_PRIOR
    prior_scale = nu_0 * variance * np.eye(d)
    posterior_scale = prior_scale.copy()
    occam = 0.0
    for label in (0, 1):
        members = signals[labels == label]
        count = len(members)
        occam += 0.5 * d * np.log(kappa_0 / (kappa_0 + count))
        if count == 0:
            continue
        mean = members.mean(axis=0)
        posterior_scale += (members - mean).T @ (members - mean)
        gap = mean - prior_mean
        posterior_scale += kappa_0 * count / (kappa_0 + count) * np.outer(gap, gap)
    nu_n = nu_0 + n
    return (
        -0.5 * n * d * np.log(np.pi)
        + multigammaln(nu_n / 2, d)
        - multigammaln(nu_0 / 2, d)
        + 0.5 * nu_0 * np.linalg.slogdet(prior_scale)[1]
        - 0.5 * nu_n * np.linalg.slogdet(posterior_scale)[1]
        + occam
    )


def test_log_evidence_differs_between_labellings_as_the_full_marginal_does():
    rng = np.random.default_rng(0)
    signals = rng.normal(size=(40, 5)) * np.array([1.0, 2.0, 0.5, 1.0, 3.0]) + 4.0
    labels = rng.integers(0, 2, size=(6, 40))
    labels[1] = 0  # one labelling with an empty class
    evidence = log_evidence(history_of(signals, labels).pooled_statistics(with_folds=False))
    full = np.array([normal_inverse_wishart_marginal(signals, row) for row in labels])
    np.testing.assert_allclose(evidence - evidence[0], full - full[0], rtol=1e-9, atol=1e-9)


def test_the_true_labelling_stands_out_and_a_shuffled_one_does_not():
    rng = np.random.default_rng(1)
    truth = rng.integers(0, 2, size=200)
    signals = rng.normal(size=(200, 8)) + np.where(truth[:, None] == 1, 0.6, 0.0)
    shuffled = [rng.permutation(truth) for _ in range(20)]
    labels = np.array([truth, *shuffled])
    evidence = log_evidence(history_of(signals, labels).pooled_statistics(with_folds=False))
    assert np.argmax(evidence) == 0
    assert normalised_likelihood(evidence)[0] > 0.999
    # The mirror labelling (classes swapped) explains the signals exactly as well.
    mirrored = log_evidence(
        history_of(signals, np.array([truth, 1 - truth])).pooled_statistics(with_folds=False)
    )
    assert mirrored[0] == pytest.approx(mirrored[1], abs=1e-8)


def test_log_evidence_is_zero_until_two_distinct_signals():
    labels = np.array([[0, 1], [1, 1]])
    history = history_of(np.zeros((2, 3)), labels)
    np.testing.assert_array_equal(log_evidence(history.pooled_statistics(with_folds=False)), 0.0)
    one = history_of(np.ones((1, 3)), labels[:, :1])
    np.testing.assert_array_equal(log_evidence(one.pooled_statistics(with_folds=False)), 0.0)


def test_the_learner_declares_on_the_evidence_then_switches_to_matching():
    config = LearnerConfig(first_target_evidence="gaussian", planner="random", evidence_beta=0.99)

    def recomputed_every_step(step, learner, beliefs):
        if step > 0:
            statistics = learner.history.pooled_statistics(with_folds=False)
            np.testing.assert_allclose(beliefs.log_likelihood, log_evidence(statistics))

    run_through_a_first_phase(config, "gaussian-evidence", 0.99, 2, 150, recomputed_every_step)


@pytest.mark.parametrize(
    "settings, message",
    [
        ({"frame": "guidance"}, "needs frame 'feedback'"),
        ({"likelihood": "simple"}, "likelihood 'matching'"),
        ({"declare_targets": False}, "declare_targets"),
        ({"first_target_evidence": "bayes"}, "first_target_evidence"),
        ({"evidence_beta": 1.0}, "evidence_beta"),
    ],
)
def test_the_evidence_settings_are_checked(settings, message):
    values = {"first_target_evidence": "gaussian"} | settings
    with pytest.raises(ValueError, match=message):
        LearnerConfig(**values)
