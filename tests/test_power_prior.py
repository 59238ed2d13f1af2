"""The ErrP power prior's two forms (``calibration_free.power_prior``) and its use."""

import numpy as np
import pytest
from scipy.stats import f_oneway

from acquisition.sources import DataSpec, synthetic_features
from calibration_free.config import LearnerConfig
from calibration_free.power_prior import (
    LogPowerEvidence,
    MeanPowerRatio,
    make_power_prior,
)
from cfbci.offline.simulation import SessionConfig, run_session


def signals_with_powers(rng: np.random.Generator, n: int, dims: int = 6) -> np.ndarray:
    """``n`` signals of random directions and log-normal powers, shape (n, dims)."""
    directions = rng.normal(size=(n, dims))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return directions * np.exp(rng.normal(0.0, 0.7, size=(n, 1)))


def fed(prior, signals: np.ndarray, weights: np.ndarray):
    """``prior`` after every signal, with label weights (n_tasks, n_signals, 2)."""
    for i, x in enumerate(signals):
        prior.add(weights[:, i], float(x @ x))
    return prior


def one_hot(labels: np.ndarray) -> np.ndarray:
    """Hard label weights (n_tasks, n_signals, 2) from labels (n_tasks, n_signals)."""
    return np.stack([1.0 - labels, labels], axis=-1).astype(float)


def test_the_evidence_is_the_analysis_of_variance_statistic_signed_by_the_class_order():
    # Hard labels: (n / 2) log(1 + F / (n - 2)), F scipy's one-way statistic of the
    # log powers, positive where the error class has the higher mean.
    rng = np.random.default_rng(0)
    signals = signals_with_powers(rng, 60)
    z = np.log((signals**2).sum(axis=1))
    labels = (rng.random((5, 60)) < 0.3).astype(int)
    labels[0] = z > np.median(z)  # errors the loudest: a large positive score
    labels[1] = 1 - labels[0]
    scores = fed(LogPowerEvidence(5), signals, one_hot(labels)).scores()
    for task in range(5):
        error, correct = z[labels[task] == 1], z[labels[task] == 0]
        f_statistic = f_oneway(error, correct).statistic
        expected = 30 * np.log1p(f_statistic / 58) * np.sign(error.mean() - correct.mean())
        assert scores[task] == pytest.approx(expected, rel=1e-9)
    assert scores[0] > 10 and scores[1] == pytest.approx(-scores[0])


def test_soft_label_weights_give_the_weighted_sums_of_squares():
    rng = np.random.default_rng(1)
    signals = signals_with_powers(rng, 40)
    z = np.log((signals**2).sum(axis=1))
    error = rng.random((3, 40))
    weights = np.stack([1.0 - error, error], axis=-1)
    scores = fed(LogPowerEvidence(3), signals, weights).scores()
    for task in range(3):
        w = weights[task]
        means = (w * z[:, None]).sum(axis=0) / w.sum(axis=0)
        within = (w * (z[:, None] - means) ** 2).sum()
        total = ((z - z.mean()) ** 2).sum()
        expected = np.sign(means[1] - means[0]) * 20 * np.log(total / within)
        assert scores[task] == pytest.approx(expected, rel=1e-9)


def test_the_evidence_does_not_depend_on_the_signals_units():
    rng = np.random.default_rng(2)
    signals = signals_with_powers(rng, 30)
    weights = one_hot((rng.random((4, 30)) < 0.4).astype(int))
    microvolts = fed(LogPowerEvidence(4), signals, weights).scores()
    volts = fed(LogPowerEvidence(4), signals * 1e-6, weights).scores()
    assert np.any(microvolts != 0)
    np.testing.assert_allclose(volts, microvolts, rtol=1e-6, atol=1e-9)


def test_nothing_before_three_signals_of_both_classes_and_no_nan_from_a_silent_signal():
    prior = LogPowerEvidence(2)
    weights = one_hot(np.array([[0, 1, 1], [0, 0, 0]]))
    signals = np.array([[1.0, 0.0], [0.0, 3.0], [0.0, 0.0]])
    for i, x in enumerate(signals):
        assert np.all(prior.scores() == 0)
        prior.add(weights[:, i], float(x @ x))
    scores = prior.scores()
    assert np.all(np.isfinite(scores)) and scores[1] == 0  # task 1 has no error yet


