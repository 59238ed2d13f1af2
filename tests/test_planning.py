"""The uncertainty planner's rewards from the frames' compact tables, against the old formula."""

import numpy as np
import pytest

from calibration_free.frames import Frame
from calibration_free.planning import (
    InformationPlanner,
    PlanningInputs,
    UncertaintyPlanner,
    greedy_action,
)
from calibration_free.world import GOAL, GridWorld
from calibration_free.worlds import PickAndPlaceWorld, make_world


def reference_rewards(
    label_distribution: np.ndarray, corrected: np.ndarray, task_weights: np.ndarray
) -> np.ndarray:
    """The planner's reward as it was defined, computed plainly from dense tables.

    For every signal e and (s, a): m_t = sum_l p(l | s, a, t) q_t(e)_l; the reward is the
    task-weighted variance of m_t over tasks, clipped at 0 per signal, summed over signals.
    """
    _, n_states, n_actions, _ = label_distribution.shape
    reward = np.zeros((n_states, n_actions))
    for e in range(corrected.shape[1]):
        m = np.einsum("tsak,tk->tsa", label_distribution, corrected[:, e])
        mean = np.einsum("t,tsa->sa", task_weights, m)
        second = np.einsum("t,tsa->sa", task_weights, m**2)
        reward += np.maximum(second - mean**2, 0.0)
    return reward


WORLDS = [GridWorld(2), GridWorld(3), GridWorld(5), make_world("line"), PickAndPlaceWorld()]


@pytest.mark.parametrize("world", WORLDS, ids=lambda w: f"{w.name}{w.n_states}")
@pytest.mark.parametrize("kind", ["feedback", "guidance"])
@pytest.mark.parametrize("seed", [0, 1])
def test_rewards_equal_the_old_formula(world, kind, seed):
    rng = np.random.default_rng(seed)
    frame = Frame(world, kind, eps=[0.1, 0.02][seed])
    corrected = rng.dirichlet(np.ones(frame.n_classes), size=(world.n_tasks, 20))
    weights = rng.dirichlet(np.full(world.n_tasks, 0.3))
    if seed == 1:  # most of the weight on a few tasks, as late in a search
        weights = weights**4 / np.sum(weights**4)
    expected = reference_rewards(frame.label_distribution, corrected, weights)
    rewards = UncertaintyPlanner(frame).rewards(corrected, weights)
    assert rewards.shape == (world.n_states, world.n_actions)
    assert np.ptp(expected) > 1e-9  # the rewards differ between state-actions
    # Absolute: each reward is a sum over 20 signals of variances of numbers in [0, 1].
    np.testing.assert_allclose(rewards, expected, rtol=1e-9, atol=1e-13)


@pytest.mark.parametrize("kind", ["feedback", "guidance"])
def test_rewards_are_the_same_with_indicators_kept_or_built_in_chunks(kind, monkeypatch):
    """Small tables keep their row indicators between steps; large ones build them a chunk
    at a time at every step. Both give the old formula's rewards, step after step."""
    import calibration_free.planning as planning

    rng = np.random.default_rng(3)
    frame = Frame(GridWorld(5), kind, eps=0.1)
    steps = [
        (rng.dirichlet(np.ones(frame.n_classes), size=(25, 20)), rng.dirichlet(np.full(25, 0.3)))
        for _ in range(3)
    ]
    kept, chunked = UncertaintyPlanner(frame), UncertaintyPlanner(frame)
    from_kept = [kept.rewards(*step) for step in steps]
    monkeypatch.setattr(planning, "KEPT_INDICATOR_BYTES", 0)
    monkeypatch.setattr(planning, "_CHUNK_ELEMENTS", 25 * 7)  # chunks of 7 columns
    from_chunks = [chunked.rewards(*step) for step in steps]
    assert kept._kept_indicators is not None and chunked._kept_indicators is None
    for (corrected, weights), one, other in zip(steps, from_kept, from_chunks, strict=True):
        expected = reference_rewards(frame.label_distribution, corrected, weights)
        np.testing.assert_allclose(one, expected, rtol=1e-9, atol=1e-13)
        np.testing.assert_allclose(other, expected, rtol=1e-9, atol=1e-13)


