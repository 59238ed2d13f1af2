"""Conformance of both learners to the small learner interface, and the learner's behaviour."""

import inspect

import numpy as np
import pytest

from calibration_free.baseline import CalibratedBaseline
from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner, TaskLearner
from calibration_free.world import ACTIONS, GOAL, GridWorld

WORLD = GridWorld(4)


def separated_signal(label: int, rng: np.random.Generator, n_features: int = 6) -> np.ndarray:
    """Two well separated classes (means 4 standard deviations apart)."""
    return (rng.normal(size=n_features) + 4.0 * label).astype(np.float32)


def make_calibration_free(config=None, rng=0):
    return CalibrationFreeLearner(WORLD, config, rng=rng)


def make_baseline(config=None, rng=0):
    return CalibratedBaseline(WORLD, calibration_target=5, n_calibration=40, config=config, rng=rng)


LEARNERS = [make_calibration_free, make_baseline]


def run(
    learner: TaskLearner,
    target: int,
    steps: int,
    seed: int = 0,
    start: int = 0,
    signal=separated_signal,
    on_step=None,
):
    """Drive a learner with a perfect feedback user; return the targets it declared.

    The user aims at ``target``, after the calibration target while a baseline calibrates,
    and answers label ``l`` with ``signal(l, rng)``. ``on_step(step, learner, proposal,
    beliefs)``, if given, is called before every observation with the beliefs the
    proposal was made from.
    """
    rng = np.random.default_rng(seed)
    state, declared = start, []
    final_target = target
    for step in range(steps):
        calibrating = getattr(learner, "calibrating", False)
        target = learner.calibration_target if calibrating else final_target
        beliefs = learner.beliefs()
        proposal = learner.propose(state)
        if on_step is not None:
            on_step(step, learner, proposal, beliefs)
        label = 0 if WORLD.optimal[target, state, proposal.action] else 1
        if proposal.declares_target:
            declared.append(state)
        learner.observe(state, proposal.action, signal(label, rng))
        state = WORLD.step(state, proposal.action)
    return declared


@pytest.mark.parametrize("make", LEARNERS)
def test_interface_takes_no_labels(make):
    learner = make()
    assert list(inspect.signature(learner.observe).parameters) == ["state", "action", "signal"]
    assert list(inspect.signature(learner.propose).parameters) == ["state"]
    assert list(inspect.signature(learner.beliefs).parameters) == []
    with pytest.raises(TypeError):
        learner.observe(0, 0, np.zeros(6, np.float32), label=1)  # type: ignore[call-arg]


@pytest.mark.parametrize("make", LEARNERS)
def test_proposals_and_beliefs_are_well_formed(make):
    learner = make()
    rng = np.random.default_rng(0)
    state = 0
    for _ in range(50):
        proposal = learner.propose(state)
        assert 0 <= proposal.action < len(ACTIONS)
        assert not proposal.declares_target or proposal.action == GOAL
        learner.observe(state, proposal.action, separated_signal(int(rng.integers(2)), rng))
        beliefs = learner.beliefs()
        assert beliefs.scores.shape == beliefs.confidence.shape == (WORLD.n_tasks,)
        assert np.all((beliefs.confidence > 0) & (beliefs.confidence < 1))
        best_confidence = beliefs.confidence[beliefs.best_task]
        assert beliefs.threshold == learner.config.frame_beta
        assert beliefs.required >= beliefs.threshold  # stricter only before a first target
        assert beliefs.confident == (best_confidence > beliefs.required)
        state = WORLD.step(state, proposal.action)
    assert learner.beliefs().n_signals == 50


@pytest.mark.parametrize("make", LEARNERS)
def test_same_seed_same_decisions(make):
    assert run(make(rng=3), target=10, steps=120, seed=1) == run(make(rng=3), 10, 120, seed=1)


@pytest.mark.parametrize("make", LEARNERS)
@pytest.mark.parametrize(
    ("signal", "message"),
    [
        (np.array([1.0, np.nan, 0, 0, 0, 0]), "NaN"),
        (np.zeros((2, 3)), "dimensions"),
        (np.array(["a"] * 6), "could not be read"),
    ],
)
def test_bad_signals_are_rejected_and_change_nothing(make, signal, message):
    learner = make()
    learner.observe(0, 0, np.zeros(6, np.float32))
    before = learner.beliefs()
    with pytest.raises((ValueError, TypeError), match=message):
        learner.observe(0, 1, signal)
    after = learner.beliefs()
    assert after.n_signals == before.n_signals
    np.testing.assert_array_equal(after.scores, before.scores)


