"""The puddle world (method-extensions §2): tasks, mixed frame, kernel map, a session."""

from __future__ import annotations

import numpy as np
import pytest

from calibration_free.puddle import MIXED_LABELS, PuddleWorld, mixed_frame, puddle_tasks
from calibration_free.puddle_learner import PuddleConfig, kernel_map
from cfbci.offline.puddle import run_puddle_session


@pytest.fixture(scope="module")
def world() -> PuddleWorld:
    return PuddleWorld()


def test_there_are_660_tasks_and_no_goal_lies_in_its_puddle() -> None:
    tasks = puddle_tasks()
    assert len(tasks) == 660 == len(set(tasks))
    assert all(task.goal not in task.puddle for task in tasks)
    assert len({task.puddle for task in tasks}) == 30


def test_policies_lead_to_the_goal_around_the_puddle(world: PuddleWorld) -> None:
    # Goal in the top-left cell, puddle across the middle row's left three cells: just
    # below the puddle the way north is blocked, so the only optimal move is east; one move
    # below the goal, north is the only optimal move.
    task = next(
        t for t, x in enumerate(world.tasks) if x.goal == 20 and x.puddle == (10, 11, 12)
    )
    optimal = world.optimal_at(np.array([[0.05, 0.35], [0.05, 0.75]]))[task]
    assert optimal[0].tolist() == [False, False, True, False]  # east, not into the puddle
    assert optimal[1].tolist() == [True, False, False, False]  # north, into the goal cell


def test_the_mixed_frame_sums_to_one_and_reduces_to_its_parts(world: PuddleWorld) -> None:
    rng = np.random.default_rng(0)
    states = rng.uniform(size=(40, 2))
    actions = rng.integers(4, size=40)
    optimal = world.optimal_at(states)
    frame = mixed_frame(optimal, actions, 0.5, 0.1)
    assert frame.shape == (660, 40, len(MIXED_LABELS))
    assert np.allclose(frame.sum(axis=2), 1.0)
    feedback_only = mixed_frame(optimal, actions, 1.0, 0.1)
    assert np.all(feedback_only[..., 2:] == 0.0)
    taken = np.take_along_axis(optimal, actions[None, :, None], axis=2)[..., 0]
    assert np.allclose(feedback_only[..., 0], np.where(taken, 0.9, 0.1))
    guidance_only = mixed_frame(optimal, actions, 0.0, 0.1)
    assert np.all(guidance_only[..., :2] == 0.0)
    assert np.allclose(guidance_only.sum(axis=2), 1.0)
    # Where every direction is optimal (ties everywhere) guidance is uniform.
    everything = np.ones((1, 1, 4), dtype=bool)
    assert mixed_frame(everything, np.array([0]), 0.0, 0.1)[0, 0, 2:] == pytest.approx([0.25] * 4)


def test_a_kernel_bump_has_its_height_at_its_centre() -> None:
    sample = np.array([[0.3, 0.6]])
    points = np.array([[0.3, 0.6], [0.4, 0.6], [0.3, 0.5]])
    assert kernel_map(points, sample, np.array([1.0]), 0.01) == pytest.approx(
        [1.0, np.exp(-0.5), np.exp(-0.5)]
    )


def test_uncertainty_planning_identifies_the_taught_task(world: PuddleWorld) -> None:
    # Seed 0, 525 steps: the taught task ends dominant (a learner that ignored the signals
    # would stay near 1/660).
    result = run_puddle_session(0, PuddleConfig(exploration="planning"), world, steps=525)
    assert len(result.taught_likelihood) == 35
    assert result.taught_likelihood[-1] > 0.9
    assert result.taught_likelihood[0] < 0.1
