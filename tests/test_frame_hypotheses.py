"""Frame hypotheses (method-extensions §4): (task, frame) pairs with different class counts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from acquisition.gaussian import generate_gaussian_features
from calibration_free.config import LearnerConfig
from calibration_free.frame_hypotheses import FrameHypothesesLearner
from calibration_free.worlds import make_world
from cfbci.cli import main
from cfbci.frame_sessions import run_frame_session

CONFIG = LearnerConfig(decoder="student_t", eps=0.01, planner="random")


@pytest.fixture(scope="module")
def signals():
    # A well-separated 4-class stand-in for move_finger.mat (11-D, 100 per class).
    return generate_gaussian_features(100, 4, 11, 0.99, seed=11)


def test_uninformative_signals_leave_every_pair_at_chance_whatever_its_class_count() -> None:
    # Fewer signals than dimensions: every Student-t decoder is uninformative, so every
    # matching term is 1/K; against each frame's chance level every pair scores 0.
    world = make_world("line")
    learner = FrameHypothesesLearner(world, config=CONFIG, rng=np.random.default_rng(0))
    rng = np.random.default_rng(1)
    for step in range(10):
        learner.observe(2, step % 3, rng.normal(size=11).astype(np.float32))
    beliefs = learner.beliefs()
    assert learner.n_hypotheses == 4
    assert np.allclose(beliefs.scores, 0.0, atol=1e-9)
    assert np.allclose(beliefs.confidence, 0.5) and not beliefs.confident


def test_the_users_task_and_frame_win_and_a_shuffled_control_stays_undecided(signals) -> None:
    world = make_world("line")
    real = [run_frame_session(seed, world, CONFIG, signals, 150) for seed in range(8)]
    # Both teacher frames are represented (seed parity) and nearly every run finds the pair.
    assert {r.teacher_frame for r in real} == {"feedback", "guidance"}
    assert sum(bool(r.first_confident_correct) for r in real) >= 7
    assert all(r.winning_frame == r.teacher_frame for r in real)
    shuffled = [run_frame_session(seed, world, CONFIG, signals, 150, True) for seed in range(8)]
    assert sum(r.first_confident_step is not None for r in shuffled) <= 1


def test_the_command_reports_the_winning_frame(tmp_path: Path, signals) -> None:
    out = tmp_path / "frames.json"
    argv = ["simulate", "--world", "line", "--frame", "hypotheses", "--synthetic", "gaussian",
            "--dims", "5", "--synthetic-accuracy", "0.97", "--seeds", "2", "--steps", "60",
            "--set", "decoder=student_t", "--set", "eps=0.01", "--jobs", "1", "--json", str(out)]
    assert main(argv) == 0
    report = json.loads(out.read_text())
    assert [s["teacher_frame"] for s in report["sessions"]] == ["feedback", "guidance"]
    for session in report["sessions"]:
        assert session["winning_frame"] in ("feedback", "guidance")
        assert len(session["user_task_likelihood"]) == 6
    assert report["config"]["learner"]["planner"] == "random"