@pytest.mark.parametrize("make", LEARNERS)
def test_bad_state_action_or_signal_length_are_rejected(make):
    learner = make()
    learner.observe(0, 0, np.zeros(6, np.float32))
    with pytest.raises(ValueError, match="state"):
        learner.observe(WORLD.n_states, 0, np.zeros(6, np.float32))
    with pytest.raises(ValueError, match="action"):
        learner.observe(0, 7, np.zeros(6, np.float32))
    with pytest.raises(ValueError, match="size 5 on axis 0; expected 6"):
        learner.observe(0, 0, np.zeros(5, np.float32))


@pytest.mark.parametrize(
    "planner", ["uncertainty", "greedy", "random", "signal", "epsilon-greedy"]
)
def test_learner_identifies_the_target_on_well_separated_signals(planner):
    config = LearnerConfig(planner=planner)
    for target in (0, 9, 15):
        learner = make_calibration_free(config, rng=target)
        declared = run(learner, target, steps=150, seed=target, start=(target + 7) % 16)
        assert declared, f"no target declared for target {target} with the {planner} planner"
        assert declared[0] == target


def test_baseline_identifies_the_target_after_calibration():
    learner = make_baseline()
    declared = run(learner, target=12, steps=120, seed=2)
    assert learner.n_signals == 120 and not learner.calibrating
    assert declared and declared[0] == 12


def test_the_second_target_comes_faster_than_the_first():
    """After a target, the history is relabelled and the decoder is already trained."""
    learner = make_calibration_free(rng=4)
    rng = np.random.default_rng(4)
    targets, reached_at, state, target = [3, 12, 9], [], 0, 3
    for step in range(400):
        proposal = learner.propose(state)
        label = 0 if WORLD.optimal[target, state, proposal.action] else 1
        learner.observe(state, proposal.action, separated_signal(label, rng))
        if proposal.declares_target:
            assert state == target
            reached_at.append(step)
            if len(reached_at) == len(targets):
                break
            target = targets[len(reached_at)]
        state = WORLD.step(state, proposal.action)
    assert len(reached_at) == 3
    gaps = np.diff([0, *reached_at])
    assert gaps[1:].max() < gaps[0]


def test_the_novelty_bonus_default_follows_the_frame_and_is_recorded_resolved():
    from dataclasses import replace

    from calibration_free.config import DEFAULT_NOVELTY_BONUS

    feedback = LearnerConfig()
    guidance = replace(feedback, frame="guidance")  # as the frame-hypotheses learner does
    assert feedback.frame_novelty_bonus == DEFAULT_NOVELTY_BONUS["feedback"]
    assert guidance.frame_novelty_bonus == DEFAULT_NOVELTY_BONUS["guidance"]
    assert DEFAULT_NOVELTY_BONUS["feedback"] != DEFAULT_NOVELTY_BONUS["guidance"]
    # A recording holds the bonus in force, and replays with it.
    recorded = guidance.to_dict()
    assert recorded["novelty_bonus"] == DEFAULT_NOVELTY_BONUS["guidance"]
    assert LearnerConfig.from_dict(recorded).frame_novelty_bonus == recorded["novelty_bonus"]
    # A given bonus is kept whatever the frame.
    assert replace(LearnerConfig(novelty_bonus=2.5), frame="guidance").frame_novelty_bonus == 2.5
    with pytest.raises(ValueError, match="novelty_bonus"):
        LearnerConfig(novelty_bonus=-1.0)


def test_the_goal_pull_is_a_setting_off_by_default_and_recorded():
    assert LearnerConfig().goal_pull == 0.0
    assert LearnerConfig.from_dict(LearnerConfig(goal_pull=1.5).to_dict()).goal_pull == 1.5
    with pytest.raises(ValueError, match="goal_pull"):
        LearnerConfig(goal_pull=-0.5)


@pytest.mark.parametrize("name", ["resplit_labels", "declare_targets", "power_prior"])
def test_a_switch_setting_that_is_not_true_or_false_is_refused(name):
    # `cfbci simulate --set resplit_labels=yes` gave the string "yes", taken as true.
    with pytest.raises(ValueError, match=f"{name} must be true or false; got 'yes'"):
        LearnerConfig.from_dict({name: "yes"})
    assert getattr(LearnerConfig.from_dict({name: False}), name) is False


