"""The Student-t decoder's two counts: each class's own (default) and the thesis code's total."""

import numpy as np
import pytest
from scipy.stats import multivariate_t

from decoding.statistics import ClassStatistics, one_hot, shrink_towards_identity, spd_inverse
from decoding.student_t import fit_student_t


def imbalanced(n_major=40, n_minor=3, d=4, seed=0):
    """A large class 0 and a small, shifted class 1."""
    rng = np.random.default_rng(seed)
    y = np.r_[np.zeros(n_major, int), np.ones(n_minor, int)]
    return rng.normal(size=(len(y), d)) + 2.0 * y[:, None], y


def thesis_log_density(X, members, n_total, shrinkage):
    """The lfui code's predictive, written out: Sigma = shrunk biased covariance of the class,
    S = Sigma (N - 1), nu = N - d, scale S (N + 1) / (N nu), with N the total count."""
    d = X.shape[1]
    mean = members.mean(axis=0)
    sigma = shrink_towards_identity(np.cov(members.T, bias=True), shrinkage)
    nu = n_total - d
    scale = sigma * (n_total - 1) * (n_total + 1) / (n_total * nu)
    return multivariate_t(mean, scale, df=nu).logpdf(X)


def test_the_total_count_is_the_thesis_codes_predictive_for_every_class():
    X, y = imbalanced()
    decoders = fit_student_t(ClassStatistics.from_signals(X, one_hot(y, 2)), 0.5, "total")
    log_density = np.stack(
        [thesis_log_density(X, X[y == k], len(X), 0.5) for k in (0, 1)], axis=1
    )
    expected = np.exp(log_density - np.logaddexp(log_density[:, :1], log_density[:, 1:]))
    np.testing.assert_allclose(np.exp(decoders.log_proba(X)), expected, atol=1e-10)
    # The small class (3 signals in 4-D) takes part; with its own count it would not.
    assert decoders.present.tolist() == [True, True]
    own = fit_student_t(ClassStatistics.from_signals(X, one_hot(y, 2)), 0.5)
    assert own.present.tolist() == [True, False] and not own.informative
    # ... and it is told apart from the large class (shifted by 2 in every dimension).
    assert np.mean(decoders.log_proba(X).argmax(axis=1) == y) > 0.9


def test_the_total_count_needs_more_signals_than_dimensions_and_two_per_class():
    X, y = imbalanced(n_major=3, n_minor=1, d=4)  # 4 signals in 4-D: improper
    decoders = fit_student_t(ClassStatistics.from_signals(X, one_hot(y, 2)), 0.5, "total")
    assert not decoders.informative
    np.testing.assert_allclose(np.exp(decoders.log_proba(X)), 0.5)
    X, y = imbalanced(n_major=20, n_minor=1, d=4)  # one signal: no covariance of its own
    decoders = fit_student_t(ClassStatistics.from_signals(X, one_hot(y, 2)), 0.5, "total")
    assert decoders.present.tolist() == [True, False]


def test_total_counts_batched_over_label_hypotheses_equal_one_at_a_time():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(50, 3))
    labels = rng.integers(0, 3, size=(4, 50))
    batch = ClassStatistics.from_signals(X, one_hot(labels, 3).swapaxes(0, 1))
    together = fit_student_t(batch, 0.5, "total").log_proba(X)
    for task, lab in enumerate(labels):
        alone = fit_student_t(ClassStatistics.from_signals(X, one_hot(lab, 3)), 0.5, "total")
        np.testing.assert_allclose(together[task], alone.log_proba(X), atol=1e-12)


def test_an_unknown_count_is_an_error_naming_it():
    X, y = imbalanced()
    with pytest.raises(ValueError, match="counts must be one of 'class', 'total'; got 'all'"):
        fit_student_t(ClassStatistics.from_signals(X, one_hot(y, 2)), 0.5, "all")


def test_a_class_of_copies_of_one_signal_takes_no_part_with_the_total_count():
    # The shuffled-label control draws signals with replacement: a class may hold two
    # copies of one signal, a zero covariance even after shrinkage.
    X, y = imbalanced(n_major=20, n_minor=1, d=4)
    X, y = np.r_[X, X[-1:]], np.r_[y, 1]
    decoders = fit_student_t(ClassStatistics.from_signals(X, one_hot(y, 2)), 0.5, "total")
    assert decoders.present.tolist() == [True, False]
    X[-1] += 1e-3  # two distinct signals: a covariance of its own
    decoders = fit_student_t(ClassStatistics.from_signals(X, one_hot(y, 2)), 0.5, "total")
    assert decoders.present.tolist() == [True, True]
    # Without shrinkage a class needs more signals than dimensions, as with its own count.
    decoders = fit_student_t(ClassStatistics.from_signals(X, one_hot(y, 2)), 0.0, "total")
    assert decoders.present.tolist() == [True, False]


def test_spd_inverse_equals_numpys_inverse_and_log_determinant():
    rng = np.random.default_rng(0)
    factors = rng.normal(size=(3, 5, 11, 30))
    matrices = factors @ np.swapaxes(factors, -1, -2) / 30 + 0.1 * np.eye(11)
    inverses, log_det = spd_inverse(matrices)
    assert np.allclose(inverses, np.linalg.inv(matrices), rtol=1e-10, atol=1e-12)
    assert np.allclose(log_det, np.linalg.slogdet(matrices)[1], rtol=1e-12)
    with pytest.raises(np.linalg.LinAlgError):
        spd_inverse(np.diag([1.0, -1.0]))
