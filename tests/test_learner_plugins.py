"""The learner's plug-ins: likelihoods, confidence rules, decoders and planners
(method-extensions §1, §5, §6.3, §7.3), driven through the real learner where they can be."""

from __future__ import annotations

from functools import cached_property

import numpy as np
import pytest
from test_learner import WORLD as GRID
from test_learner import run as drive

from calibration_free.config import LearnerConfig
from calibration_free.frames import Frame
from calibration_free.learner import CalibrationFreeLearner, first_target_requirement
from calibration_free.likelihood import normalised_likelihood, pairwise_confidence
from calibration_free.planning import SignalPlanner
from calibration_free.task_decoders import TaskHistory, TaskModels
from calibration_free.task_likelihoods import BHATTACHARYYA_THRESHOLD, TaskLikelihood
from calibration_free.world import GOAL, GridWorld, Transitions, World
from calibration_free.worlds import LineWorld
from decoding.statistics import BatchedDecoders

BUTTONS = np.eye(2, dtype=np.float32)  # B = [1, 0], O = [0, 1]


# --- likelihoods -------------------------------------------------------------------------


@pytest.mark.parametrize("likelihood", ["matching", "simple", "batch", "bhattacharyya"])
@pytest.mark.parametrize("target", [5, 10])
def test_each_likelihood_ranks_the_true_task_first_on_separable_signals(likelihood, target):
    config = LearnerConfig(likelihood=likelihood, planner="random")
    learner = CalibrationFreeLearner(GRID, config, rng=target)
    first_confident = []

    def check(step, learner, proposal, beliefs):
        if beliefs.confident and not first_confident:
            first_confident.append(beliefs)

    declared = drive(learner, target, steps=150, seed=target, start=15 - target, on_step=check)
    assert first_confident, f"{likelihood} never became confident"
    beliefs = first_confident[0]
    assert beliefs.best_task == target
    assert np.argmax(beliefs.normalised_likelihood()) == target
    assert declared and set(declared) == {target}


def test_batch_matching_recomputes_the_segment_with_the_latest_decoders():
    """Each step's batch log-likelihood is the sum over the segment of the matches with
    the decoders fitted on the whole history, not a running sum of earlier matches."""
    config = LearnerConfig(likelihood="batch", planner="random", decoder="gaussian")
    learner = CalibrationFreeLearner(GRID, config, rng=3)
    totals = []
    drive(learner, 6, steps=30, seed=3,
          on_step=lambda *_: totals.append(learner.log_likelihood.copy()))
    changes = np.diff(np.array(totals), axis=0)
    # A filter only ever adds log(match) <= 0; a batch recomputation also rises when the
    # newest decoders explain the earlier signals better.
    assert np.any(changes > 1e-6)


class FirstClassDecoders(BatchedDecoders):
    """The §7.4 degenerate decoder: ``[1, 0]`` for every signal, whatever it is."""

    def __init__(self, batch_shape: tuple[int, ...]) -> None:
        self.present = np.ones((*batch_shape, 2), dtype=bool)

    def _known_log_proba(self, X: np.ndarray) -> np.ndarray:
        shape = np.broadcast_shapes((*self.present.shape[:-1], 1), X.shape[:-1])  # (*B, n)
        log_proba = np.zeros((*shape, 2))
        log_proba[..., 1] = -np.inf
        return log_proba


def test_simple_matching_commits_wrongly_where_matching_learns_nothing():
    """§7.4: a decoder that always answers ``[1, 0]``. Its cross-validated confusion
    (no smoothing) has the column [0.5, 0.5] for the class it predicts, so the corrected
    prediction is uniform and every task gets the same update (no information); simple
    matching believes the decoder and commits to the task that calls the most visited
    actions correct: the walk's top cell, where ``goal`` is tried, while the user's is at the
    bottom."""
    frame = Frame(GRID, "feedback", eps=0.1)
    rng = np.random.default_rng(0)
    history = TaskHistory(GRID.n_tasks, 2, 3)
    matching, simple = TaskLikelihood(GRID.n_tasks), TaskLikelihood(GRID.n_tasks, corrected=False)
    state = 12  # bottom-left: the walk goes up to the top-left corner, tries goal, and back
    up, down = 0, 1
    for step in range(68):
        action = (up, up, up, GOAL, down, down, down)[step % 7]
        expected = frame.distribution_at(state, action)
        if step >= 12:
            assert np.all(history.label_weights.sum(axis=1) > 0)  # both classes, every task
            n_labellings = len(history.labellings[1])
            models = TaskModels.cross_validated(
                history, FirstClassDecoders((n_labellings,)),
                FirstClassDecoders((history.n_folds, n_labellings)), smoothing=0.0,
            )
            signal = rng.normal(size=(1, 3))
            np.testing.assert_allclose(models.confusion[:, :, 0], 0.5)
            corrected = models.corrected_proba(signal)[:, 0]
            np.testing.assert_allclose(corrected, 0.5)
            matching.take(expected, corrected)
            simple.take(expected, models.proba(signal)[:, 0])
        history.add(rng.normal(size=3), frame.weights_at(state, action))
        state = GRID.step(state, action)
    np.testing.assert_allclose(matching.log_likelihood, matching.log_likelihood[0])
    assert pairwise_confidence(matching.log_likelihood).max() == pytest.approx(0.5)
    best = int(np.argmax(simple.log_likelihood))
    assert pairwise_confidence(simple.log_likelihood)[best] > 0.9
    assert best == 0  # the top-left corner, not the user's cell (the bottom row)


