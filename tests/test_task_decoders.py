"""The shared-statistics decoders of all tasks equal plain references.

Hard labels: scikit-learn's pooled-covariance LDA with the equal-prior correction
(``reference.EqualPriorLDA``), refitted per task and per fold. Soft labels and signals a
task gives no label (guidance): the same formulas written out with numpy.
"""

import tracemalloc

import numpy as np
import pytest
from reference import (
    confusion,
    lda,
    reference_log_match,
    weighted_cross_validated_proba,
    weighted_lda_log_proba,
)

from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.likelihood import confusion_matrices, corrected_proba, match
from calibration_free.task_decoders import TaskHistory, TaskModels, decoder_fit
from calibration_free.world import GridWorld
from decoding.lda import ShrinkageLDA
from decoding.statistics import ClassStatistics, one_hot
from decoding.student_t import fit_student_t


def random_problem(rng, n_signals, n_features, n_tasks, n_classes):
    """Signals with a class-dependent mean and per-task labels balanced enough for 10 folds."""
    labels = np.stack([rng.permutation(np.arange(n_signals) % n_classes) for _ in range(n_tasks)])
    history = rng.normal(size=(n_signals, n_features)) + 0.8 * labels[0][:, None]
    expected = rng.dirichlet(np.ones(n_classes), size=n_tasks)
    return history, labels, rng.normal(size=n_features), expected


def soft_weights(rng, n_tasks, n_signals, n_classes, unlabelled_share=0.15):
    """Soft labels (Dirichlet), some split over two classes only, some signals unlabelled
    (all-zero weights, as guidance at a task's own cell)."""
    weights = rng.dirichlet(np.full(n_classes, 0.5), size=(n_tasks, n_signals))
    two = rng.random((n_tasks, n_signals)) < 0.3
    weights[two, -1] = 0.0
    weights /= weights.sum(axis=-1, keepdims=True)
    weights[rng.random((n_tasks, n_signals)) < unlabelled_share] = 0.0
    return weights


def history_of(signals, weights, **kwargs):
    tasks = TaskHistory(weights.shape[0], weights.shape[2], signals.shape[1], **kwargs)
    for i, x in enumerate(signals):
        tasks.add(x, weights[:, i])
    return tasks


@pytest.mark.parametrize(
    ("seed", "n_signals", "n_features", "n_classes", "shrinkage"),
    [(0, 60, 4, 2, 0.5), (1, 83, 7, 2, 0.2), (2, 120, 5, 3, 0.5), (3, 97, 12, 2, 0.9),
     (4, 75, 6, 2, 0.0)],
)
@pytest.mark.parametrize("eigen_period", [None, 1, 4, 7])
def test_batched_update_equals_sklearn_lda_with_kfold(
    seed, n_signals, n_features, n_classes, shrinkage, eigen_period
):
    """Scatters decomposed by the decoders, or kept decomposed with up to ``eigen_period -
    1`` signals pending (shrinkage 0 decomposes them anyway)."""
    rng = np.random.default_rng(seed)
    history, labels, signal, expected = random_problem(rng, n_signals, n_features, 5, n_classes)
    tasks = history_of(history, one_hot(labels, n_classes), eigen_period=eigen_period)
    if eigen_period is not None:  # some training set has signals pending, or none may
        assert (tasks.pooled_statistics().eigen.pending.shape[-2] > 0) == (eigen_period > 1)
    for balanced in (True, False):
        models = TaskModels.fit(tasks, decoder_fit("lda", shrinkage), 1.0, balanced)
        fast = np.log(match(expected, models.corrected_proba(signal[None])[:, 0]))
        reference = reference_log_match(
            history, labels, signal, expected, n_classes=n_classes, shrinkage=shrinkage,
            balanced=balanced,
        )
        np.testing.assert_allclose(fast, reference, rtol=0, atol=1e-8)


