"""A config's ``learner`` object: each setting takes the JSON kinds its annotation allows."""

from __future__ import annotations

import pytest

from calibration_free.config import DEFAULT_NOVELTY_BONUS, LearnerConfig
from wire.messages import learner_settings


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
        ({"shrinkage": [0.5]}, "'shrinkage' must be a number or a string; got [0.5]"),
        ({"shrinkage": True}, "'shrinkage' must be a number or a string; got True"),
        ({"novelty_bonus": "1"}, "'novelty_bonus' must be a number or null; got '1'"),
        ({"eps": None}, "'eps' must be a number; got None"),
        ({"n_folds": 2.0}, "'n_folds' must be an integer; got 2.0"),
        ({"power_prior": 1}, "'power_prior' must be a boolean; got 1"),
        ({"planner": 3}, "'planner' must be a string; got 3"),
        ({"shrinkage": "ledoit"}, "shrinkage"),  # a string, but not a rule
        ({"bogus": 1}, "unknown learner setting"),
    ],
)
def test_a_wrong_kind_is_refused_naming_the_setting(values: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        learner_settings(values, "feedback")
