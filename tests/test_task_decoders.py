"""The batched per-task computation equals a scikit-learn reference."""

import numpy as np
import pytest
from reference import lda, reference_log_match

from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.likelihood import match
from calibration_free.task_decoders import TaskHistory, TaskModels, decoder_fit
from calibration_free.world import GridWorld
from decoding.lda import ShrinkageLDA
from decoding.statistics import one_hot


def random_problem(rng, n_signals, n_features, n_tasks, n_classes):
    """Signals with a class-dependent mean and per-task labels balanced enough for 10 folds."""
    labels = np.stack([rng.permutation(np.arange(n_signals) % n_classes) for _ in range(n_tasks)])
    history = rng.normal(size=(n_signals, n_features)) + 0.8 * labels[0][:, None]
    expected = rng.dirichlet(np.ones(n_classes), size=n_tasks)
    return history, labels, rng.normal(size=n_features), expected


@pytest.mark.parametrize(
    ("seed", "n_signals", "n_features", "n_classes", "shrinkage"),
    [(0, 60, 4, 2, 0.5), (1, 83, 7, 2, 0.2), (2, 120, 5, 3, 0.5), (3, 97, 12, 2, 0.9)],
)
def test_batched_update_equals_sklearn_lda_with_kfold(
    seed, n_signals, n_features, n_classes, shrinkage
):
    rng = np.random.default_rng(seed)
    history, labels, signal, expected = random_problem(rng, n_signals, n_features, 5, n_classes)
    tasks = TaskHistory(len(labels), n_classes, n_features)
    for i, x in enumerate(history):
        tasks.add(x, one_hot(labels[:, i], n_classes))
    for balanced in (True, False):
        models = TaskModels.fit(tasks, decoder_fit("lda", shrinkage), 1.0, balanced)
        fast = np.log(match(expected, models.corrected_proba(signal[None])[:, 0]))
        reference = reference_log_match(
            history, labels, signal, expected, n_classes=n_classes, shrinkage=shrinkage,
            balanced=balanced,
        )
        np.testing.assert_allclose(fast, reference, rtol=0, atol=1e-8)


def test_learner_updates_equal_the_reference_along_a_session():
    """Every log-likelihood increment of the learner, for every task, against sklearn."""
    world = GridWorld(3)
    config = LearnerConfig(planner="random", beta=0.999999, power_prior=False)
    learner = CalibrationFreeLearner(world, config, rng=0)
    rng = np.random.default_rng(5)
    frame = learner.frame
    states, actions, signals = [], [], []
    state = 4
    checked = 0
    for step in range(70):
        action = learner.propose(state).action
        signal = rng.normal(size=3).astype(np.float32)
        before = learner.log_likelihood.copy()
        learner.observe(state, action, signal)
        increment = learner.log_likelihood - before
        if step >= 40 and step % 10 == 0:
            history = np.asarray(signals, dtype=np.float64)
            labels = np.argmax(frame.label_weights[:, states, actions], axis=-1)
            ok = [_every_fold_informative(task_labels) for task_labels in labels]
            reference = reference_log_match(
                history, labels[ok], signal.astype(np.float64),
                frame.label_distribution[ok, state, action],
            )
            np.testing.assert_allclose(increment[ok], reference, rtol=0, atol=1e-8)
            checked += int(np.sum(ok))
        states.append(state)
        actions.append(action)
        signals.append(signal)
        state = world.step(state, action)
    assert checked >= 10  # enough tasks were informative to make the comparison mean something


def _every_fold_informative(labels, n_folds=10, min_count=2):
    folds = np.arange(len(labels)) % n_folds
    return all(
        np.all(np.bincount(labels[folds != f], minlength=2) >= min_count) for f in range(n_folds)
    )


def test_single_class_task_gives_no_information():
    rng = np.random.default_rng(0)
    tasks = TaskHistory(2, 2, 3)
    for i in range(30):
        tasks.add(rng.normal(size=3), one_hot(np.array([0, i % 2]), 2))
    models = TaskModels.fit(tasks, decoder_fit("lda", 0.5), smoothing=1.0)
    assert models.informative.tolist() == [False, True]
    q = models.corrected_proba(rng.normal(size=(4, 3)))
    assert np.allclose(q[0], 0.5) and not np.allclose(q[1], 0.5)


def test_relabel_copies_one_task_onto_all():
    rng = np.random.default_rng(1)
    tasks = TaskHistory(3, 2, 4)
    for _ in range(40):
        tasks.add(rng.normal(size=4), one_hot(rng.integers(0, 2, size=3), 2))
    tasks.relabel(2)
    models = TaskModels.fit(tasks, decoder_fit("lda", 0.5), smoothing=1.0)
    q = models.corrected_proba(rng.normal(size=(5, 4)))
    np.testing.assert_allclose(q[0], q[2], atol=1e-12)
    np.testing.assert_allclose(q[1], q[2], atol=1e-12)


@pytest.mark.parametrize("n_classes", [2, 4])
def test_shrinkage_lda_estimator_equals_sklearn(n_classes):
    rng = np.random.default_rng(n_classes)
    y = np.arange(90) % n_classes
    X = rng.normal(size=(90, 6)) + y[:, None] * 0.5
    ours = ShrinkageLDA(shrinkage=0.3).fit(X, y)
    theirs = lda(n_classes, 0.3).fit(X, y)
    np.testing.assert_allclose(ours.predict_proba(X), theirs.predict_proba(X), atol=1e-12)
    assert (ours.predict(X) == theirs.predict(X)).all()


def test_balanced_accuracy_equals_sklearn_cross_validation():
    from sklearn.metrics import balanced_accuracy_score
    from sklearn.model_selection import KFold, cross_val_predict

    rng = np.random.default_rng(7)
    history, labels, _, _ = random_problem(rng, 90, 4, 3, 2)
    tasks = TaskHistory(len(labels), 2, 4)
    for i, x in enumerate(history):
        tasks.add(x, one_hot(labels[:, i], 2))
    models = TaskModels.fit(tasks, decoder_fit("lda", 0.5), 1.0)
    order = np.lexsort((np.arange(90), np.arange(90) % 10))
    for task in range(len(labels)):
        predicted = np.empty(90, dtype=int)
        predicted[order] = cross_val_predict(
            lda(2, 0.5), history[order], labels[task][order], cv=KFold(10)
        )
        expected = balanced_accuracy_score(labels[task], predicted)
        assert models.balanced_accuracy(task, tasks.label_weights[task]) == pytest.approx(
            expected, abs=1e-12
        )
    assert models.balanced_accuracy(0, np.c_[np.ones(90), np.zeros(90)]) is None
