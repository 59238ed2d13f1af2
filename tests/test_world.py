"""The worlds (grid, line, pick-and-place), the interaction frames and value iteration."""

import numpy as np
import pytest

from calibration_free.frames import CORRECT, ERROR, Frame
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.streams import session_streams
from calibration_free.world import (
    ACTIONS,
    GOAL,
    GridWorld,
    Transitions,
    optimal_action_values,
    optimal_actions,
    policy_iteration,
    transition_draws,
    value_iteration,
)
from calibration_free.worlds import PickAndPlaceWorld, make_world

UP, DOWN, LEFT, RIGHT = (ACTIONS.index(a) for a in ("up", "down", "left", "right"))


def test_moves_are_deterministic_and_clamp_at_walls():
    world = GridWorld(5)
    assert world.step(12, UP) == 7 and world.step(12, DOWN) == 17
    assert world.step(12, LEFT) == 11 and world.step(12, RIGHT) == 13
    assert world.step(12, GOAL) == 12
    assert world.step(0, UP) == 0 and world.step(0, LEFT) == 0
    assert world.step(24, DOWN) == 24 and world.step(24, RIGHT) == 24
    assert world.step(4, RIGHT) == 4 and world.step(20, LEFT) == 20


@pytest.mark.parametrize("size", [2, 3, 5, 10])
def test_optimal_actions_reduce_the_distance_and_goal_only_at_the_task(size):
    world = GridWorld(size)
    distance = world.distances()
    for task in range(world.n_tasks):
        for state in range(world.n_states):
            optimal = set(np.flatnonzero(world.optimal[task, state]))
            if state == task:
                assert optimal == {GOAL}
                continue
            expected = {
                a
                for a in range(4)
                if distance[task, world.step(state, a)] == distance[task, state] - 1
            }
            assert optimal == expected and len(optimal) in (1, 2)


def test_value_iteration_recovers_shortest_paths():
    world = GridWorld(5)
    task = 7
    reward = np.full((world.n_states, world.n_actions), -1.0)
    reward[task, GOAL] = 0.0
    # Reaching the goal ends nothing here, so make the task cell absorbing with value 0.
    next_state = world.next_state.copy()
    next_state[task] = task
    reward[task] = np.where(np.arange(world.n_actions) == GOAL, 0.0, -1.0)
    q = value_iteration(
        reward, next_state, discount=0.999999, tolerance=1e-12, max_iterations=10_000
    )
    values = q.max(axis=1)
    assert np.allclose(-values, world.distances()[task], atol=1e-4)
    greedy = q.argmax(axis=1)
    for state in range(world.n_states):
        assert world.optimal[task, state, greedy[state]]


def _value_iteration_testing_every_sweep(reward, transitions, discount, tolerance,
                                         max_iterations, initial_values=None):
    """The textbook loop: stop at the first sweep whose largest change is below tolerance."""
    values = np.zeros(reward.shape[:-1]) if initial_values is None else initial_values
    for _ in range(max_iterations):
        q = reward + discount * transitions.expected(values)
        new_values = q.max(axis=-1)
        if np.max(np.abs(new_values - values)) < tolerance:
            break
        values = new_values
    return q


@pytest.mark.parametrize("case", ["grid", "several MDPs", "stochastic", "capped", "warm"])
def test_value_iteration_in_blocks_equals_testing_after_every_sweep_bit_for_bit(case):
    rng = np.random.default_rng(3)
    transitions = GridWorld(5).transitions
    reward = rng.random((25, 5)) ** 3
    options = {"discount": 0.9, "tolerance": 1e-8, "max_iterations": 1000}
    if case == "several MDPs":
        reward = rng.random((3, 25, 5))
    elif case == "stochastic":
        probabilities = rng.random((25, 5, 3))
        transitions = Transitions(
            rng.integers(0, 25, (25, 5, 3)), probabilities / probabilities.sum(-1, keepdims=True)
        )
    elif case == "capped":  # stops on max_iterations, inside a block
        options["max_iterations"] = 45
    elif case == "warm":
        options.update(tolerance=1e-13, max_iterations=100_000,
                       initial_values=reward.max(axis=-1) / 0.1)
    expected = _value_iteration_testing_every_sweep(reward, transitions, **options)
    assert np.array_equal(value_iteration(reward, transitions, **options), expected)