def run_through_a_first_phase(config, first_name, threshold, seed, steps, check_first_phase):
    """Drive a learner toward task 9 and check its phases: ``first_name`` up to the first
    declared target (confident at a normalised likelihood above ``threshold``, every
    step's beliefs also checked by ``check_first_phase(step, learner, beliefs)``), the
    matching filter with the configured pairwise rule after it. Returns the learner and
    the first target's step."""
    learner = CalibrationFreeLearner(GRID, config, rng=seed)
    phases, declared_at = [], []

    def check(step, learner, proposal, beliefs):
        phases.append(learner.likelihood_in_use)
        if learner.likelihood_in_use == first_name:
            normalised = normalised_likelihood(beliefs.scores)
            assert (beliefs.rule, beliefs.threshold) == ("normalised", threshold)
            required = first_target_requirement(threshold, learner.n_signals, 90)
            assert beliefs.required == required  # stricter while the history is short
            assert beliefs.confident == (normalised.max() > required)
            np.testing.assert_allclose(beliefs.confidence, normalised)
            check_first_phase(step, learner, beliefs)
        elif beliefs.rule == "pairwise":
            pairwise = pairwise_confidence(beliefs.scores)
            np.testing.assert_allclose(beliefs.confidence, pairwise)
            assert beliefs.confident == (pairwise[beliefs.best_task] > config.frame_beta)
        if proposal.declares_target:
            declared_at.append(step)

    declared = drive(learner, 9, steps=steps, seed=seed, on_step=check)
    assert declared and set(declared) == {9} and len(declared) >= 2
    first = declared_at[0]
    assert set(phases[: first + 1]) == {first_name}
    assert set(phases[first + 1 :]) == {"matching"}
    return learner, first


def test_bhattacharyya_decides_at_0_99_then_switches_to_matching_at_the_first_target():
    config = LearnerConfig(likelihood="bhattacharyya", planner="random", beta=0.9)
    previous = [np.zeros(GRID.n_tasks)]

    def non_increasing(step, learner, beliefs):
        if step <= 3:  # a class of fewer than two signals somewhere: the steps add nothing
            np.testing.assert_array_equal(beliefs.log_likelihood, 0.0)
        assert np.all(beliefs.log_likelihood <= previous[0] + 1e-12)
        previous[0] = beliefs.log_likelihood

    learner, first = run_through_a_first_phase(
        config, "bhattacharyya", BHATTACHARYYA_THRESHOLD, 1, 200, non_increasing
    )
    # The switch relabelled the history: every task holds the declared task's labels of
    # the signals up to the target.
    weights = learner.history.label_weights[:, : first + 1]
    np.testing.assert_array_equal(weights, np.broadcast_to(weights[9], weights.shape))


def test_bhattacharyya_needs_the_feedback_frame():
    with pytest.raises(ValueError, match="needs frame 'feedback'"):
        LearnerConfig(likelihood="bhattacharyya", frame="guidance")
    with pytest.raises(ValueError, match="likelihood must be one of"):
        LearnerConfig(likelihood="overlap")
    with pytest.raises(ValueError, match="confidence must be one of"):
        LearnerConfig(confidence="entropy")


# --- confidence rules ---------------------------------------------------------------------


def test_normalised_confidence_compares_the_normalised_likelihood_with_beta():
    config = LearnerConfig(confidence="normalised", beta=0.95, planner="random")
    learner = CalibrationFreeLearner(GRID, config, rng=2)
    seen = {"confident": 0, "unsure": 0}

    def check(step, learner, proposal, beliefs):
        normalised = normalised_likelihood(beliefs.scores)
        np.testing.assert_allclose(beliefs.confidence, normalised)
        assert normalised.sum() == pytest.approx(1.0)
        required = beliefs.threshold  # after a target: 0.95, or calibrated_beta
        if not learner.n_targets:
            assert beliefs.threshold == 0.95
            required = first_target_requirement(0.95, learner.n_signals, 90)
        assert beliefs.required == required
        assert beliefs.confident == (normalised[beliefs.best_task] > required)
        seen["confident" if beliefs.confident else "unsure"] += 1
        np.testing.assert_allclose(
            learner.normalised_likelihood(), normalised_likelihood(beliefs.log_likelihood)
        )

    declared = drive(learner, 3, steps=120, seed=2, on_step=check)
    assert seen["confident"] > 0 and seen["unsure"] > 0
    assert declared and declared[0] == 3


