"""The decoders as estimators, and their batched forms."""

import numpy as np
import pytest
from scipy.stats import multivariate_normal, multivariate_t
from sklearn.base import clone
from sklearn.model_selection import cross_val_score
from sklearn.pipeline import make_pipeline

from decoding.categorical import fit_categorical
from decoding.gaussian import GaussianClassifier, fit_gaussian
from decoding.lda import ShrinkageLDA, fit_lda
from decoding.statistics import ClassStatistics, one_hot, shrink_towards_identity
from decoding.student_t import StudentTClassifier, fit_student_t

ESTIMATORS = [ShrinkageLDA, StudentTClassifier, GaussianClassifier]


def two_blobs(n=80, d=4, seed=0):
    rng = np.random.default_rng(seed)
    y = np.arange(n) % 2
    return rng.normal(size=(n, d)) + 1.5 * y[:, None], y


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_estimators_follow_the_scikit_learn_conventions(estimator):
    X, y = two_blobs()
    model = estimator(shrinkage=0.3)
    assert model.get_params() == {"shrinkage": 0.3}
    assert clone(model).get_params() == model.get_params()
    assert not hasattr(model, "classes_")
    assert model.fit(X, y) is model
    proba = model.predict_proba(X)
    assert proba.shape == (len(X), 2) and np.allclose(proba.sum(axis=1), 1.0)
    assert (model.predict(X) == model.classes_[proba.argmax(axis=1)]).all()
    scores = cross_val_score(make_pipeline(estimator()), X, y, cv=5)
    assert scores.mean() > 0.8


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_estimators_reject_bad_input(estimator):
    X, y = two_blobs()
    with pytest.raises(ValueError, match="shrinkage"):
        estimator(shrinkage=1.5).fit(X, y)
    with pytest.raises(ValueError, match="2 classes"):
        estimator().fit(X, np.zeros(len(X)))
    with pytest.raises(ValueError, match=r"NaN|infinity"):
        estimator().fit(np.where(np.eye(len(X), 4) > 0, np.nan, X), y)


def test_student_t_equals_the_scipy_multivariate_t_predictive():
    X, y = two_blobs(n=60, d=4, seed=1)
    model = StudentTClassifier(shrinkage=0.0).fit(X, y)
    log_density = []
    for k in (0, 1):
        Xk = X[y == k]
        n, d = Xk.shape
        centred = Xk - Xk.mean(axis=0)
        shape = centred.T @ centred * (n + 1) / (n * (n - d))
        log_density.append(multivariate_t(Xk.mean(axis=0), shape, df=n - d).logpdf(X))
    log_density = np.array(log_density).T
    expected = np.exp(log_density - np.logaddexp(log_density[:, :1], log_density[:, 1:]))
    np.testing.assert_allclose(model.predict_proba(X), expected, atol=1e-10)


def test_student_t_gives_no_information_while_classes_have_at_most_d_signals():
    rng = np.random.default_rng(0)
    X, y = rng.normal(size=(8, 5)), np.arange(8) % 2
    decoders = fit_student_t(ClassStatistics.from_signals(X, one_hot(y, 2)))
    assert not decoders.informative
    np.testing.assert_allclose(np.exp(decoders.log_proba(X)), 0.5)
    with pytest.raises(ValueError, match="needs at least 6 signals"):
        StudentTClassifier().fit(X, y)


@pytest.mark.parametrize("shrinkage", [0.0, 0.5])
def test_gaussian_equals_the_scipy_normal_densities_with_shrunk_covariances(shrinkage):
    X, y = two_blobs(n=60, d=4, seed=2)
    y = np.where(np.arange(60) < 10, 0, y)  # unequal class sizes: equal priors still
    model = GaussianClassifier(shrinkage=shrinkage).fit(X, y)
    log_density = []
    for k in (0, 1):
        Xk = X[y == k]
        covariance = shrink_towards_identity(np.cov(Xk.T, bias=True), shrinkage)
        log_density.append(multivariate_normal(Xk.mean(axis=0), covariance).logpdf(X))
    log_density = np.array(log_density).T
    expected = np.exp(log_density - np.logaddexp(log_density[:, :1], log_density[:, 1:]))
    np.testing.assert_allclose(model.predict_proba(X), expected, atol=1e-10)