def reference_information(
    label_distribution: np.ndarray, corrected: np.ndarray, task_weights: np.ndarray
) -> np.ndarray:
    """Mutual information between the task and the next signal, plainly: for every (s, a),
    ``p(e | t)`` = ``m_t(s, a, e)`` normalised over the sampled signals, and ``sum_t w_t
    KL(p(. | t) || sum_u w_u p(. | u))``."""
    m = np.einsum("tsak,tek->saet", label_distribution, corrected)
    p = m / m.sum(axis=2, keepdims=True)
    mixture = np.einsum("saet,t->sae", p, task_weights)
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(p > 0, p * np.log(p / mixture[..., None]), 0.0)
    return np.einsum("saet,t->sa", terms, task_weights)


@pytest.mark.parametrize("world", WORLDS[:4], ids=lambda w: f"{w.name}{w.n_states}")
@pytest.mark.parametrize("kind", ["feedback", "guidance"])
def test_information_rewards_equal_the_mutual_information(world, kind):
    rng = np.random.default_rng(5)
    frame = Frame(world, kind, eps=0.05)
    corrected = rng.dirichlet(np.ones(frame.n_classes), size=(world.n_tasks, 20))
    weights = rng.dirichlet(np.full(world.n_tasks, 0.3))
    expected = reference_information(frame.label_distribution, corrected, weights)
    rewards = InformationPlanner(frame).rewards(corrected, weights)
    assert np.ptp(expected) > 1e-6
    np.testing.assert_allclose(rewards, expected, rtol=1e-9, atol=1e-12)


def test_an_uninformative_decoder_gives_no_information():
    world = GridWorld(3)
    frame = Frame(world, "feedback", eps=0.1)
    corrected = np.full((world.n_tasks, 20, 2), 0.5)  # every signal looks the same
    rewards = InformationPlanner(frame).rewards(corrected, np.full(world.n_tasks, 1 / 9))
    np.testing.assert_allclose(rewards, 0.0, atol=1e-12)


def test_the_planner_walks_where_the_hypotheses_disagree():
    # Two tasks left and right of the start, one decoder: an action both tasks label alike
    # is worth nothing, one they label differently is worth the most.
    world = make_world("line")
    frame = Frame(world, "feedback", eps=0.0)
    corrected = np.tile([0.9, 0.1], (2, 5, 1))
    rewards = UncertaintyPlanner(frame).rewards(corrected, np.array([0.5, 0.5]))
    no_move = world.action_names.index("no-move")
    # No-move in the middle is wrong for both tasks: no information.
    assert rewards[2, no_move] == pytest.approx(0.0, abs=1e-12)
    assert rewards[2, 0] == pytest.approx(5 * 0.8**2 / 4)  # 5 signals, m = 0.9 or 0.1
    assert rewards[0, no_move] == pytest.approx(rewards[2, 0])


def test_greedy_action_declares_in_the_tasks_state():
    grid = GridWorld(3)
    assert greedy_action(grid, 4, 4, np.random.default_rng(0)) == GOAL
    line = make_world("line")
    assert greedy_action(line, 0, 0, np.random.default_rng(0)) == line.NO_MOVE
    assert greedy_action(line, 2, 0, np.random.default_rng(0)) == line.LEFT
    place = PickAndPlaceWorld()
    assert greedy_action(place, 5, 5, np.random.default_rng(0)) == place.declaration_action(5)


def test_a_state_bonus_on_the_likely_goal_draws_the_agent_to_it():
    # Every task's decoder says the same of every signal: the uncertainty reward is 0
    # everywhere, so the action is a tie among all five unless a state bonus (the learner's
    # goal pull) marks the likely goal, cell 24: then every choice moves toward it.
    world = GridWorld(5)
    frame = Frame(world, "feedback", eps=0.1)
    planner = UncertaintyPlanner(frame, discount=0.95)
    weights = np.full(world.n_tasks, 1 / world.n_tasks)
    corrected = np.full((world.n_tasks, 20, 2), 0.5)
    pull = np.zeros(world.n_states)
    pull[24] = 1.0

    def actions(bonus):
        inputs = PlanningInputs(0, weights, bonus, lambda: corrected, lambda: None)
        return {planner.action(0, inputs, np.random.default_rng(seed)) for seed in range(40)}

    toward = set(np.flatnonzero(world.optimal[24, 0]))
    assert actions(pull) <= toward
    assert not actions(None) <= toward  # without it, any action
