"""The documentation's generated reference (docs/hooks/reference.py) covers the code: every
command, every learner setting with its default and accepted values, every service limit."""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
from pathlib import Path

import pytest

from calibration_free.config import LearnerConfig
from calibration_free.continuous_goals import ContinuousConfig
from calibration_free.puddle_learner import PuddleConfig
from cfbci.cli import build_parser

HOOK = Path(__file__).resolve().parents[1] / "docs" / "hooks" / "reference.py"


@pytest.fixture(scope="module")
def reference():
    spec = importlib.util.spec_from_file_location("docs_reference", HOOK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _commands(parser: argparse.ArgumentParser, name: str = "cfbci"):
    yield name
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from _commands(sub, f"{name} {sub_name}")


def test_every_command_has_its_help(reference) -> None:
    text = reference.cli_reference()
    for command in _commands(build_parser()):
        assert f"`{command}`" in text, command
        assert f"usage: {command}" in " ".join(text.split()), command


@pytest.mark.parametrize("config", [LearnerConfig, ContinuousConfig, PuddleConfig])
def test_every_setting_has_a_row_with_its_default(reference, config) -> None:
    rows = {line.split("|")[1].strip(): line for line in
            reference.settings_reference(config).splitlines()[2:]}
    for spec in dataclasses.fields(config):
        row = rows[f"`{spec.name}`"]
        if spec.default is not None and not isinstance(spec.default, bool):
            assert f"{spec.default:g}" in row if isinstance(spec.default, float) else \
                str(spec.default) in row, row


def test_accepted_values_come_from_the_checks(reference) -> None:
    learner = reference.accepted_values(LearnerConfig)
    assert learner["eps"] == "[0, 0.5]"
    assert learner["beta"] == "(0.5, 1)"
    assert learner["confusion_smoothing"] == "x >= 0"
    assert '"matching"' in learner["likelihood"]
    puddle = reference.accepted_values(PuddleConfig)
    assert puddle["mixing"] == "(0, 1)"
    assert puddle["update_every"] == "x >= 1"
    assert puddle["kernel_variance"] == "x > 0"
    assert puddle["map_discount"] == "[0, 1)"
    assert reference.accepted_values(ContinuousConfig)["n_hypotheses"] == "x >= 2"


def test_every_limit_is_listed(reference) -> None:
    from cfbci.service.limits import ServiceLimits

    text = reference.limits_reference()
    for spec in dataclasses.fields(ServiceLimits):
        assert f"`--{spec.name.replace('_', '-')}`" in text, spec.name