@pytest.mark.parametrize(
    ("seed", "n_classes", "shrinkage"), [(0, 4, 0.5), (1, 2, 0.3), (2, 4, 0.8)]
)
@pytest.mark.parametrize("eigen_period", [None, 5])
def test_soft_and_unlabelled_weights_equal_the_weighted_numpy_reference(
    seed, n_classes, shrinkage, eigen_period
):
    """Full decoders, fold decoders (out-of-fold predictions) and log-likelihood updates,
    with the scatters decomposed by the decoders or kept decomposed with signals pending."""
    rng = np.random.default_rng(seed)
    n_signals, n_features, n_tasks = 90, 5, 4
    signals = rng.normal(size=(n_signals, n_features)) + rng.normal(size=n_features)
    weights = soft_weights(rng, n_tasks, n_signals, n_classes)
    weights[0] = one_hot(np.arange(n_signals) % n_classes, n_classes)  # one hard task
    new = rng.normal(size=(3, n_features))
    tasks = history_of(signals, weights, eigen_period=eigen_period)
    assert eigen_period is None or tasks.pooled_statistics().eigen.pending.shape[-2] > 0
    models = TaskModels.fit(tasks, decoder_fit("lda", shrinkage), 1.0)
    expected = rng.dirichlet(np.ones(n_classes), size=n_tasks)
    for task in range(n_tasks):
        full = weighted_lda_log_proba(signals, weights[task], shrinkage, new)
        np.testing.assert_allclose(
            np.exp(models.decoders.log_proba(new)[models.labelling[task]]),
            np.exp(full),
            rtol=0,
            atol=1e-10,
        )
        cv = weighted_cross_validated_proba(signals, weights[task], shrinkage)
        np.testing.assert_allclose(models.cv_proba[task], cv, rtol=0, atol=1e-10)
        q = confusion(weights[task], cv) @ np.exp(full[0])
        np.testing.assert_allclose(
            np.log(match(expected, models.corrected_proba(new[:1])[:, 0]))[task],
            np.log(expected[task] @ q),
            rtol=0,
            atol=1e-8,
        )


def test_unlabelled_signals_widen_the_covariance_but_train_no_class():
    """A task that labels no signal of a third cluster: its decoder equals the one
    trained on the labelled signals with that cluster's within-class scatter added."""
    rng = np.random.default_rng(8)
    labelled = rng.normal(size=(40, 3)) + np.arange(40)[:, None] % 2
    unlabelled = 5.0 + rng.normal(size=(15, 3)) * np.array([3.0, 0.1, 1.0])
    signals = np.r_[labelled, unlabelled]
    weights = np.r_[one_hot(np.arange(40) % 2, 2), np.zeros((15, 2))][None]
    models = TaskModels.fit(history_of(signals, weights), decoder_fit("lda", 0.5), 1.0)
    probe = rng.normal(size=(4, 3))
    with_rest = weighted_lda_log_proba(signals, weights[0], 0.5, probe)
    np.testing.assert_allclose(
        models.decoders.log_proba(probe)[models.labelling[0]], with_rest, atol=1e-10
    )
    # ... which is not the decoder of the labelled signals alone: the rest counts.
    alone = weighted_lda_log_proba(labelled, weights[0, :40], 0.5, probe)
    assert np.abs(with_rest - alone).max() > 1e-3


def test_learner_updates_equal_the_reference_along_a_session():
    """Every log-likelihood increment of the learner, for every task, against sklearn."""
    world = GridWorld(3)
    # A fixed shrinkage before the first target (the reference cannot choose one).
    config = LearnerConfig(
        planner="random", beta=0.999999, power_prior=False, first_target_shrinkage=0.9
    )
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
                shrinkage=config.shrinkage_before_first_target,  # no target is declared
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


