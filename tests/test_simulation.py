"""Closed-loop sessions, the simulated user, and the ``cfbci simulate`` command."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from acquisition.labelled import LabelledFeatures
from acquisition.sources import DataSpec
from acquisition.user import SimulatedUser
from calibration_free.config import LearnerConfig
from calibration_free.shrinkage_choice import SHRINKAGE_GRID
from calibration_free.streams import StepRecord
from calibration_free.world import ACTIONS, GOAL, MOVES, GridWorld
from cfbci.cli import main
from cfbci.offline.simulation import SessionConfig, SessionResult, run_session, summarise

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"


def separated(n_per_class: int = 200, n_classes: int = 2, seed: int = 0) -> LabelledFeatures:
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(n_classes), n_per_class)
    features = rng.normal(size=(len(labels), 5)) + 3.0 * np.eye(n_classes, 5)[labels]
    return LabelledFeatures(features, labels, n_classes, "separated")


def test_feedback_user_labels_follow_the_target_and_pools_cycle():
    world = GridWorld(3)
    labels = np.array([0, 0, 0, 1, 1])
    user = SimulatedUser(world, "feedback", labels, np.random.default_rng(0))
    user.target = 4
    drawn = [user.answer(1, ACTIONS.index("down")) for _ in range(6)]  # 1 -> 4: correct
    assert all(label == 0 for _, label in drawn)
    # Without replacement within a pass over the pool, then reshuffled.
    assert sorted(i for i, _ in drawn[:3]) == [0, 1, 2]
    assert sorted(i for i, _ in drawn[3:]) == [0, 1, 2]
    assert user.answer(1, ACTIONS.index("up"))[1] == 1
    assert user.answer(4, GOAL)[1] == 0 and user.answer(3, GOAL)[1] == 1


def test_guidance_user_answers_with_the_direction_to_the_target():
    world = GridWorld(3)
    labels = np.repeat(np.arange(4), 3)
    user = SimulatedUser(world, "guidance", labels, np.random.default_rng(0))
    user.target = 2  # top-right corner
    seen = {user.answer(6, 0)[1] for _ in range(40)}  # from bottom-left: up or right
    assert seen == {MOVES.index("up"), MOVES.index("right")}
    assert {user.answer(2, GOAL)[1] for _ in range(60)} == {0, 1, 2, 3}


def test_user_error_rate_flips_labels_at_that_rate():
    world = GridWorld(3)
    user = SimulatedUser(world, "feedback", np.array([0, 1] * 50), np.random.default_rng(1), 0.2)
    user.target = 4
    flipped = np.mean([user.answer(1, ACTIONS.index("down"))[1] for _ in range(4000)])
    assert 0.18 < flipped < 0.22


def test_new_target_is_always_another_cell():
    user = SimulatedUser(GridWorld(3), "feedback", np.array([0, 1]), np.random.default_rng(2))
    for _ in range(50):
        old = user.target
        assert user.new_target() != old


def test_a_session_is_determined_by_its_seed_and_reaches_targets():
    config = SessionConfig(steps=150, grid=4)
    first, trace_a, trace_b = [], [], []
    first = run_session(3, config, separated(), trace_a.append)
    again = run_session(3, config, separated(), trace_b.append)
    other = run_session(4, config, separated())
    assert first == again and trace_a == trace_b
    assert first != other
    assert first.correct_targets >= 3 and first.wrong_targets == 0
    events = [r for r in trace_a if r.event]
    assert next(r.step for r in events if r.event == "correct_target") == first.first_target_step
    assert all(r.action == "goal" and r.confident for r in events)


def test_baseline_session_counts_calibration_steps():
    config = SessionConfig(steps=120, grid=4, baseline="calibrated", calibration_trials=60)
    trace = []
    result = run_session(0, config, separated(), trace.append)
    assert result.first_target_step is None or result.first_target_step > 60
    assert next(r.event for r in trace if r.event) == "calibration_done"
    assert result.correct_targets >= 1
    # The shrinkage chosen at the end of the calibration holds for every target after it.
    targets = result.correct_targets + result.wrong_targets
    assert len(result.shrinkages) == 1 + targets
    assert result.shrinkages[0] in SHRINKAGE_GRID and len(set(result.shrinkages)) == 1


def test_a_session_reports_the_shrinkage_in_force_from_each_target():
    chosen = run_session(3, SessionConfig(steps=150, grid=4), separated())
    fixed = run_session(
        3, SessionConfig(steps=150, grid=4, learner=LearnerConfig(shrinkage=0.3)), separated()
    )
    for result in (chosen, fixed):
        assert len(result.shrinkages) == result.correct_targets + result.wrong_targets >= 3
    assert set(chosen.shrinkages) <= set(SHRINKAGE_GRID)
    assert set(fixed.shrinkages) == {0.3}


def test_a_session_reports_the_evidence_temperature_of_each_segment():
    learner = LearnerConfig(calibration_signals=40)
    calibrated = run_session(3, SessionConfig(steps=150, grid=4, learner=learner), separated())
    tempered = run_session(
        3,
        SessionConfig(steps=150, grid=4, learner=replace(learner, calibrated_evidence=False)),
        separated(),
    )
    for result in (calibrated, tempered):
        assert len(result.temperatures) == result.correct_targets + result.wrong_targets >= 3
    assert set(tempered.temperatures) == {1.0}
    # The first segment is never calibrated; a later one on well separated signals is, with
    # evidence stronger than the tempered filter's.
    assert calibrated.temperatures[0] == 1.0
    assert max(calibrated.temperatures[1:]) > 1.5


def test_summary_statistics():
    results = [
        SessionResult(0, 100, 10, 10, 3, 1, 8, True, [0.5, 1.0]),
        SessionResult(1, 100, None, None, 0, 0, None, None, [0.1, 0.2]),
        SessionResult(2, 100, 30, 50, 5, 0, 29, False, [0.0, 0.3]),
    ]
    summary = summarise(results)
    assert summary["median_first_target_step"] == 30  # the session with none counts as 101
    assert summary["median_first_confident_step"] == 29
    assert summary["sessions_with_a_target"] == 2
    assert summary["wrong_first_target_fraction"] == pytest.approx(1 / 2)  # seed 2's first
    assert summary["mean_user_task_likelihood"] == pytest.approx({"10": 0.2, "20": 0.5})
    assert summary["mean_correct_targets"] == pytest.approx(8 / 3)
    assert summary["mean_wrong_targets"] == pytest.approx(1 / 3)
    assert summary["wrong_target_rate"] == pytest.approx(1 / 9)


def test_simulate_command_writes_report_and_trace(tmp_path, capsys):
    report, trace = tmp_path / "r.json", tmp_path / "t.jsonl"
    code = main([
        "simulate", "--seeds", "2", "--first-seed", "5", "--steps", "60", "--grid", "3",
        "--jobs", "1", "--json", str(report), "--trace", str(trace), "--set", "beta=0.95",
    ])
    assert code == 0
    out = json.loads(report.read_text())
    assert out["config"]["learner"]["beta"] == 0.95 and out["config"]["first_seed"] == 5
    assert [s["seed"] for s in out["sessions"]] == [5, 6]
    assert set(out["summary"]) == {
        "median_first_target_step", "mean_correct_targets", "mean_wrong_targets",
        "wrong_target_rate", "sessions_with_a_target", "median_first_confident_step",
        "wrong_first_target_fraction", "mean_user_task_likelihood", "confidence_calibration",
        "confidence_calibration_by_rule",
    }
    assert {"first_confident_step", "first_confident_correct", "user_task_likelihood",
            "calibration_counts"} <= set(out["sessions"][0])
    assert sum(b["steps"] for b in out["summary"]["confidence_calibration"]) == 2 * 60
    lines = [json.loads(line) for line in trace.read_text().splitlines()]
    assert len(lines) == 120
    assert set(lines[0]) == {
        "seed", "step", "state", "action", "next_state", "confident", "best_task", "event"
    }
    assert "median first target" in capsys.readouterr().out


def test_simulate_on_a_local_dask_cluster_equals_one_process(tmp_path):
    """``--scheduler local`` (a real Dask LocalCluster of two worker processes) writes the
    same JSON report and trace as ``--jobs 1`` (in this process) for the same seeds."""
    outputs = []
    for name, options in (("one", ["--jobs", "1"]), ("dask", ["--scheduler", "local",
                                                              "--jobs", "2"])):
        report, trace = tmp_path / f"{name}.json", tmp_path / f"{name}.jsonl"
        assert main(["simulate", "--seeds", "3", "--first-seed", "4", "--steps", "40",
                     "--grid", "3", *options, "--json", str(report), "--trace", str(trace)]) == 0
        outputs.append((json.loads(report.read_text()), trace.read_text()))
    (one, one_trace), (dask, dask_trace) = outputs
    assert dask == one
    assert [s["seed"] for s in one["sessions"]] == [4, 5, 6]
    assert any(s["first_target_step"] for s in one["sessions"])  # sessions that did something
    assert dask_trace == one_trace and len(one_trace.splitlines()) == 3 * 40


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--set", "colour=blue"], "unknown learner setting"),
        (["--set", "beta=2"], "beta must be in"),
        (["--set", "beta=high"], "'beta' must be a number"),  # not a TypeError's traceback
        (["--set", "first_target_signals=1.5"], "'first_target_signals' must be an integer"),
        (["--set", "frame=guidance"], "the frame is set with --frame"),
        (["--frame", "guidance"], "needs a 4-class dataset"),
        (["--synthetic-accuracy", "0.99"], "accuracy"),
        (["--dataset", "/nonexistent/file.mat"], "file.mat"),
        (["--scheduler", "127.0.0.1:8786"], "tcp://HOST:PORT"),
        (["--scheduler", "tcp://127.0.0.1:8786", "--jobs", "2"], "leave --jobs out"),
    ],
)
def test_simulate_reports_bad_options_clearly(arguments, message, capsys):
    code = main(["simulate", "--seeds", "1", "--steps", "5", "--jobs", "1", *arguments])
    assert code == 2
    assert message in capsys.readouterr().err


@pytest.mark.skipif(not (SHARED / "finger-moves").is_dir(), reason="../shared/datasets absent")
def test_guidance_on_real_finger_data_finds_targets():
    config = SessionConfig(steps=150, learner=LearnerConfig(frame="guidance"))
    data = DataSpec(SHARED / "finger-moves" / "move_finger.mat").resolve("guidance")
    result = run_session(0, config, data)
    assert result.first_target_step is not None and result.first_target_step <= 60
    assert result.correct_targets >= 3 and result.wrong_targets == 0


def test_a_session_reports_when_it_was_first_confident_and_its_task_likelihood() -> None:
    config = SessionConfig(steps=80, grid=5)
    trace: list[StepRecord] = []
    result = run_session(1, config, separated(), trace.append)
    assert result.first_confident_step == next(r.step for r in trace if r.confident)
    assert result.first_confident_correct  # separable data: the right task
    assert result.first_confident_step <= result.first_target_step  # declared once confident
    assert len(result.user_task_likelihood) == 8  # after steps 10, 20, ..., 80
    assert all(0.0 <= v <= 1.0 for v in result.user_task_likelihood)
    # Well above uniform (1/25) already after 10 steps, and (the likelihood restarts in each
    # target's segment) the user's task above every other together at some point.
    assert result.user_task_likelihood[0] > 2 / 25
    assert max(result.user_task_likelihood) > 0.5


def test_without_declarations_the_user_teaches_one_task_whose_likelihood_rises() -> None:
    learner = LearnerConfig(declare_targets=False, planner="epsilon-greedy", power_prior=False)
    config = SessionConfig(steps=120, grid=3, learner=learner)
    trace: list[StepRecord] = []
    result = run_session(0, config, separated(), trace.append)
    assert result.first_target_step is None and not any(r.event for r in trace)
    assert result.first_confident_step is not None  # confident, yet it declares nothing
    assert result.user_task_likelihood[-1] > 0.9 > result.user_task_likelihood[0]


def test_the_simulate_config_records_the_novelty_bonus_in_force() -> None:
    from calibration_free.config import DEFAULT_NOVELTY_BONUS

    for frame in ("feedback", "guidance"):
        config = SessionConfig(learner=LearnerConfig(frame=frame)).to_dict()
        assert config["learner"]["novelty_bonus"] == DEFAULT_NOVELTY_BONUS[frame]


def test_after_observe_sees_the_learner_after_every_signal_without_changing_the_session():
    config = SessionConfig(steps=60)
    seen: list[int] = []
    watched = run_session(
        3, config, separated(), after_observe=lambda learner: seen.append(learner.n_signals)
    )
    assert seen == list(range(1, 61))
    plain = run_session(3, config, separated())
    assert (watched.first_target_step, watched.correct_targets, watched.wrong_targets) == (
        plain.first_target_step, plain.correct_targets, plain.wrong_targets
    )
    assert watched.correct_targets > 0  # the session did something worth comparing