def test_the_normalised_likelihood_has_no_power_prior_and_restarts_at_a_target():
    learner = CalibrationFreeLearner(GRID, LearnerConfig(planner="random"), rng=4)
    declared_at, after_targets = [], []

    def check(step, learner, proposal, beliefs):
        if declared_at and declared_at[-1] == step - 1:
            after_targets.append(learner.normalised_likelihood())
        if proposal.declares_target:
            declared_at.append(step)

    drive(learner, 14, steps=200, seed=4, on_step=check)
    beliefs = learner.beliefs()
    assert not np.allclose(beliefs.scores, beliefs.log_likelihood)  # the prior is on
    expected = np.exp(beliefs.log_likelihood - beliefs.log_likelihood.max())
    np.testing.assert_allclose(learner.normalised_likelihood(), expected / expected.sum())
    assert after_targets
    np.testing.assert_allclose(after_targets, 1 / GRID.n_tasks)


# --- decoders -----------------------------------------------------------------------------


@pytest.mark.parametrize("decoder", ["lda", "student_t", "gaussian"])
def test_each_decoder_finds_the_target(decoder):
    learner = CalibrationFreeLearner(GRID, LearnerConfig(decoder=decoder), rng=6)
    declared = drive(learner, 6, steps=150, seed=6, start=11)
    assert declared and declared[0] == 6


def test_the_categorical_decoder_finds_the_target_from_button_presses():
    """A consistent teacher pressing B for correct and O for wrong (the mapping unknown)."""
    config = LearnerConfig(decoder="categorical", likelihood="simple", eps=0.1)
    learner = CalibrationFreeLearner(GRID, config, rng=7)
    declared = drive(learner, 13, steps=150, seed=7, signal=lambda label, rng: BUTTONS[label])
    assert declared and set(declared) == {13}


# --- the proof's worked example (§5) -------------------------------------------------------


class TableWorld(World):
    """A hand-built symbolic world: ``n_states`` states, 2 actions that keep the state,
    one task per row of ``correct`` (n_tasks, n_states, 2), which says which state-action
    pairs the task calls correct; no declaration."""

    name = "table"

    def __init__(self, correct: np.ndarray) -> None:
        self._correct = np.asarray(correct, dtype=bool)

    @property
    def action_names(self) -> tuple[str, ...]:
        return ("a", "b")

    @property
    def n_states(self) -> int:
        return self._correct.shape[1]

    @cached_property
    def task_states(self) -> np.ndarray:
        return np.zeros(len(self._correct), dtype=int)

    @cached_property
    def transitions(self) -> Transitions:
        stay = np.repeat(np.arange(self.n_states)[:, None], 2, axis=1)
        return Transitions.deterministic(stay)

    @property
    def guidance_actions(self) -> tuple[int, ...]:
        return (0, 1)

    def state_name(self, state: int) -> str:
        return f"s{state}"

    def declaration_action(self, state: int) -> int | None:
        return None

    def _optimal_table(self) -> np.ndarray:
        return self._correct.copy()


PROOF_CONFIG = LearnerConfig(
    decoder="categorical", likelihood="batch", eps=0.0, power_prior=False, planner="random"
)


def visit_once(world: TableWorld, presses: list[int]) -> CalibrationFreeLearner:
    """Every (state, action) visited once, in order, answered with ``presses``."""
    learner = CalibrationFreeLearner(world, PROOF_CONFIG, rng=0)
    pairs = [(s, a) for s in range(world.n_states) for a in range(2)]
    for (state, action), press in zip(pairs, presses, strict=True):
        learner.observe(state, action, BUTTONS[press])
    return learner


def test_the_proofs_worked_example():
    """Four visited pairs, presses [B, O, O, B]; G1 expects [C, W, W, C], G2 [W, C, W, C]:
    L(G1) = 1, L(G2) = 0.5^4 = 0.0625, normalised 0.94 and 0.06."""
    correct = np.array([[[1, 0], [0, 1]], [[0, 1], [0, 1]]])  # G1, G2 over (s0a, s0b, s1a, s1b)
    learner = visit_once(TableWorld(correct), presses=[0, 1, 1, 0])
    np.testing.assert_allclose(np.exp(learner.log_likelihood), [1.0, 0.0625], rtol=1e-12)
    np.testing.assert_allclose(learner.normalised_likelihood(), [1 / 1.0625, 0.0625 / 1.0625])
    assert learner.normalised_likelihood()[0] == pytest.approx(0.94, abs=0.005)


