"""The grid world, the interaction frames and value iteration."""

import numpy as np
import pytest

from calibration_free.frames import CORRECT, ERROR, Frame
from calibration_free.world import ACTIONS, GOAL, GridWorld, value_iteration

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


def test_value_iteration_rejects_a_discount_of_one():
    world = GridWorld(3)
    with pytest.raises(ValueError, match="discount"):
        value_iteration(np.zeros((9, 5)), world.next_state, discount=1.0)


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