@pytest.mark.parametrize("stochastic", [False, True])
def test_policy_iteration_is_the_fixed_point_value_iteration_approaches(stochastic):
    """Policy iteration's q satisfies the Bellman equation to rounding, value iteration at
    a tight tolerance lands on it, and the planners' solver uses it on small worlds only."""
    rng = np.random.default_rng(4)
    transitions = GridWorld(5).transitions
    if stochastic:
        probabilities = rng.random((25, 5, 3))
        transitions = Transitions(
            rng.integers(0, 25, (25, 5, 3)), probabilities / probabilities.sum(-1, keepdims=True)
        )
    for _ in range(20):
        reward = rng.random((25, 5)) ** 3
        q = policy_iteration(reward, transitions, discount=0.9)
        bellman = reward + 0.9 * transitions.expected(q.max(axis=1))
        np.testing.assert_allclose(q, bellman, rtol=0, atol=1e-12)
        slow = value_iteration(reward, transitions, discount=0.9, tolerance=1e-14,
                               max_iterations=100_000)
        np.testing.assert_allclose(q, slow, rtol=0, atol=1e-11)
        assert np.array_equal(optimal_action_values(reward, transitions, 0.9), q)
    big = GridWorld(11)  # 121 states: value iteration
    reward = rng.random((121, 5))
    assert np.array_equal(
        optimal_action_values(reward, big.transitions, 0.9),
        value_iteration(reward, big.transitions, discount=0.9),
    )


def test_value_iteration_rejects_a_discount_of_one():
    world = GridWorld(3)
    with pytest.raises(ValueError, match="discount"):
        value_iteration(np.zeros((9, 5)), world.next_state, discount=1.0)
    with pytest.raises(ValueError, match="max_iterations"):
        value_iteration(np.zeros((9, 5)), world.next_state, max_iterations=0)
    with pytest.raises(ValueError, match="discount must be < 1"):
        policy_iteration(np.zeros((9, 5)), world.transitions, discount=1.0)
    with pytest.raises(ValueError, match="max_iterations"):
        policy_iteration(np.zeros((9, 5)), world.transitions, max_iterations=0)


def test_grid_rejects_bad_sizes():
    for bad in (1, 0, 2.5):
        with pytest.raises(ValueError, match="grid size"):
            GridWorld(bad)


def test_feedback_frame_labels_and_expected_distribution():
    frame = Frame(GridWorld(5), "feedback", eps=0.1)
    assert frame.n_classes == 2 and frame.class_names() == ("correct", "error")
    weights, dist = frame.label_weights, frame.label_distribution
    # At the task itself only goal is correct.
    assert weights[12, 12, GOAL, CORRECT] == 1 and weights[12, 12, UP, ERROR] == 1
    # Moving towards the task is correct, away is an error; goal elsewhere is an error.
    assert weights[12, 7, DOWN, CORRECT] == 1 and weights[12, 7, UP, ERROR] == 1
    assert weights[12, 7, GOAL, ERROR] == 1
    assert np.allclose(dist[12, 7, DOWN], [0.9, 0.1]) and np.allclose(dist[12, 7, UP], [0.1, 0.9])
    assert np.allclose(dist.sum(axis=-1), 1.0)


def test_guidance_frame_labels_the_direction_from_the_state():
    frame = Frame(GridWorld(5), "guidance", eps=0.2)
    assert frame.n_classes == 4 and frame.class_names() == ("up", "down", "left", "right")
    w, dist = frame.label_weights, frame.label_distribution
    # Task 0 (top-left) from the centre: up or left, half each, whatever the action.
    for action in range(5):
        assert np.allclose(w[0, 12, action], [0.5, 0, 0.5, 0])
        assert np.allclose(dist[0, 12, action], [0.4, 0.1, 0.4, 0.1])
    # A single optimal direction.
    assert np.allclose(w[2, 12, RIGHT], [1, 0, 0, 0])
    assert np.allclose(dist[2, 12, RIGHT], [0.8, 0.2 / 3, 0.2 / 3, 0.2 / 3])
    # At the task itself no move is optimal: uniform over the four.
    # The expected label is uniform; it trains no decoder (weight 0).
    assert np.allclose(w[12, 12, GOAL], 0.0) and np.allclose(dist[12, 12, UP], 0.25)
    assert np.allclose(dist.sum(axis=-1), 1.0)