@pytest.mark.parametrize("decoder", ["lda", "student_t", "gaussian"])
def test_relabelling_equals_copying_the_task_labels(decoder):
    """Relabel at a switch, go on with per-task labels, switch again: every model equals
    that of a history built from scratch with the copied labels."""
    rng = np.random.default_rng(1)
    n_tasks, n_features = 4, 3
    signals = rng.normal(size=(110, n_features)) + 0.5
    weights = soft_weights(rng, n_tasks, 110, 2, unlabelled_share=0.1)
    switches = {40: 2, 75: 0}
    fit = decoder_fit(decoder, 0.5)
    tasks = TaskHistory(n_tasks, 2, n_features, class_scatters=fit.class_scatters)
    copied = weights.copy()
    for i, x in enumerate(signals):
        tasks.add(x, weights[:, i])
        if i + 1 in switches:
            tasks.relabel(switches[i + 1])
            copied[:, : i + 1] = copied[switches[i + 1], : i + 1]
    np.testing.assert_array_equal(tasks.label_weights, copied)
    for task in range(n_tasks):
        np.testing.assert_array_equal(tasks.task_label_weights(task), copied[task])
    fast = TaskModels.fit(tasks, fit, 1.0)
    slow = TaskModels.fit(history_of(signals, copied, class_scatters=fit.class_scatters), fit, 1.0)
    probe = rng.normal(size=(5, n_features))
    np.testing.assert_allclose(fast.cv_proba, slow.cv_proba, rtol=0, atol=1e-10)
    np.testing.assert_allclose(fast.confusion, slow.confusion, rtol=0, atol=1e-10)
    np.testing.assert_allclose(
        fast.corrected_proba(probe), slow.corrected_proba(probe), rtol=0, atol=1e-10
    )


@pytest.mark.parametrize("decoder", ["lda", "student_t", "gaussian", "categorical"])
def test_fits_without_folds_equal_the_whole_history_decoders(decoder):
    """What "simple" and "batch" matching fit: the whole history's decoders alone, equal to
    those of the cross-validated fit, and no confusion."""
    rng = np.random.default_rng(5)
    n_signals, n_features = 60, 3
    signals = rng.normal(size=(n_signals, n_features)) + 2.0
    if decoder == "categorical":
        signals = np.eye(n_features)[rng.integers(0, n_features, size=n_signals)]
    weights = soft_weights(rng, 4, n_signals, 2, unlabelled_share=0.0)
    fit = decoder_fit(decoder, 0.5)
    history = history_of(signals, weights, class_scatters=fit.class_scatters)
    alone = TaskModels.fit(history, fit, 1.0, cross_validate=False)
    assert alone.confusion is None and alone.cv_proba is None
    with pytest.raises(RuntimeError, match="without cross-validation"):
        alone.corrected_proba(signals[:2])
    validated = TaskModels.fit(history, fit, 1.0)
    assert alone.informative.all()
    np.testing.assert_allclose(alone.proba(signals), validated.proba(signals), atol=1e-12)


def test_relabelling_allocates_no_per_task_statistics():
    """A switch moves one task's statistics into the shared part: it allocates far less
    than the per-task statistics (an in-place reset, no copy)."""
    n_tasks, n_features = 400, 57
    tasks = TaskHistory(n_tasks, 2, n_features)
    rng = np.random.default_rng(2)
    for _ in range(30):
        tasks.add(rng.normal(size=n_features), one_hot(rng.integers(0, 2, size=n_tasks), 2))
    per_task_bytes = tasks._sums.own.nbytes + tasks._counts.own.nbytes
    tracemalloc.start()
    tasks.relabel(7)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < per_task_bytes / 100


def test_student_t_task_decoders_equal_one_at_a_time():
    """The per-task path: full and fold decoders against fits on each task's own data."""
    rng = np.random.default_rng(4)
    signals = rng.normal(size=(80, 3))
    labels = rng.integers(0, 2, size=(3, 80))
    weights = one_hot(labels, 2)
    fit = decoder_fit("student_t", 0.5)
    full, folds = fit(history_of(signals, weights, class_scatters=True))
    probe = rng.normal(size=(6, 3))
    in_fold = np.arange(80) % 10
    for task in range(3):
        alone = fit_student_t(ClassStatistics.from_signals(signals, weights[task]))
        np.testing.assert_allclose(full.log_proba(probe)[task], alone.log_proba(probe), atol=1e-10)
        for f in (0, 7):
            train = in_fold != f
            held = fit_student_t(ClassStatistics.from_signals(signals[train], weights[task, train]))
            np.testing.assert_allclose(
                folds.log_proba(probe)[f, task], held.log_proba(probe), atol=1e-10
            )


