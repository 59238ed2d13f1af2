"""The shrinkage chosen from the data (``shrinkage="cv"``): its measure against a plain
reference, which shrinkage it picks where the answer is known, and the learner's use."""

from __future__ import annotations

import numpy as np
import pytest
from test_learner import WORLD, run

from calibration_free.baseline import CalibratedBaseline
from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.shrinkage_choice import (
    FIRST_CHOICE_PERIOD,
    FIRST_CHOICE_START,
    FIRST_TARGET_GRID,
    SHRINKAGE_GRID,
    STANDARD_ERRORS,
    choose_shrinkage,
    evidence_discriminability,
    labelled_history,
    shrinkage_grid,
)
from decoding.lda import ShrinkageLDA


def reference_discriminability(X, y, shrinkage, eps=0.1, n_folds=10, smoothing=1.0):
    """The measure for hard labels of two classes, written out plainly: the project's
    (scikit-learn-checked) LDA estimator per fold, then numpy."""
    n = len(y)
    proba = np.empty((n, 2))
    for fold in range(n_folds):
        test = np.arange(n) % n_folds == fold
        model = ShrinkageLDA(shrinkage).fit(X[~test], y[~test])
        proba[test] = model.predict_proba(X[test])
    counts = np.array([proba[y == k].sum(axis=0) for k in (0, 1)]) + smoothing
    counts /= counts.sum(axis=1, keepdims=True)  # every true class weighs the same
    confusion = counts / counts.sum(axis=0, keepdims=True)  # p(true | predicted)
    corrected = proba @ confusion.T
    true = corrected[np.arange(n), y]
    match_true = (1 - eps) * true + eps * (1 - true)
    match_other = (1 - eps) * (1 - true) + eps * true
    increments = np.log(match_true / match_other)
    means = [increments[y == k].mean() for k in (0, 1)]
    variances = [increments[y == k].var() for k in (0, 1)]
    return np.mean(means) / np.sqrt(np.mean(variances))


def correlated_pair(n, rng):
    """Two strongly correlated features plus noise features; the classes differ along the
    pair's small-variance direction (1, -1): shrinkage towards the identity hides it."""
    shared = rng.normal(size=(n, 1)) * 3.0
    y = rng.integers(0, 2, size=n)
    pair = shared + 0.3 * rng.normal(size=(n, 2)) + 0.5 * np.c_[y, -y]
    return np.c_[pair, rng.normal(size=(n, 4))], y


def correlated_signal(label, rng):
    """One signal of `correlated_pair`'s kind, of class ``label``."""
    pair = rng.normal() * 3.0 + 0.3 * rng.normal(size=2) + 0.5 * np.array([label, -label])
    return np.r_[pair, rng.normal(size=4)]


def isotropic_many(n, rng, d=40):
    """Isotropic noise in many dimensions, the class difference spread over all of them,
    few signals: only heavy shrinkage keeps the decoder from fitting the noise."""
    y = rng.integers(0, 2, size=n)
    return rng.normal(size=(n, d)) + 0.25 * y[:, None], y


@pytest.mark.parametrize("n", [37, 120])
def test_the_measure_equals_a_plain_reference(n: int) -> None:
    X, y = correlated_pair(n, np.random.default_rng(n))
    measured = evidence_discriminability(
        labelled_history(X, np.eye(2)[y]), 0, (0.1, 0.5, 0.9), eps=0.1, smoothing=1.0
    )
    expected = [reference_discriminability(X, y, s) for s in (0.1, 0.5, 0.9)]
    np.testing.assert_allclose(measured, expected, rtol=1e-8)


def test_it_picks_little_shrinkage_where_the_correlation_carries_the_classes() -> None:
    X, y = correlated_pair(400, np.random.default_rng(0))
    chosen = choose_shrinkage(labelled_history(X, np.eye(2)[y]), 0, eps=0.1, smoothing=1.0)
    assert chosen is not None and chosen <= 0.1


def test_it_keeps_the_heaviest_for_few_signals_in_many_dimensions() -> None:
    X, y = isotropic_many(80, np.random.default_rng(0))
    history = labelled_history(X, np.eye(2)[y])
    scores = evidence_discriminability(history, 0, SHRINKAGE_GRID, eps=0.1, smoothing=1.0)
    assert np.argmax(scores) == len(SHRINKAGE_GRID) - 1  # less shrinkage fits the noise
    assert choose_shrinkage(history, 0, eps=0.1, smoothing=1.0) == max(SHRINKAGE_GRID)