def test_gaussian_leaves_out_a_class_with_a_singular_covariance():
    rng = np.random.default_rng(0)
    X, y = rng.normal(size=(20, 5)), (np.arange(20) < 3).astype(int)  # class 1: 3 signals
    decoders = fit_gaussian(ClassStatistics.from_signals(X, one_hot(y, 2)), shrinkage=0.0)
    assert decoders.present.tolist() == [True, False] and not decoders.informative
    np.testing.assert_allclose(np.exp(decoders.log_proba(X)), 0.5)
    shrunk = fit_gaussian(ClassStatistics.from_signals(X, one_hot(y, 2)), shrinkage=0.5)
    assert shrunk.informative


def test_categorical_decoder_reads_button_frequencies():
    """Class 0 pressed B 3 times and O once, class 1 O twice: p(0 | B) = 1 (class 1
    never pressed B), p(0 | O) = 0.25 / (0.25 + 1); an unseen third button is uniform."""
    presses = np.eye(3)[[0, 0, 0, 1, 1, 1]]
    labels = one_hot([0, 0, 0, 0, 1, 1], 2)
    statistics = ClassStatistics.from_signals(presses, labels)
    decoders = fit_categorical(statistics.counts, statistics.sums)
    np.testing.assert_allclose(decoders.frequencies, [[0.75, 0.25, 0], [0, 1, 0]])
    proba = decoders.proba(np.eye(3))
    np.testing.assert_allclose(proba, [[1, 0], [0.2, 0.8], [0.5, 0.5]])
    with pytest.raises(ValueError, match="symbolic signals"):
        decoders.proba(-np.eye(3))
    alone = fit_categorical(statistics.counts * [1, 0], statistics.sums * [[1], [0]])
    assert not alone.informative
    np.testing.assert_allclose(alone.proba(np.eye(3)), 0.5)


@pytest.mark.parametrize("fit", [fit_lda, fit_student_t, fit_gaussian])
def test_batched_fits_equal_one_at_a_time(fit):
    rng = np.random.default_rng(3)
    X = rng.normal(size=(50, 3))
    labels = rng.integers(0, 3, size=(4, 50))
    batch = ClassStatistics.from_signals(X, one_hot(labels, 3).swapaxes(0, 1))
    together = fit(batch).log_proba(X)
    for task, lab in enumerate(labels):
        alone = fit(ClassStatistics.from_signals(X, one_hot(lab, 3))).log_proba(X)
        np.testing.assert_allclose(together[task], alone, atol=1e-12)


def test_a_class_without_data_gets_probability_zero():
    X, y = two_blobs()
    weights = np.c_[one_hot(y, 2), np.zeros(len(y))]  # a third class never seen
    decoders = fit_lda(ClassStatistics.from_signals(X, weights))
    assert decoders.informative and decoders.present.tolist() == [True, True, False]
    proba = np.exp(decoders.log_proba(X))
    assert np.all(proba[:, 2] == 0) and np.allclose(proba.sum(axis=1), 1.0)
    reference = ShrinkageLDA().fit(X, y).predict_proba(X)
    np.testing.assert_allclose(proba[:, :2], reference, atol=1e-12)


@pytest.mark.parametrize("fit", [fit_gaussian, fit_student_t])
def test_a_rounding_residue_of_a_class_count_is_an_empty_class(fit):
    # A held-out fold's count of a class whose weight is all in that fold is a difference
    # of sums: it can be -1e-17 with a sum of 1e-16. Divided through, that was a mean of
    # 1e291, an overflow and a NaN covariance that stopped the fit (eigh did not converge).
    rng = np.random.default_rng(0)
    X = rng.normal(size=(40, 3))
    statistics = ClassStatistics.from_signals(X, one_hot(np.arange(40) % 2, 3))
    counts = statistics.counts.copy()
    counts[2] = -1e-17
    sums, scatters = statistics.sums.copy(), statistics.scatters.copy()
    sums[2], scatters[2] = 1e-16, 1e-16
    residue = ClassStatistics(counts, sums, scatters)
    means, covariances = residue.class_moments()
    assert np.all(means[2] == 0.0) and np.all(covariances[2] == 0.0)
    decoders = fit(residue, 0.5)
    proba = decoders.proba(X)
    assert np.all(np.isfinite(proba)) and np.all(proba[:, 2] == 0.0)
    np.testing.assert_allclose(proba, fit(statistics, 0.5).proba(X), rtol=0, atol=1e-12)