@pytest.mark.parametrize("n_classes", [2, 4])
def test_shrinkage_lda_estimator_equals_sklearn(n_classes):
    rng = np.random.default_rng(n_classes)
    y = np.arange(90) % n_classes
    X = rng.normal(size=(90, 6)) + y[:, None] * 0.5
    ours = ShrinkageLDA(shrinkage=0.3).fit(X, y)
    theirs = lda(0.3).fit(X, y)
    np.testing.assert_allclose(ours.predict_proba(X), theirs.predict_proba(X), atol=1e-12)
    assert (ours.predict(X) == theirs.predict(X)).all()


def test_balanced_accuracy_equals_sklearn_cross_validation():
    from sklearn.metrics import balanced_accuracy_score
    from sklearn.model_selection import KFold, cross_val_predict

    rng = np.random.default_rng(7)
    history, labels, _, _ = random_problem(rng, 90, 4, 3, 2)
    tasks = history_of(history, one_hot(labels, 2))
    models = TaskModels.fit(tasks, decoder_fit("lda", 0.5), 1.0)
    order = np.lexsort((np.arange(90), np.arange(90) % 10))
    for task in range(len(labels)):
        predicted = np.empty(90, dtype=int)
        predicted[order] = cross_val_predict(
            lda(0.5), history[order], labels[task][order], cv=KFold(10)
        )
        expected = balanced_accuracy_score(labels[task], predicted)
        assert models.balanced_accuracy(task, tasks.task_label_weights(task)) == pytest.approx(
            expected, abs=1e-12
        )
    assert models.balanced_accuracy(0, np.c_[np.ones(90), np.zeros(90)]) is None


def _oas_intensity(signals, labels, n_classes):
    """scikit-learn's OAS intensity of the pooled within-class covariance."""
    from sklearn.covariance import OAS

    means = np.stack([signals[labels == k].mean(axis=0) for k in range(n_classes)])
    return OAS(assume_centered=True).fit(signals - means[labels]).shrinkage_


@pytest.mark.parametrize(("seed", "n_classes"), [(11, 2), (12, 3)])
def test_oas_lda_equals_sklearn_lda_at_each_training_sets_oas_intensity(seed, n_classes):
    rng = np.random.default_rng(seed)
    signals, labels, _, _ = random_problem(rng, 70, 6, 3, n_classes)
    models = TaskModels.fit(history_of(signals, one_hot(labels, n_classes)),
                            decoder_fit("lda", "oas"), 1.0)
    probe = rng.normal(size=(9, 6))
    fold = np.arange(len(signals)) % 10
    intensities = []
    for task, y in enumerate(labels):
        intensity = _oas_intensity(signals, y, n_classes)
        intensities.append(intensity)
        expected = lda(intensity).fit(signals, y).predict_proba(probe)
        np.testing.assert_allclose(
            models.decoders.proba(probe)[models.labelling[task]], expected, atol=1e-10
        )
        for f in (0, 3, 9):
            train = fold != f
            held_out = lda(_oas_intensity(signals[train], y[train], n_classes)).fit(
                signals[train], y[train]
            )
            np.testing.assert_allclose(
                models.cv_proba[task][~train], held_out.predict_proba(signals[~train]),
                atol=1e-10,
            )
    # The intensity is each labelling's own: they differ between tasks.
    assert 0.0 < min(intensities) < max(intensities)


def test_oas_shrinkage_is_rejected_where_it_is_not_computed():
    with pytest.raises(ValueError, match="needs decoder 'lda'"):
        LearnerConfig(decoder="gaussian", shrinkage="oas")
    with pytest.raises(ValueError, match="shrinkage"):
        LearnerConfig(shrinkage="ledoit-wolf")


