"""A config's ``learner`` object: each setting takes the JSON kinds its annotation allows."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_learner import WORLD, run

from calibration_free.config import (
    DEFAULT_BETA,
    DEFAULT_FIRST_TARGET_SHRINKAGE,
    DEFAULT_NOVELTY_BONUS,
    LearnerConfig,
)
from calibration_free.learner import CalibrationFreeLearner
from session.config import learner_settings


def test_every_setting_written_by_to_dict_is_read_back() -> None:
    for config in (LearnerConfig(), LearnerConfig(frame="guidance", shrinkage="oas")):
        values = config.to_dict()
        read = learner_settings(values, config.frame)
        assert read.to_dict() == values


def test_a_string_shrinkage_and_a_null_novelty_bonus_are_settings() -> None:
    config = learner_settings({"shrinkage": "oas", "novelty_bonus": None}, "guidance")
    assert config.shrinkage == "oas"
    assert config.frame_novelty_bonus == DEFAULT_NOVELTY_BONUS["guidance"]
    assert learner_settings({"shrinkage": 1, "eps": 0}, "feedback").shrinkage == 1


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"shrinkage": [0.5]}, "'shrinkage' must be a number or a string or null; got [0.5]"),
        ({"shrinkage": True}, "'shrinkage' must be a number or a string or null; got True"),
        ({"novelty_bonus": "1"}, "'novelty_bonus' must be a number or null; got '1'"),
        ({"first_target_shrinkage": [0.9]},
         "'first_target_shrinkage' must be a number or a string or null; got [0.9]"),
        ({"first_target_shrinkage": "ledoit"}, "first_target_shrinkage"),  # not a rule
        ({"eps": None}, "'eps' must be a number; got None"),
        ({"n_folds": 2.0}, "'n_folds' must be an integer; got 2.0"),
        ({"power_prior": 1}, "'power_prior' must be a boolean; got 1"),
        ({"calibrated_evidence": "yes"},
         "'calibrated_evidence' must be a boolean or null; got 'yes'"),
        ({"planner": 3}, "'planner' must be a string; got 3"),
        ({"shrinkage": "ledoit"}, "shrinkage"),  # a string, but not a rule
        ({"bogus": 1}, "unknown learner setting"),
    ],
)
def test_a_wrong_kind_is_refused_naming_the_setting(values: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        learner_settings(values, "feedback")


def test_the_first_target_shrinkage_is_the_frames_and_is_recorded_resolved() -> None:
    feedback, guidance = LearnerConfig(), LearnerConfig(frame="guidance", shrinkage=0.3)
    assert feedback.shrinkage_before_first_target == "cv"  # chosen where it can be
    fixed = LearnerConfig(decoder="gaussian").shrinkage_before_first_target
    assert fixed == DEFAULT_FIRST_TARGET_SHRINKAGE["feedback"]
    assert guidance.shrinkage_before_first_target == 0.3  # guidance: shrinkage throughout
    assert LearnerConfig(first_target_shrinkage=0.7).shrinkage_before_first_target == 0.7
    # Without declarations there is no first target: one shrinkage, unless one is given.
    silent = LearnerConfig(declare_targets=False, shrinkage=0.4)
    assert silent.shrinkage_before_first_target == 0.4
    assert silent.to_dict()["first_target_shrinkage"] == 0.4
    assert replace(silent, first_target_shrinkage=0.9).shrinkage_before_first_target == 0.9
    # Recorded as in force, so that a later change of the frame's default cannot move it.
    assert feedback.to_dict()["first_target_shrinkage"] == feedback.shrinkage_before_first_target
    assert guidance.to_dict()["first_target_shrinkage"] == 0.3
    with pytest.raises(ValueError, match="first_target_shrinkage"):
        LearnerConfig(first_target_shrinkage=1.5)
    with pytest.raises(ValueError, match=r"first_target_shrinkage 'oas' .* needs decoder 'lda'"):
        LearnerConfig(first_target_shrinkage="oas", decoder="gaussian")


def test_the_decoders_take_the_shrinkage_after_the_first_target() -> None:
    config = LearnerConfig(planner="random", first_target_shrinkage=0.8, shrinkage=0.3)
    learner = CalibrationFreeLearner(WORLD, config, rng=0)
    fits = []
    run(learner, target=5, steps=120, seed=1, on_step=lambda *_: fits.append(
        (learner.n_targets, learner._fit.shrinkage)))
    assert learner.n_targets >= 1, "the session must reach a target for the switch to show"
    assert {shrinkage for n, shrinkage in fits if n == 0} == {0.8}
    assert {shrinkage for n, shrinkage in fits if n >= 1} == {0.3}


def test_the_threshold_is_the_frames_and_is_recorded_resolved() -> None:
    feedback, guidance = LearnerConfig(), LearnerConfig(frame="guidance")
    assert feedback.frame_beta == DEFAULT_BETA["feedback"] == 0.93  # with the power evidence
    assert guidance.frame_beta == DEFAULT_BETA["guidance"] > 0.9
    assert replace(LearnerConfig(beta=0.95), frame="guidance").frame_beta == 0.95
    assert replace(feedback, frame="guidance").frame_beta == DEFAULT_BETA["guidance"]
    # Recorded as in force: a guidance recording made when the default was 0.9 says so, and
    # is read back with it.
    assert guidance.to_dict()["beta"] == DEFAULT_BETA["guidance"]
    old = learner_settings(guidance.to_dict() | {"beta": 0.9}, "guidance")
    assert old.frame_beta == 0.9
    with pytest.raises(ValueError, match="beta"):
        LearnerConfig(frame="guidance", beta=1.0)


def test_a_confidence_between_the_frames_thresholds_declares_in_one_frame_only() -> None:
    # Two tasks ahead of the rest, the best's pairwise confidence 0.925: above guidance's
    # threshold (0.92), below feedback's (0.93). Without the stricter first target (which
    # at 0 signals would require 1 in feedback), so that the thresholds alone decide.
    log_likelihood = np.full(WORLD.n_tasks, -50.0)
    log_likelihood[3], log_likelihood[4] = np.log(0.925), np.log(0.075)
    confident = {}
    for frame in ("feedback", "guidance"):
        config = LearnerConfig(frame=frame, power_prior=False, first_target_signals=0)
        learner = CalibrationFreeLearner(WORLD, config, rng=0)
        learner.log_likelihood[:] = log_likelihood  # the likelihood's own array
        beliefs = learner.beliefs()
        assert beliefs.best_task == 3 and abs(beliefs.confidence[3] - 0.925) < 1e-9
        assert beliefs.required == beliefs.threshold == DEFAULT_BETA[frame]
        confident[frame] = beliefs.confident
    assert confident == {"feedback": False, "guidance": True}


def test_an_unknown_shrinkage_names_every_accepted_form() -> None:
    """A number is accepted too: the message says so, besides the named rules."""
    for name in ("shrinkage", "first_target_shrinkage"):
        with pytest.raises(ValueError) as error:
            LearnerConfig.from_dict({name: "banana"})
        message = str(error.value)
        assert "a number in [0, 1]" in message and "'oas'" in message and "'cv'" in message
        assert name in message and "'banana'" in message