def test_the_goal_pull_walks_the_exploring_learner_toward_its_leading_task():
    # Forty random moves answered with well-separated feedback signals for target 24; the
    # learner is not confident yet (beta close to 1) and leads with a task of the far
    # corner. From the two farthest rows, with the pull its planner always moves toward the
    # leading task; without it, it explores elsewhere too.
    world = GridWorld(5)
    rng = np.random.default_rng(3)
    target, state, steps = 24, 12, []
    for _ in range(40):
        action = int(rng.integers(world.n_actions))
        correct = bool(world.optimal[target, state, action])
        signal = rng.normal(size=3) + (0.0 if correct else 4.0)
        steps.append((state, action, signal.astype(np.float32)))
        state = world.step(state, action)

    def first_moves(pull: float) -> tuple[set[tuple[int, int]], set[tuple[int, int]]]:
        moves, toward = set(), set()
        for seed in range(8):
            config = LearnerConfig(
                planner="uncertainty", novelty_bonus=0.0, warmup_steps=0, beta=0.999999,
                goal_pull=pull,
            )
            learner = CalibrationFreeLearner(world, config, rng=seed)
            for step in steps:
                learner.observe(*step)
            beliefs = learner.beliefs()
            assert not beliefs.confident and beliefs.best_task in (18, 19, 23, 24)
            for start in range(10):  # the two rows farthest from it
                action = learner.propose(start).action
                moves.add((start, action))
                if world.optimal[beliefs.best_task, start, action]:
                    toward.add((start, action))
        return moves, toward

    pulled, toward = first_moves(50.0)
    assert pulled == toward
    free, toward = first_moves(0.0)
    assert free != toward


class _CountingFits(CalibrationFreeLearner):
    """The learner, counting the fits of its decoders."""

    n_fits = 0

    def _fit_models(self, cross_validate: bool):
        self.n_fits += 1
        return super()._fit_models(cross_validate)


class _AlwaysPredicting(_CountingFits):
    """The learner as it was: its decoders predict every signal, a target step's too."""

    def _prediction_is_discarded(self, state: int, action: int) -> bool:
        return False


def test_a_target_step_skips_only_the_prediction_it_would_discard():
    learners = [_CountingFits(WORLD, rng=0), _AlwaysPredicting(WORLD, rng=0)]
    traces = []
    for learner in learners:
        trace = []

        def record(step, learner, proposal, beliefs, trace=trace):
            trace.append((proposal, beliefs.log_likelihood, learner.n_fits, learner.n_targets))

        declared = run(learner, target=5, steps=150, seed=3, on_step=record)
        assert len(declared) >= 2, "the session must reach targets for the skip to show"
        traces.append(trace)
    skipping, predicting = traces
    for (proposal, log_likelihood, _, _), (other, other_log_likelihood, _, _) in zip(
        skipping, predicting, strict=True
    ):
        assert proposal == other
        np.testing.assert_array_equal(log_likelihood, other_log_likelihood)
    # Each target step (the one after a declaration) made one fit fewer.
    target_steps = [i for i in range(1, 150) if skipping[i][3] > skipping[i - 1][3]]
    assert len(target_steps) >= 2
    for trace, saved in ((skipping, 1), (predicting, 0)):
        for i in target_steps:
            fits_then = trace[i][2] - trace[i - 1][2]
            assert fits_then == 2 - saved  # (with the proposal's fit after the switch)


def test_the_balanced_accuracy_between_fits_fits_one_task_and_gives_the_same_figure():
    """Asked before the decoders are fitted on the latest signal (the service's state
    message after a declared target), the learner fits that task's fold decoders alone,
    not every task's, and reports what the fitted models report."""
    learner = _CountingFits(WORLD, rng=0)
    rng = np.random.default_rng(4)
    checked = 0
    for step in range(60):
        state = int(rng.integers(WORLD.n_states))
        action = int(rng.integers(WORLD.n_actions))
        learner.observe(state, action, rng.normal(size=6) + (action == 0))
        fits = learner.n_fits
        between = [learner.balanced_accuracy(task) for task in (0, 7, 15)]
        assert learner.n_fits == fits, "no models fitted for the balanced accuracy"
        learner.propose(state)  # fits every task's models (with cross-validation)
        if learner.n_fits == fits:
            continue
        fitted = [learner.balanced_accuracy(task) for task in (0, 7, 15)]
        assert between == pytest.approx(fitted, abs=1e-12)
        checked += step > 20 and None not in fitted
    assert checked > 20
