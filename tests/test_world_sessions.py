"""Closed-loop sessions in the line and pick-and-place worlds (``SessionConfig.world``)."""

import numpy as np
import pytest

from acquisition.labelled import LabelledFeatures
from acquisition.user import SimulatedUser
from calibration_free.config import LearnerConfig
from calibration_free.world import transition_draws
from calibration_free.worlds import make_world
from cfbci.offline.simulation import SessionConfig, run_session


def separated(n_classes: int, n_per_class: int = 150, seed: int = 0) -> LabelledFeatures:
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(n_classes), n_per_class)
    features = rng.normal(size=(len(labels), 5)) + 3.0 * np.eye(n_classes, 5)[labels]
    return LabelledFeatures(features, labels, n_classes, "separated")


@pytest.mark.parametrize("frame", ["feedback", "guidance"])
def test_line_world_sessions_are_reproducible_declare_with_no_move_and_follow_the_edges(frame):
    config = SessionConfig(steps=120, world="line", learner=LearnerConfig(frame=frame))
    data = separated(2 if frame == "feedback" else 3)
    trace, again = [], []
    result = run_session(4, config, data, trace.append)
    run_session(4, config, data, again.append)
    assert trace == again and trace[0].state == 2  # the middle
    assert result.correct_targets >= 3 and result.wrong_targets == 0
    world, draws = make_world("line"), transition_draws(4)
    for record in trace:
        action = world.action_names.index(record.action)
        assert record.next_state == world.step(record.state, action, draws.uniform(record.step))
        if record.event is not None:
            assert record.action == "no-move" and record.state in (0, 4)
    # The edges were pushed against, and bounced back at least once.
    pushes = [r for r in trace if (r.state, r.action) in ((0, "left"), (4, "right"))]
    assert any(r.next_state != r.state for r in pushes)


def test_a_pick_and_place_session_declares_with_the_no_op_in_the_tasks_state():
    config = SessionConfig(steps=60, world="pick-and-place")
    trace = []
    run_session(1, config, separated(2), trace.append)
    world = make_world("pick-and-place")
    assert all(r.next_state == world.step(r.state, world.action_names.index(r.action))
               for r in trace)
    declared = [r for r in trace if r.event in ("correct_target", "wrong_target")]
    for record in declared:
        assert world.action_names.index(record.action) == world.declaration_action(record.state)
        assert record.next_state == record.state


def test_the_line_user_answers_in_the_worlds_classes_and_starts_in_the_middle():
    world = make_world("line")
    rng = np.random.default_rng(0)
    user = SimulatedUser(world, "guidance", np.repeat(np.arange(3), 4), rng)
    assert user.start_state == 2 and user.target in (0, 1)
    user.target = 0  # G1: left, and no-move at state 1
    assert {user.answer(2, 0)[1] for _ in range(10)} == {world.LEFT}
    assert {user.answer(0, 1)[1] for _ in range(10)} == {world.NO_MOVE}
    assert user.new_target() == 1


def test_an_unknown_world_is_an_error():
    with pytest.raises(ValueError, match="world must be one of"):
        SessionConfig(world="torus")