def test_a_gain_within_the_margin_keeps_the_heaviest_and_one_beyond_it_does_not() -> None:
    X, y = correlated_pair(400, np.random.default_rng(0))
    history = labelled_history(X, np.eye(2)[y])
    grid = (0.05, 0.06, 0.3)  # close neighbours, and one clearly heavier
    scores = evidence_discriminability(history, 0, grid, eps=0.1, smoothing=1.0)
    margin = STANDARD_ERRORS * np.sqrt((1 + np.max(scores) ** 2 / 2) / len(X))
    assert np.argmax(scores) == 0 and scores[0] - scores[1] < margin < scores[0] - scores[2]
    assert choose_shrinkage(history, 0, eps=0.1, smoothing=1.0, grid=grid) == 0.06
    # The margin is a parameter: none takes the best, a wide one the heaviest.
    assert choose_shrinkage(history, 0, eps=0.1, smoothing=1.0, grid=grid, margin=0) == 0.05
    wide = (scores[0] - scores[2]) / margin * STANDARD_ERRORS * 1.01
    assert choose_shrinkage(history, 0, eps=0.1, smoothing=1.0, grid=grid, margin=wide) == 0.3


def test_the_grid_keeps_the_intensities_from_its_floor_up() -> None:
    assert shrinkage_grid(SHRINKAGE_GRID[0]) == SHRINKAGE_GRID
    assert shrinkage_grid(0.05) == (0.05, 0.1, 0.2, 0.3, 0.5)  # the rule's first grid
    assert shrinkage_grid(0.04) == (0.05, 0.1, 0.2, 0.3, 0.5)
    assert shrinkage_grid(0.5) == (0.5,)


def test_a_class_too_rare_to_measure_gives_no_choice() -> None:
    X, y = correlated_pair(60, np.random.default_rng(1))
    y[:] = 0
    y[:2] = 1  # fold 0's training set holds one of them: no decoder knows the class
    history = labelled_history(X, np.eye(2)[y])
    assert np.all(np.isnan(evidence_discriminability(
        history, 0, SHRINKAGE_GRID, eps=0.1, smoothing=1.0)))
    assert choose_shrinkage(history, 0, eps=0.1, smoothing=1.0) is None


def test_unlabelled_signals_do_not_count_as_evidence() -> None:
    X, y = correlated_pair(300, np.random.default_rng(2))
    weights = np.eye(2)[y]
    weights[::7] = 0.0  # signals no label covers (guidance at a task's own cell)
    labelled = ~np.all(weights == 0.0, axis=1)
    with_rest = evidence_discriminability(
        labelled_history(X, weights), 0, (0.1, 0.5), eps=0.1, smoothing=1.0)
    # The unlabelled signals widen the covariance but add no increment: not the same as
    # dropping them, and not the same as labelling them.
    dropped = evidence_discriminability(
        labelled_history(X[labelled], weights[labelled]), 0, (0.1, 0.5), eps=0.1,
        smoothing=1.0)
    assert np.all(np.isfinite(with_rest)) and not np.allclose(with_rest, dropped)


@pytest.mark.parametrize(
    ("signals", "weights", "message"),
    [
        (np.zeros((5, 3)), np.zeros((4, 2)), "same n; got shapes"),
        (np.zeros(5), np.zeros((5, 2)), "same n; got shapes"),
        (np.zeros((5, 3)), np.zeros((5, 1)), "at least two classes"),
    ],
)
def test_a_history_of_wrong_shapes_is_refused(signals, weights, message) -> None:
    with pytest.raises(ValueError, match=message):
        labelled_history(signals, weights)