def test_frames_reject_bad_settings():
    with pytest.raises(ValueError, match="frame must be one of"):
        Frame(GridWorld(3), "instruction")
    with pytest.raises(ValueError, match="eps"):
        Frame(GridWorld(3), "feedback", eps=0.7)


# --- the world interface, the line and pick-and-place worlds ---------------------------


@pytest.mark.parametrize("size", [2, 3, 5])
def test_the_grid_closed_form_is_what_value_iteration_gives(size):
    world = GridWorld(size)
    reward = np.stack([world.task_reward(t) for t in range(world.n_tasks)])
    assert np.array_equal(optimal_actions(reward, world.transitions, 0.9), world.optimal)
    assert all(world.declares(t, GOAL, t) for t in range(world.n_tasks))
    assert not world.declares(0, GOAL, 1) and not world.declares(0, UP, 0)


def test_large_tables_are_built_on_first_use_only():
    world = GridWorld(50)
    frame = Frame(world, "feedback")
    assert "optimal" not in vars(world) and "_tables" not in vars(frame)
    assert frame.weights_at(0, GOAL).shape == (2500, 2)
    assert "optimal" in vars(world) and frame.row_index.base is world.optimal


def test_a_learner_builds_its_tables_at_its_first_epoch_not_at_its_construction():
    world = GridWorld(50)
    learner = CalibrationFreeLearner(world, rng=0)
    learner.propose(0)  # a warm-up action: no table needed yet
    assert "optimal" not in vars(world) and "_tables" not in vars(learner.frame)
    learner.observe(0, GOAL, np.ones(3, dtype=np.float32))
    assert world.optimal.shape == (2500, 2500, 5) and "_tables" in vars(learner.frame)


def test_line_world_edges_bounce_and_no_move_is_optimal_only_at_the_goal():
    world = make_world("line")
    right, left, stay = (world.action_names.index(a) for a in ("right", "left", "no-move"))
    assert world.n_states == 5 and world.n_tasks == 2 and list(world.task_states) == [0, 4]
    assert world.step(2, right) == 3 and world.step(2, left) == 1 and world.step(2, stay) == 2
    # Into the wall: back to the neighbour with probability 0.5, else stay.
    outcomes = [world.step(4, right, u) for u in (0.1, 0.4, 0.6, 0.9)]
    assert outcomes == [3, 3, 4, 4] and world.step(0, left, 0.2) == 1
    with pytest.raises(ValueError, match="uniform draw"):
        world.step(4, right)
    optimal = world.optimal
    # G1 (state 1): left everywhere but at the goal, where no-move is the unique optimum.
    assert [set(np.flatnonzero(optimal[0, s])) for s in range(5)] == [
        {stay}, {left}, {left}, {left}, {left}
    ]
    assert [set(np.flatnonzero(optimal[1, s])) for s in range(5)] == [
        {right}, {right}, {right}, {right}, {stay}
    ]
    assert world.declares(0, stay, 0) and world.declares(4, stay, 1)
    assert not world.declares(0, left, 0) and not world.declares(2, stay, 0)
    assert world.start_state(np.random.default_rng(0)) == 2


def test_line_world_without_no_move_has_nothing_to_declare_with():
    world = make_world("line", actions=2)
    assert world.action_names == ("right", "left") and world.declaration_action(0) is None
    assert np.array_equal(world.optimal[0, :, 1], np.ones(5, bool))  # G1: always left
    assert np.array_equal(world.optimal[1, :, 0], np.ones(5, bool))
    with pytest.raises(ValueError, match="line world only"):
        make_world("grid", actions=2)