@pytest.mark.parametrize("n_classes", [2, 3])
def test_without_shrinkage_and_fewer_signals_than_features_lda_is_sklearns_least_squares(
    n_classes,
):
    rng = np.random.default_rng(20 + n_classes)
    signals, labels, _, _ = random_problem(rng, 12, 15, 3, n_classes)
    models = TaskModels.fit(history_of(signals, one_hot(labels, n_classes)),
                            decoder_fit("lda", 0.0), 1.0)
    probe = rng.normal(size=(5, 15))
    fold = np.arange(len(signals)) % 10
    for task, y in enumerate(labels):
        expected = lda(0.0).fit(signals, y).predict_proba(probe)
        np.testing.assert_allclose(
            models.decoders.proba(probe)[models.labelling[task]], expected, atol=1e-8
        )
        train = fold != 0  # balanced labels: every class keeps at least 2 signals
        assert np.all(np.bincount(y[train], minlength=n_classes) >= 2)
        held_out = lda(0.0).fit(signals[train], y[train])
        np.testing.assert_allclose(
            models.cv_proba[task][~train], held_out.predict_proba(signals[~train]), atol=1e-8,
        )


def test_a_labelling_without_within_class_spread_does_not_stop_the_others():
    """Every class of task 0 holds one signal (no within-class spread: an exactly singular
    covariance for some draws); it is uninformative, and task 1 is still scikit-learn's."""
    from decoding.lda import fit_pooled_lda
    from decoding.statistics import PooledStatistics

    rng = np.random.default_rng(0)
    weights = np.stack([one_hot(np.array([0, 1, 2, 3, 0]), 4),
                        one_hot(np.array([0, 0, 1, 1, 1]), 4)], axis=1)  # (n, T, K)
    weights[4, 0] = 0.0  # task 0 gives the last signal no label
    for _ in range(200):  # some of these draws made the old solve raise "Singular matrix"
        signals = rng.normal(size=(5, 2))
        statistics = PooledStatistics.from_class_statistics(
            ClassStatistics.from_signals(signals, weights)
        )
        decoders = fit_pooled_lda(statistics, 0.5)
        assert list(decoders.informative) == [False, True]
        expected = lda(0.5).fit(signals, np.array([0, 0, 1, 1, 1])).predict_proba(signals)
        np.testing.assert_allclose(decoders.proba(signals)[1][:, :2], expected, atol=1e-10)


@pytest.mark.parametrize("eigen_period", [None, 3])
def test_one_shrinkage_per_labelling_equals_fitting_each_shrinkage_apart(eigen_period):
    from decoding.lda import fit_pooled_lda

    rng = np.random.default_rng(5)
    history = TaskHistory(4, 2, 6, eigen_period=eigen_period)
    labels = rng.integers(0, 2, size=(4, 47))
    for i, signal in enumerate(rng.normal(size=(47, 6)) + labels[0][:, None]):
        history.add(signal, one_hot(labels[:, i], 2))
    shrinkages = np.array([0.02, 0.3, 0.9])
    together = fit_pooled_lda(history.pooled_statistics(tasks=np.full(3, 2)), shrinkages)
    signals = rng.normal(size=(9, 6))
    for index, shrinkage in enumerate(shrinkages):
        apart = fit_pooled_lda(history.pooled_statistics(tasks=np.array([2])), shrinkage)
        np.testing.assert_allclose(
            together.proba(signals)[:, index], apart.proba(signals)[:, 0], rtol=1e-12
        )