@pytest.mark.parametrize(
    "rule", [{}, {"shrinkage_floor": 0.05, "shrinkage_margin": 1.0}, {"shrinkage_margin": 0.0}]
)
def test_the_learner_chooses_at_every_target_from_the_adopted_labels(rule: dict) -> None:
    config = LearnerConfig(planner="random", shrinkage="cv", first_target_shrinkage=0.0, **rule)
    grid = shrinkage_grid(config.shrinkage_floor)
    learner = CalibrationFreeLearner(WORLD, config, rng=0)
    chosen = []

    def at_step(*_):
        if learner.n_targets > len(chosen):  # a target was just reached
            history = learner.history
            assert history.n_adopted == history.n_signals
            # Recomputed on a fresh history of the adopted labels (its scatters decomposed
            # anew, where the learner's reuse its rolling decompositions).
            fresh = labelled_history(history.signals, history.task_label_weights(0))
            chosen.append((learner.shrinkage_in_use, choose_shrinkage(
                fresh, 0, eps=config.eps, smoothing=config.confusion_smoothing, grid=grid,
                margin=config.shrinkage_margin)))

    # On correlated signals the three rules choose differently (0.02, 0.05 and 0.01).
    run(learner, target=5, steps=300, seed=1, signal=correlated_signal, on_step=at_step)
    assert len(chosen) >= 2, "the session must reach targets for the choice to show"
    previous = config.shrinkage_before_first_target
    for in_use, expected in chosen:  # a choice that cannot be measured keeps the last
        assert in_use == (previous if expected is None else expected)
        previous = in_use
    assert previous in grid, "some target must have been measurable"


def test_the_baseline_chooses_at_the_end_of_its_calibration() -> None:
    config = LearnerConfig(shrinkage="cv")
    baseline = CalibratedBaseline(WORLD, 3, n_calibration=60, config=config, rng=0)
    assert baseline.shrinkage_in_use == FIRST_TARGET_GRID[-1]  # never used: it calibrates
    run(baseline, target=5, steps=61, seed=2)
    assert baseline.shrinkage_in_use in SHRINKAGE_GRID


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"first_target_shrinkage": "cv", "declare_targets": False}, "needs declare_targets"),
        ({"shrinkage": "cv", "declare_targets": False}, "needs declare_targets"),
        ({"first_target_shrinkage": "cv", "decoder": "student_t"}, "needs decoder 'lda'"),
        ({"shrinkage": "cv", "decoder": "gaussian"}, "needs decoder 'lda' and likelihood"),
        ({"shrinkage": "cv", "likelihood": "simple"}, "needs decoder 'lda' and likelihood"),
        ({"shrinkage_floor": 0.0}, r"shrinkage_floor must be in \[0.01, 0.5\]; got 0.0"),
        ({"shrinkage_floor": 0.7}, r"shrinkage_floor must be in \[0.01, 0.5\]; got 0.7"),
        ({"shrinkage_margin": -1.0}, r"shrinkage_margin must be in \[0.0, 100.0\]; got -1.0"),
    ],
)
def test_a_choice_that_cannot_be_made_is_refused(values: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LearnerConfig(**values)


def test_until_the_first_target_feedback_chooses_where_it_can() -> None:
    assert LearnerConfig(shrinkage=0.5).shrinkage_before_first_target == "cv"
    assert LearnerConfig(likelihood="simple").shrinkage_before_first_target == 0.9
    guidance = LearnerConfig(frame="guidance", shrinkage="cv")
    assert guidance.shrinkage_before_first_target == 0.5
    assert guidance.to_dict()["shrinkage"] == "cv"


def test_until_the_first_target_the_learner_chooses_on_the_leading_tasks_labels() -> None:
    learner = CalibrationFreeLearner(WORLD, LearnerConfig(planner="random"), rng=0)
    checked = []

    def at_step(step, _, __, beliefs):
        n = learner.n_signals
        due = n >= FIRST_CHOICE_START and n % FIRST_CHOICE_PERIOD == 0
        if learner.n_targets or not due:
            return
        # The choice just made, on the leader's labels (the beliefs after that signal).
        history = learner.history
        fresh = labelled_history(history.signals, history.task_label_weights(
            beliefs.best_task))
        expected = choose_shrinkage(
            fresh, 0, eps=0.1, smoothing=1.0, grid=FIRST_TARGET_GRID, margin=1.0)
        if expected is not None:
            checked.append(expected)
            assert learner.shrinkage_in_use == expected

    # Correlated signals: less than the heaviest is chosen (0.9 until the first choice).
    run(learner, target=5, steps=150, seed=1, signal=correlated_signal, on_step=at_step)
    assert len(checked) >= 3 and min(checked) < FIRST_TARGET_GRID[-1], checked