def test_a_target_switch_gives_every_task_the_adopted_sums():
    rng = np.random.default_rng(3)
    signals = signals_with_powers(rng, 30)
    weights = one_hot((rng.random((4, 30)) < 0.4).astype(int))
    for kind in ("evidence", "ratio"):
        prior = fed(make_power_prior(kind, 4), signals[:20], weights[:, :20])
        adopted = prior.scores()[2]
        prior.adopt(2)
        np.testing.assert_array_equal(prior.scores(), np.full(4, adopted))
        fed(prior, signals[20:], weights[:, 20:])  # each task's own signals since
        assert len(set(prior.scores())) > 1


def test_the_ratio_is_method_md_s_log_ratio_of_mean_powers():
    rng = np.random.default_rng(4)
    signals = signals_with_powers(rng, 25)
    power = (signals**2).sum(axis=1)
    error = rng.random((3, 25))
    weights = np.stack([1.0 - error, error], axis=-1)
    scores = fed(MeanPowerRatio(3), signals, weights).scores()
    expected = np.log((error * power).sum(1) / error.sum(1)) - np.log(
        ((1 - error) * power).sum(1) / (1 - error).sum(1)
    )
    np.testing.assert_allclose(scores, expected, rtol=1e-12)


def test_on_synthetic_errp_features_the_true_labels_gain_and_their_complement_loses():
    # The generator's error epochs carry more power (theta burst, larger waves): the
    # evidence for the true labels grows with the signals, and the complement's is its
    # negative. A prior that ignores the class order would not tell them apart.
    data = synthetic_features(0.78, np.random.default_rng(5))
    rng = np.random.default_rng(6)
    order = np.concatenate(
        [rng.permutation(np.flatnonzero(data.labels == k))[: n] for k, n in ((0, 280), (1, 120))]
    )
    order = rng.permutation(order)
    labels = data.labels[order][None]
    prior = LogPowerEvidence(2)
    weights = one_hot(np.concatenate([labels, 1 - labels]))
    true_scores = []
    for i, x in enumerate(data.features[order].astype(float)):
        prior.add(weights[:, i], float(x @ x))
        if i + 1 in (100, 200, 400):
            true_scores.append(prior.scores()[0])
            assert prior.scores()[1] == pytest.approx(-true_scores[-1])
    assert 0 < true_scores[0] < true_scores[2] and true_scores[2] > 8


def test_the_form_is_a_setting_and_an_unknown_one_is_refused():
    assert LearnerConfig().power_prior_kind == "evidence_then_ratio"
    with pytest.raises(ValueError, match="power_prior_kind"):
        LearnerConfig(power_prior_kind="mean")
    with pytest.raises(ValueError, match="power_prior_kind"):
        make_power_prior("mean", 4)


def test_the_evidence_keeps_a_session_out_of_the_complementary_mapping():
    # Synthetic ErrP 0.78, seed 35: with method.md's bounded ratio (and the threshold of its
    # time, 0.9) the first target (step 22) is the complement-like task, and every later
    # target follows its labels (0 correct, 43 wrong in 500 steps); with the evidence, until
    # the first target or throughout, at that threshold or the default's, it never adopts them.
    data = DataSpec(synthetic_accuracy=0.78).resolve("feedback")
    before = LearnerConfig(power_prior_kind="ratio", beta=0.9, first_target_signals=0)
    ratio = run_session(35, SessionConfig(learner=before), data)
    for other in (LearnerConfig(beta=0.9), LearnerConfig(power_prior_kind="evidence")):
        assert run_session(35, SessionConfig(learner=other), data).correct_targets > 15
    evidence = run_session(35, SessionConfig(), data)
    assert ratio.correct_targets == 0 and ratio.wrong_targets > 20
    assert evidence.correct_targets > 15 and evidence.wrong_targets <= 1


def test_the_default_form_is_the_evidence_until_the_first_target_then_the_ratio():
    rng = np.random.default_rng(7)
    signals = signals_with_powers(rng, 40)
    weights = one_hot((rng.random((4, 40)) < 0.4).astype(int))
    forms = [make_power_prior(kind, 4) for kind in ("evidence_then_ratio", "evidence", "ratio")]
    for prior in forms:
        fed(prior, signals[:25], weights[:, :25])
    np.testing.assert_array_equal(forms[0].scores(), forms[1].scores())
    for prior in forms:
        prior.adopt(1)
        fed(prior, signals[25:], weights[:, 25:])
    np.testing.assert_array_equal(forms[0].scores(), forms[2].scores())
    assert not np.allclose(forms[1].scores(), forms[2].scores())