@pytest.mark.parametrize("decoder", ["lda", "gaussian"])
def test_splitting_ambiguous_labels_again_equals_a_history_built_with_the_new_split(decoder):
    """Labels that allow two of three classes (guidance's two optimal directions) split
    again by new probabilities, after a switch: every model equals that of a history
    built from scratch with the new split; labels of one class, unlabelled signals and the
    labels adopted before the switch are kept."""
    rng = np.random.default_rng(7)
    n_tasks, n_signals, n_classes, n_features, switch = 3, 90, 3, 4, 30
    signals = rng.normal(size=(n_signals, n_features)) + 0.5
    frame = np.zeros((n_tasks, n_signals, n_classes))
    kind = rng.integers(3, size=(n_tasks, n_signals))  # 0: one class, 1: two, 2: none
    first = rng.integers(n_classes, size=(n_tasks, n_signals))
    second = (first + 1 + rng.integers(n_classes - 1, size=first.shape)) % n_classes
    np.put_along_axis(frame, first[..., None], 1.0, axis=-1)
    two = np.zeros_like(frame)
    np.put_along_axis(two, first[..., None], 0.5, axis=-1)
    np.put_along_axis(two, second[..., None], 0.5, axis=-1)
    frame = np.where((kind == 1)[..., None], two, np.where((kind == 2)[..., None], 0.0, frame))
    arrival = resolve_ambiguous(frame, rng.dirichlet(np.ones(n_classes), size=frame.shape[:2]))
    fit = decoder_fit(decoder, 0.5)
    tasks = TaskHistory(
        n_tasks, n_classes, n_features, n_folds=5, class_scatters=fit.class_scatters,
        keeps_frame_labels=True,
    )
    for i, x in enumerate(signals):
        tasks.add(x, arrival[:, i], frame[:, i])
        if i + 1 == switch:
            tasks.relabel(1)
    proba = rng.dirichlet(np.ones(n_classes), size=(n_tasks, n_signals))
    with pytest.raises(ValueError, match="signals since the switch"):
        tasks.resplit_own_labels(proba)  # every signal's, not those since the switch
    assert tasks.n_adopted == switch
    tasks.resplit_own_labels(proba[:, tasks.n_adopted :])
    expected = arrival.copy()
    expected[:, :switch] = arrival[1, :switch]
    expected[:, switch:] = resolve_ambiguous(frame[:, switch:], proba[:, switch:])
    np.testing.assert_allclose(tasks.label_weights, expected, rtol=0, atol=1e-15)
    assert not np.allclose(expected[:, switch:], arrival[:, switch:])  # the split moved
    fast = TaskModels.fit(tasks, fit, 1.0)
    slow = TaskModels.fit(
        history_of(signals, expected, n_folds=5, class_scatters=fit.class_scatters), fit, 1.0
    )
    np.testing.assert_allclose(fast.cv_proba, slow.cv_proba, rtol=0, atol=1e-10)
    np.testing.assert_allclose(fast.confusion, slow.confusion, rtol=0, atol=1e-10)
    # The out-of-fold probabilities the learner splits by, from the switch on: the
    # cross-validated ones in signal order (every class of these decoders is known).
    assert fast.decoders.present.all()
    np.testing.assert_array_equal(fast.held_out_proba(switch), fast.cv_proba[:, switch:])


def resolve_ambiguous(frame, proba):
    """The split of labels allowing two classes by ``proba``; other labels as they are."""
    two = (frame > 0).sum(axis=-1, keepdims=True) == 2
    shared = frame * proba
    return np.where(two, shared / np.where(two, shared.sum(axis=-1, keepdims=True), 1.0), frame)


def test_a_history_without_frame_labels_refuses_to_split_them_again():
    tasks = TaskHistory(2, 3, 2)
    tasks.add(np.ones(2), np.full((2, 3), 1 / 3))
    with pytest.raises(RuntimeError, match="frame labels"):
        tasks.resplit_own_labels(np.full((2, 1, 3), 1 / 3))


def test_one_tasks_pooled_statistics_equal_its_slice_of_every_tasks() -> None:
    rng = np.random.default_rng(8)
    signals = rng.normal(size=(57, 5))
    weights = soft_weights(rng, 4, 57, 3)
    tasks = history_of(signals[:40], weights[:, :40])
    tasks.relabel(2)  # shared parts and own parts both non-zero below
    for i in range(40, 57):
        tasks.add(signals[i], weights[:, i])
    for with_folds in (True, False):
        every = tasks.pooled_statistics(with_folds)
        for task in range(4):
            one = tasks.pooled_statistics(with_folds, tasks=np.array([task]))
            np.testing.assert_array_equal(one.counts, every.counts[:, [task]])
            np.testing.assert_array_equal(one.sums, every.sums[:, [task]])
            np.testing.assert_array_equal(one.scatter, every.scatter)


