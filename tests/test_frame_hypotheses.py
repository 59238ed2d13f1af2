"""Frame hypotheses (method-extensions §4): (task, frame) pairs with different class counts."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from acquisition.gaussian import generate_gaussian_features
from calibration_free.config import LearnerConfig
from calibration_free.frame_hypotheses import FRAME_DEFAULTS, FrameHypothesesLearner, beats_chance
from calibration_free.worlds import make_world
from cfbci.cli import main
from cfbci.offline.frame_sessions import frame_hypotheses_report, run_frame_session

CONFIG = LearnerConfig(**{**FRAME_DEFAULTS, "decoder": "student_t", "eps": 0.01})


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


def test_the_thesis_codes_count_finds_a_guidance_teacher_sooner(signals) -> None:
    # Under guidance only the no-move class, labelled at a goal, tells G1 from G2. With its
    # own count a class takes part from its 12th signal (11-D); with the total, its 2nd.
    world = make_world("line")
    guidance_seeds = range(1, 16, 2)
    steps = {
        counts: [
            run_frame_session(
                seed, world, replace(CONFIG, student_t_counts=counts), signals, 100
            )
            for seed in guidance_seeds
        ]
        for counts in ("total", "class")
    }
    assert all(r.teacher_frame == "guidance" for r in steps["total"])
    assert all(r.first_confident_correct for r in steps["total"])
    total = [r.user_pair_confident_step for r in steps["total"]]
    own = [r.user_pair_confident_step or 101 for r in steps["class"]]
    assert None not in total
    assert sum(t < o for t, o in zip(total, own, strict=True)) >= 7


def test_beating_chance_needs_a_wider_margin_when_a_class_is_rare() -> None:
    assert beats_chance(0.8, np.array([40.0, 40.0]))
    # The same accuracy over the same 80 signals, but one class has 2 of them.
    assert not beats_chance(0.8, np.array([78.0, 2.0]))
    assert beats_chance(0.6, np.array([30.0, 30.0, 30.0]))  # chance 1/3
    assert not beats_chance(0.6, np.array([30.0, 0.0, 30.0]))  # chance 1/2 of 2 classes
    assert not beats_chance(1.0, np.array([80.0, 0.0]))  # one class: no accuracy to beat


@pytest.mark.parametrize(
    ("counts", "rates"),
    [([60, 5], [0.5, 0.5]), ([60, 5], [0.8, 0.2]), ([50, 30, 4], [1 / 3] * 3),
     ([50, 30, 4], [0.6, 0.3, 0.1])],
)
def test_the_chance_margin_holds_its_level_for_predictions_independent_of_labels(
    counts, rates
) -> None:
    # Predictions drawn at fixed rates whatever the label: a class's hits are binomial.
    rng = np.random.default_rng(0)
    hits = rng.binomial(counts, rates, size=(4000, len(counts)))
    accuracy = np.mean(hits / np.array(counts), axis=1)
    passed = [beats_chance(a, np.array(counts, dtype=float), z=2.326) for a in accuracy]
    assert np.mean(passed) <= 0.015  # one-sided 1 % (the bound is conservative)


def test_the_report_counts_decisions_and_the_thesis_w_per_teacher() -> None:
    def session(frame, first, correct, user_first, w_at_50, winner=None):
        confidence = [0.5] * 49 + [w_at_50] + [w_at_50] * 150
        return {"teacher_frame": frame, "winning_frame": winner or frame,
                "first_confident_step": first,
                "first_confident_correct": correct, "user_pair_confident_step": user_first,
                "user_pair_confidence": confidence}

    sessions = [
        session("feedback", 30, True, 30, 0.95),
        session("feedback", 40, False, 120, 0.95),  # wrong first, W passed beta at step 50
        session("guidance", None, None, None, 0.6, winner="feedback"),
        session("guidance", 90, True, 90, 0.99),
    ]
    report = frame_hypotheses_report(sessions, steps=200)
    assert report["sessions"] == 4 and report["sessions_confident"] == 3
    assert report["first_confident_correct"] == 2
    assert report["winning_frame_is_teachers"] == 3
    assert report["user_pair_confident_by_step_100"] == 0.5
    assert report["user_pair_w_above_beta_by_step_100"] == 0.75
    assert report["median_first_confident_step"] == 65.0  # 30, 40, 90, 201 (undecided)
    assert report["undecided"] == 0.25
    assert report["mean_user_pair_w"]["51"] == pytest.approx((0.95 * 2 + 0.6 + 0.99) / 4, abs=1e-3)
    assert report["mean_user_pair_w"]["21"] == 0.5
    assert report["feedback_teacher"]["user_pair_confident_by_step_100"] == 0.5
    assert report["guidance_teacher"]["undecided"] == 0.5
    assert "200" in report["mean_user_pair_w"]
    assert "101" not in frame_hypotheses_report(sessions, steps=100)["mean_user_pair_w"]


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
        assert all(0.0 <= p <= 1.0 for p in session["user_task_likelihood"])
        assert {"first_confident_step", "first_confident_correct",
                "user_pair_confident_step"} <= set(session)
    assert set(report["summary"]["mean_user_pair_w"]) == {"21", "31", "41", "51"}
    assert report["summary"]["feedback_teacher"]["sessions"] == 1
    assert report["config"]["learner"]["planner"] == "random"
