"""Pairs of task hypotheses that no signal can tell apart (method-extensions.md §7.1)."""

import numpy as np
import pytest

from calibration_free.frames import Frame
from calibration_free.identifiability import confusable_pairs
from calibration_free.world import GridWorld, Transitions, World
from calibration_free.worlds import PickAndPlaceWorld, make_world
from cfbci.cli import main


class MovesOnlyGrid(World):
    """A 3 x 3 grid with the four moves but no goal action; tasks rewarded in their cell
    (any cells, repeated ones included)."""

    name = "moves-only grid"

    def __init__(self, task_states=range(9)) -> None:
        self._tasks = np.array(list(task_states))
        self._next = GridWorld(3).next_state[:, :4]

    action_names = ("up", "down", "left", "right")
    n_states = 9
    guidance_actions = (0, 1, 2, 3)

    @property
    def task_states(self) -> np.ndarray:
        return self._tasks

    @property
    def transitions(self) -> Transitions:
        return Transitions.deterministic(self._next)

    def state_name(self, state: int) -> str:
        return f"cell {state}"

    def declaration_action(self, state: int) -> None:
        return None

    def task_reward(self, task: int) -> np.ndarray:
        reward = np.zeros((9, 4))
        reward[self._tasks[task]] = 1.0
        return reward


@pytest.mark.parametrize("kind", ["feedback", "guidance"])
def test_the_two_action_line_world_confuses_g1_and_g2_and_no_move_clears_it(kind):
    pairs = confusable_pairs(Frame(make_world("line", actions=2), kind))
    assert [(p.task, p.other, p.kind, p.permutation) for p in pairs] == [
        (0, 1, "symmetric", (1, 0))
    ]
    assert confusable_pairs(Frame(make_world("line"), kind)) == []


def test_the_grid_is_identifiable_in_both_frames():
    assert confusable_pairs(Frame(GridWorld(3), "feedback")) == []
    assert confusable_pairs(Frame(GridWorld(4), "guidance")) == []


def test_identical_tasks_are_flagged_with_the_identity():
    pairs = confusable_pairs(Frame(MovesOnlyGrid([0, 4, 4]), "guidance"))
    assert [(p.task, p.other, p.kind) for p in pairs] == [(1, 2, "identical")]
    assert pairs[0].permutation == (0, 1, 2, 3)


def test_pick_and_place_is_identifiable_in_both_frames():
    world = PickAndPlaceWorld()
    assert confusable_pairs(Frame(world, "feedback")) == []
    assert confusable_pairs(Frame(world, "guidance")) == []


def test_world_check_command(capsys):
    assert main(["world", "check", "--world", "line", "--actions", "2"]) == 1
    out = capsys.readouterr().out
    assert "G1 (state 1) / G2 (state 5): symmetric (correct -> error, error -> correct)" in out
    assert "symmetric (right -> left, left -> right)" in out
    assert main(["world", "check", "--world", "line"]) == 0
    assert "feedback frame: clear" in capsys.readouterr().out
    assert main(["world", "check", "--world", "grid", "--actions", "2"]) == 2