@pytest.mark.parametrize(
    ("decoder", "history_options"),
    [("lda", {}), ("lda", {"eigen_period": 3}), ("student_t", {"class_scatters": True}),
     ("gaussian", {"class_scatters": True}), ("categorical", {})],
)
def test_one_task_fit_equals_that_task_in_the_batch(decoder, history_options):
    """What the learner fits for one task's balanced accuracy between two fits of all."""
    rng = np.random.default_rng(11)
    signals = rng.normal(size=(64, 5)) + 0.5 * rng.integers(0, 2, size=(64, 1))
    if decoder == "categorical":  # button presses: one-hot signals
        signals = np.eye(5)[rng.integers(0, 5, size=64)]
    weights = soft_weights(rng, 4, 64, 2)
    tasks = history_of(signals[:40], weights[:, :40], **history_options)
    tasks.relabel(1)  # shared and own parts both non-zero
    for i in range(40, 64):
        tasks.add(signals[i], weights[:, i])
    fit = decoder_fit(decoder, 0.4)
    every, every_folds = fit(tasks)
    every_proba = tasks.cross_validated_proba(every_folds)
    probe = signals[:6]
    assert every.informative.all(), "uninformative decoders would compare uniform to uniform"
    for task in range(4):
        one, one_folds = fit(tasks, tasks=np.array([task]))
        np.testing.assert_allclose(one.proba(probe)[0], every.proba(probe)[task], atol=1e-12)
        np.testing.assert_allclose(
            tasks.cross_validated_proba(one_folds)[:, :, 0], every_proba[:, :, task], atol=1e-12
        )


def _grouped_weights(rng, n_signals, n_classes, groups):
    """Soft labels where the tasks of each group (a list of task counts) agree exactly:
    (n_tasks, n_signals, n_classes)."""
    distinct = soft_weights(rng, len(groups), n_signals, n_classes)
    return np.repeat(distinct, groups, axis=0)


def test_tasks_with_the_same_labels_since_the_switch_share_one_labelling():
    rng = np.random.default_rng(21)
    signals = rng.normal(size=(50, 4))
    weights = _grouped_weights(rng, 50, 3, [2, 3, 1])  # tasks 0-1, 2-4, 5
    weights[4, 45:] = weights[5, 45:]  # task 4 leaves its group at signal 45
    tasks = TaskHistory(6, 3, 4)
    assert len(tasks.labellings[1]) == 1  # no signal yet: every task alike
    for i in range(45):
        tasks.add(signals[i], weights[:, i])
    labelling, representatives = tasks.labellings
    assert len(representatives) == 3
    assert len(set(labelling[:2])) == 1 and len(set(labelling[2:5])) == 1
    assert len(set(labelling[[0, 2, 5]])) == 3
    np.testing.assert_array_equal(labelling[representatives], np.arange(3))
    for i in range(45, 50):
        tasks.add(signals[i], weights[:, i])
    labelling, representatives = tasks.labellings
    assert len(representatives) == 4 and labelling[4] not in labelling[[0, 2, 5]]
    tasks.relabel(3)  # every task adopts task 3's labels: one labelling again
    assert tasks.labellings[0].tolist() == [0] * 6 and tasks.labellings[1].tolist() == [0]


def test_labellings_are_the_distinct_label_rows_since_the_switch_in_lexicographic_order():
    # The labellings are numbered, and represented, as np.unique numbers the tasks'
    # distinct rows of label weights (value equality: -0.0 is 0.0), signal after signal.
    rng = np.random.default_rng(22)
    n_tasks, n_signals = 40, 30
    weights = _grouped_weights(rng, n_signals, 2, [5, 1, 7, 3, 2, 9, 4, 6, 3])
    weights = weights[rng.permutation(n_tasks)]
    weights[rng.random(weights.shape) < 0.3] = 0.0
    weights[:, ::3][weights[:, ::3] == 0.0] = -0.0
    tasks = TaskHistory(n_tasks, 2, 3)
    for i, signal in enumerate(rng.normal(size=(n_signals, 3))):
        tasks.add(signal, weights[:, i])
        _, first, inverse = np.unique(
            weights[:, : i + 1].reshape(n_tasks, -1), axis=0, return_index=True,
            return_inverse=True,
        )
        labelling, representatives = tasks.labellings
        np.testing.assert_array_equal(labelling, inverse.reshape(-1))
        np.testing.assert_array_equal(representatives, first)
    assert len(representatives) > 5


