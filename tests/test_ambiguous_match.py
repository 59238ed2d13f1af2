"""``ambiguous_match``: what a task expects of a signal whose label allows two directions."""

from __future__ import annotations

import numpy as np
import pytest

from calibration_free.config import SETTINGS_BEFORE_THEY_EXISTED, LearnerConfig
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.likelihood import log_match
from calibration_free.world import GridWorld
from session.config import learner_settings, recorded_config

WORLD = GridWorld(5)
TARGET = 12  # the middle cell: every other cell off its row and column is diagonal to it


def test_the_setting_defaults_to_the_resolved_choice_and_older_recordings_read_it() -> None:
    assert LearnerConfig().ambiguous_match == "resolved"
    assert LearnerConfig(ambiguous_match="even").to_dict()["ambiguous_match"] == "even"
    assert SETTINGS_BEFORE_THEY_EXISTED["ambiguous_match"] == "resolved"
    guidance = LearnerConfig(frame="guidance", ambiguous_match="even")
    older = {k: v for k, v in guidance.to_dict().items()
             if k != "ambiguous_match"}
    replayed = recorded_config({"frame": "guidance", "learner": older})["learner"]
    assert learner_settings(replayed, "guidance").ambiguous_match == "resolved"
    with pytest.raises(ValueError, match="ambiguous_match must be one of"):
        LearnerConfig(ambiguous_match="max")


def _guided_learner(ambiguous_match: str) -> CalibrationFreeLearner:
    """A guidance learner after 60 random moves answered by a user aiming at TARGET with
    well separated signals (class k: 4 standard deviations along axis k)."""
    learner = CalibrationFreeLearner(
        WORLD, LearnerConfig(frame="guidance", ambiguous_match=ambiguous_match), rng=0
    )
    rng = np.random.default_rng(1)
    state = 0
    for _ in range(60):
        action = int(rng.integers(4))
        learner.observe(state, action, _signal(state, rng))
        state = WORLD.step(state, action)
    return learner


def _signal(state: int, rng: np.random.Generator) -> np.ndarray:
    directions = np.flatnonzero(WORLD.optimal[TARGET, state][list(WORLD.guidance_actions)])
    label = int(rng.choice(directions)) if len(directions) else int(rng.integers(4))
    return (rng.normal(size=6) + 4.0 * np.eye(6)[label]).astype(np.float32)


@pytest.mark.parametrize("ambiguous_match", ["even", "resolved"])
def test_a_task_with_two_allowed_directions_matches_the_even_mixture_or_the_resolved_choice(
    ambiguous_match: str,
) -> None:
    learner = _guided_learner(ambiguous_match)
    state, action = 0, 1  # the top-left corner, moving down
    expected = learner.frame.distribution_at(state, action)  # (tasks, K), the even split
    two_allowed = (learner.frame.weights_at(state, action) > 0).sum(axis=1) == 2
    assert two_allowed.sum() >= 8  # every cell off the corner's row and column
    signal = _signal(state, np.random.default_rng(2))
    models = learner._current_models()
    predicted = learner._likelihood.predict(models, signal[None].astype(np.float64))[:, 0]
    before = learner.log_likelihood.copy()
    learner.observe(state, action, signal)
    gained = learner.log_likelihood - before
    even = log_match(expected, predicted)
    if ambiguous_match == "even":
        np.testing.assert_allclose(gained, even, rtol=1e-12, atol=1e-12)
    else:
        # The resolved split weighs the allowed classes by the prediction itself, which
        # matches at least as well as the even split (Cauchy-Schwarz), strictly here.
        assert np.all(gained[two_allowed] >= even[two_allowed] - 1e-12)
        assert np.any(gained[two_allowed] > even[two_allowed] + 1e-3)
        np.testing.assert_allclose(gained[~two_allowed], even[~two_allowed], rtol=1e-12)