def test_the_closed_form_equals_the_learner_on_a_half_half_world():
    """§5: with every pair visited once, ``L = U^(n U) (1 - U)^(n (1 - U))`` for a
    hypothesis agreeing with the truth on a fraction U of the n pairs; the symmetric one
    (U = 0) is exactly as likely as the truth."""
    n_states, half = 5, 5  # 10 pairs, 5 correct under every hypothesis
    truth = np.arange(2 * n_states) < half  # pairs 0-4 correct
    agreements = [5, 4, 3, 2, 0]  # correct pairs shared with the truth
    tables = []
    for shared in agreements:
        pairs = np.zeros(2 * n_states, dtype=bool)
        pairs[:shared] = True  # correct for both
        pairs[half : half + half - shared] = True  # correct here, wrong for the truth
        tables.append(pairs.reshape(n_states, 2))
    world = TableWorld(np.array(tables))
    learner = visit_once(world, presses=[0 if c else 1 for c in truth])
    upsilon = np.array([(2 * s) / (2 * n_states) for s in agreements])
    n = 2 * n_states
    with np.errstate(divide="ignore", invalid="ignore"):
        closed = np.nan_to_num(upsilon ** (n * upsilon)) * np.nan_to_num(
            (1 - upsilon) ** (n * (1 - upsilon))
        )
    closed[upsilon == 0] = 1.0
    closed[upsilon == 1] = 1.0
    np.testing.assert_allclose(np.exp(learner.log_likelihood), closed, rtol=1e-12)
    assert learner.log_likelihood[-1] == pytest.approx(learner.log_likelihood[0])  # symmetric
    assert np.all(np.diff(learner.log_likelihood[:4]) < 0)  # falls as U nears 0.5


# --- planners -----------------------------------------------------------------------------


def reference_signal_map(frame: Frame, means: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``1/2 sum_ij w_i w_j ||mu_i(s, a) - mu_j(s, a)||^2``, with the frame's most probable
    labels, by brute force."""
    labels = np.argmax(frame.label_distribution, axis=-1)  # (T, S, A)
    expected = means[np.arange(len(means))[:, None, None], labels]  # (T, S, A, d)
    gaps = expected[:, None] - expected[None, :]
    return 0.5 * np.einsum("i,j,ijsad->sa", weights, weights, gaps**2)


@pytest.mark.parametrize(
    ("world", "kind"),
    [(GridWorld(3), "feedback"), (GridWorld(3), "guidance"), (LineWorld(), "feedback")],
    ids=["grid-feedback", "grid-guidance", "line-feedback"],
)
def test_the_signal_planner_map(world, kind):
    frame = Frame(world, kind)
    rng = np.random.default_rng(0)
    means = rng.normal(size=(world.n_tasks, frame.n_classes, 3))
    weights = rng.dirichlet(np.ones(world.n_tasks))
    planner = SignalPlanner(frame)
    rewards = planner.rewards(means, weights)
    assert rewards.shape == (world.n_states, world.n_actions)
    assert np.all(rewards >= 0) and rewards.max() > 0
    np.testing.assert_allclose(rewards, reference_signal_map(frame, means, weights), atol=1e-12)
    one = np.zeros(world.n_tasks)
    one[1] = 1.0
    np.testing.assert_allclose(planner.rewards(means, one), 0.0, atol=1e-12)


@pytest.mark.parametrize(("epsilon", "rate"), [(0.0, 0.0), (0.3, 0.18), (1.0, 0.6)])
def test_epsilon_greedy_takes_a_random_action_at_rate_epsilon(epsilon, rate):
    """From the centre of the 5 x 5 grid towards the top-left corner (the most likely task
    of a learner that knows nothing), 2 of the 5 actions are optimal: a uniform action is
    non-optimal with probability 3/5, so non-optimal actions come at ``epsilon * 3 / 5``."""
    world = GridWorld(5)
    config = LearnerConfig(planner="epsilon-greedy", epsilon=epsilon, warmup_steps=0)
    learner = CalibrationFreeLearner(world, config, rng=11)
    assert not learner.beliefs().confident and learner.beliefs().best_task == 0
    actions = np.array([learner.propose(12).action for _ in range(4000)])
    non_optimal = ~world.optimal[0, 12, actions]
    margin = 4 * np.sqrt(max(rate * (1 - rate), 1e-9) / len(actions))
    assert abs(non_optimal.mean() - rate) <= margin
    assert GOAL not in actions[~non_optimal]