@pytest.mark.parametrize(
    ("decoder", "history_options"),
    [("lda", {}), ("lda", {"eigen_period": 3}), ("student_t", {"class_scatters": True}),
     ("categorical", {})],
)
def test_models_of_shared_labellings_equal_every_task_fitted_on_its_own(
    decoder, history_options
):
    """The models fit one decoder per labelling; fitting every task's labels (the same
    labels repeated) must give every task the same decoders, predictions and confusion."""
    rng = np.random.default_rng(22)
    signals = rng.normal(size=(70, 5)) + 0.6 * rng.integers(0, 2, size=(70, 1))
    if decoder == "categorical":
        signals = np.eye(5)[rng.integers(0, 5, size=70)]
    weights = _grouped_weights(rng, 70, 2, [3, 1, 2, 2])
    tasks = history_of(signals[:40], weights[:, :40], **history_options)
    tasks.relabel(4)  # a shared part, then own parts that group the tasks
    for i in range(40, 70):
        tasks.add(signals[i], weights[:, i])
    fit = decoder_fit(decoder, 0.4)
    models = TaskModels.fit(tasks, fit, smoothing=1.0)
    assert len(models.labelling) == 8 and models.decoders.present.shape[0] == 4
    every = np.arange(8)
    decoders, folds = fit(tasks, tasks=every)
    by_fold = tasks.cross_validated_proba(folds)
    confusion = confusion_matrices(
        tasks.label_confusion_counts(by_fold, every), decoders.present, 1.0, True
    )
    corrected = corrected_proba(confusion, decoders.proba(probe := signals[:7]))
    assert decoders.informative.all(), "uninformative decoders would compare uniform to uniform"
    for task in range(8):
        own = models.labelling[task]
        np.testing.assert_allclose(
            models.decoders.proba(probe)[own], decoders.proba(probe)[task], atol=1e-12
        )
        np.testing.assert_allclose(models.cv_by_fold[:, :, own], by_fold[:, :, task], atol=1e-12)
        np.testing.assert_allclose(models.confusion[own], confusion[task], atol=1e-12)
        np.testing.assert_allclose(models.corrected_proba(probe)[task], corrected[task], atol=1e-12)


def test_splitting_labels_again_regroups_the_tasks_by_their_new_labels():
    """Probabilities that differ within a labelling split it; the labelling follows the
    weights, not the probabilities' provenance."""
    frame = np.array([[0.5, 0.5, 0.0], [1.0, 0.0, 0.0]])  # ambiguous, then a plain label
    tasks = TaskHistory(3, 3, 2, keeps_frame_labels=True)
    for x in np.eye(2):
        tasks.add(x, np.repeat(frame[None, 0], 3, axis=0))
    assert len(tasks.labellings[1]) == 1
    proba = np.full((3, 2, 3), 1 / 3)
    proba[2, :, 0] = 0.6  # task 2's probabilities differ: its split too
    proba[2, :, 1:] = 0.2
    tasks.resplit_own_labels(proba)
    labelling, representatives = tasks.labellings
    assert len(representatives) == 2 and labelling[0] == labelling[1] != labelling[2]


@pytest.mark.parametrize("shrinkage", [1.5, -0.1, np.nan, np.array([0.2, 1.2])])
def test_a_shrinkage_outside_zero_one_is_rejected_with_its_value(shrinkage):
    from decoding.lda import fit_pooled_lda

    history = TaskHistory(2, 2, 3)
    for signal in np.random.default_rng(0).normal(size=(12, 3)):
        history.add(signal, one_hot(np.array([0, 1]), 2))
    with pytest.raises(ValueError, match=r"shrinkage must be in \[0, 1\]"):
        fit_pooled_lda(history.pooled_statistics(tasks=np.array([0, 0])), shrinkage)