def test_pick_and_place_has_624_states_and_illegal_grasps_and_releases_do_nothing():
    world = PickAndPlaceWorld()
    assert world.n_states == 624 and world.n_tasks == 624 and world.n_actions == 4
    index = {state: i for i, state in enumerate(world.states)}
    grasp, release = world.GRASP, world.RELEASE
    empty_column = next(
        s for s, (holding, column, cubes) in enumerate(world.states)
        if not holding and column not in cubes
    )
    assert world.step(empty_column, grasp) == empty_column  # nothing to grasp
    assert world.step(empty_column, release) == empty_column  # nothing held
    holding = next(
        s for s, (held, column, cubes) in enumerate(world.states)
        if held and column + 4 in cubes
    )
    assert world.step(holding, grasp) == holding  # the hand is full
    assert world.step(holding, release) == holding  # the column is full
    # Grasp takes the top cube; release puts it back where it was.
    stacked = index[(False, 0, (0, 4, 2))]
    taken = world.step(stacked, grasp)
    assert world.states[taken] == (True, 0, (0, 8, 2))
    assert world.step(taken, release) == stacked
    # Move right, then release on the empty column's bottom.
    assert world.states[world.step(world.step(taken, world.RIGHT), release)] == (
        False, 1, (0, 1, 2)
    )
    assert world.step(index[(False, 3, (0, 1, 2))], world.RIGHT) == index[(False, 3, (0, 1, 2))]
    # In its own state, every task's declaration action (the no-op) is optimal.
    optimal = world.optimal
    for task in range(0, world.n_tasks, 7):
        assert optimal[task, task, world.declaration_action(task)]
        assert world.step(task, world.declaration_action(task)) == task
    assert optimal.any(axis=-1).all()
    assert world.state_name(stacked).startswith("robot at column 1, hand empty; cube 1 on")


def test_transition_draws_are_one_per_step_and_reproducible():
    draws, again = transition_draws(7), transition_draws(7)
    assert draws.uniform(3) == again.uniform(3) == draws.uniform(3)
    assert [draws.uniform(k) for k in (1, 2)] == [again.uniform(k) for k in (1, 2)]
    assert draws.uniform(1) != transition_draws(8).uniform(1)
    # The fourth spawned stream of the seed, not one of the data, user or learner streams.
    assert draws.uniform(1) not in [rng.random() for rng in session_streams(7)]
    with pytest.raises(ValueError, match="from 1"):
        draws.uniform(0)


ALL_WORLDS = [GridWorld(3), GridWorld(4), make_world("line"), PickAndPlaceWorld()]


@pytest.mark.parametrize("world", ALL_WORLDS, ids=lambda w: f"{w.name}{w.n_states}")
@pytest.mark.parametrize("kind", ["feedback", "guidance"])
@pytest.mark.parametrize("eps", [0.0, 0.1, 0.5])
def test_label_distributions_sum_to_one_ties_included(world, kind, eps):
    frame = Frame(world, kind, eps)
    dist = frame.label_distribution
    assert dist.shape == (world.n_tasks, world.n_states, world.n_actions, frame.n_classes)
    assert np.allclose(dist.sum(axis=-1), 1.0) and (dist >= 0).all()
    weights = frame.label_weights
    trained = weights.sum(axis=-1)
    assert np.allclose(trained[trained > 0], 1.0)
    if kind == "guidance":
        n_optimal = world.optimal[:, :, list(world.guidance_actions)].sum(axis=-1)
        # Ties: the weight is split evenly over the optimal guidance actions.
        tied = (n_optimal > 1) & (n_optimal < frame.n_classes)
        assert tied.any() or world.name == "line"
        assert np.allclose(weights.max(axis=-1)[tied], 1.0 / n_optimal[tied][:, None])
    for state, action in [(0, 0), (world.n_states - 1, world.n_actions - 1)]:
        assert np.array_equal(frame.weights_at(state, action), weights[:, state, action])
        assert np.array_equal(frame.distribution_at(state, action), dist[:, state, action])


def test_guidance_classes_are_the_worlds_guidance_actions():
    assert Frame(make_world("line"), "guidance").class_names() == ("right", "left", "no-move")
    assert Frame(PickAndPlaceWorld(), "guidance").class_names() == (
        "right", "left", "grasp", "release"
    )
    line = Frame(make_world("line"), "guidance", eps=0.1)
    assert np.allclose(line.distribution_at(0, 1)[0], [0.05, 0.05, 0.9])  # G1 at its goal
    assert np.allclose(line.weights_at(2, 0), [[0, 1, 0], [1, 0, 0]])
