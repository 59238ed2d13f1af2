"""``cfbci simulate --preset``: the thesis's experiments' settings, overridable."""

from __future__ import annotations

import json

import pytest

from cfbci.cli import build_parser, main
from cfbci.cli.options import parse_settings
from cfbci.offline.presets import PRESETS, preset


def _parsed(*argv: str):
    args = build_parser().parse_args(argv)
    return build_parser(PRESETS[args.preset]).parse_args(argv)


def test_a_preset_sets_options_and_learner_settings() -> None:
    args = _parsed("simulate", "--preset", "simple-vs-matching")
    assert (args.synthetic, args.synthetic_accuracy, args.seeds, args.steps) == (
        "gaussian", 0.65, 100, 500
    )
    assert parse_settings(args.set) == PRESETS["simple-vs-matching"].learner


def test_explicit_options_and_settings_override_the_preset() -> None:
    args = _parsed(
        "simulate", "--seeds", "3", "--preset", "simple-vs-matching", "--set",
        "likelihood=matching", "--synthetic-accuracy", "0.9",
    )
    assert (args.seeds, args.synthetic_accuracy, args.steps) == (3, 0.9, 500)
    settings = parse_settings(args.set)
    assert settings["likelihood"] == "matching"  # the command line's, given after
    assert settings["decoder"] == "student_t"  # the preset's, untouched


def test_every_preset_is_listed_and_an_unknown_one_is_refused(capsys) -> None:
    assert main(["simulate", "--list-presets"]) == 0
    listed = capsys.readouterr().out
    assert all(f"{name}:" in listed for name in PRESETS)
    with pytest.raises(ValueError, match="unknown preset 'nope'; known: frame-hypotheses"):
        preset("nope")
    with pytest.raises(SystemExit):
        build_parser().parse_args(["simulate", "--preset", "nope"])


def test_a_preset_that_needs_a_dataset_says_which(capsys) -> None:
    assert main(["simulate", "--preset", "pick-and-place-speech"]) == 2
    assert "needs --dataset FILE.npz from `cfbci datasets speech" in capsys.readouterr().err


def test_the_likelihood_flag_overrides_the_preset_and_reaches_the_learner(tmp_path) -> None:
    report = tmp_path / "r.json"
    assert main([
        "simulate", "--preset", "world-properties", "--likelihood", "matching", "--seeds", "1",
        "--steps", "15", "--jobs", "1", "--json", str(report),
    ]) == 0
    learner = json.loads(report.read_text())["config"]["learner"]
    assert learner["likelihood"] == "matching" and learner["decoder"] == "gaussian"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["simulate", "--likelihood", "entropy"])
