"""``cfbci report``: metrics of recordings, figures and the HTML report.

Recordings are written in-process with `SessionRecorder` (no Zenoh): a hand-built one
whose every metric is known by construction, and a real one made by running the learner and
a simulated user exactly as the service and the replay source do (checked with
`replay.rerun.replay_check`).
"""

from __future__ import annotations

import base64
import dataclasses
import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from acquisition.sources import DEFAULT_SYNTHETIC_ACCURACY, synthetic_epochs
from acquisition.user import SimulatedUser
from calibration_free.config import DEFAULT_BETA
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.streams import session_streams, start_cell
from calibration_free.world import ACTIONS, GridWorld, transition_draws
from cfbci.cli import main
from decoding.features import ErrPFeatures
from replay.figures import session_figures
from replay.html_report import SessionReport, render_html
from replay.metrics import aggregate, latency_summary, session_metrics
from replay.recording import SessionRecorder, read_recording
from replay.rerun import replay_check
from session.config import learner_settings
from session.tasks import move_fields, state_fields

KINDS = ("confidence", "belief", "accuracy", "erp", "latency")

# -- a hand-built recording: 2 x 2 grid (cells 0 1 / 2 3), 6 steps ------------------------
#: (from_state, action, to_state, target_reached, user's target, true label)
HAND_STEPS = [
    (0, "right", 1, False, 3, 0),
    (1, "down", 3, False, 3, 0),
    (3, "goal", 3, True, 3, 0),  # correct target at step 3
    (3, "left", 2, False, 0, 0),
    (2, "goal", 2, True, 0, 1),  # wrong target at step 5 (the user wants cell 0)
    (2, "up", 0, False, 1, 0),
]
#: Confidence of each cell in the state accompanying move k (k = 1..6), then the final one.
HAND_CONFIDENCE = [
    [0.5, 0.5, 0.5, 0.5],
    [0.4, 0.3, 0.2, 0.6],
    [0.1, 0.2, 0.05, 0.95],
    [0.5, 0.5, 0.5, 0.5],
    [0.3, 0.1, 0.92, 0.2],
    [0.45, 0.5, 0.4, 0.5],
    [0.5, 0.5, 0.5, 0.5],
]
HAND_SELF_ACCURACY = [None, None, None, 0.5, 0.6, 0.75, 0.8]  # by n_signals 0..6
HAND_UPDATE_MS = [None, 1.0, 2.0, 3.0, 4.0, 10.0]  # none on the first move


def write_hand_built(
    path: Path, frame: str = "feedback", n_features: int = 3, **fields: Any
) -> None:
    """The recording of HAND_STEPS as the service would write it (feature vectors of
    ``n_features``); ``fields`` are added to (or replace) the config's."""
    config = {
        "seq": 0, "t_ns": 0, "seed": 0, "grid": 2, "frame": frame, "steps": len(HAND_STEPS),
        "learner": {}, "dataset": {"description": "hand-built"}, "signal": "features",
        **fields,
    }
    rng = np.random.default_rng(0)
    with SessionRecorder(path, "hand", config) as recorder:
        t = 1
        for k, (src, action, dst, reached, target, label) in enumerate(HAND_STEPS, start=1):
            move = {"seq": k, "t_ns": t, "step": k, "from_state": src, "action": action,
                    "to_state": dst, "target_reached": reached}
            if HAND_UPDATE_MS[k - 1] is not None:
                move["update_ms"] = HAND_UPDATE_MS[k - 1]
            recorder.record("/move", move, t)
            record_hand_state(recorder, k - 1, t)
            if reached:
                recorder.record("/event", {"seq": k, "t_ns": t, "event": "target_reached",
                                           "message": f"step {k}: target reached in cell {src}"}, t)
            # Guidance: label k stands for a direction; feedback: 0 correct, 1 error.
            label = label if frame == "feedback" else (k - 1) % 4
            features = rng.normal(size=n_features) + 2.0 * label
            header = {"seq": k, "t_ns": t, "units": "uV", "step": k, "signal": "features"}
            recorder.record_array("/epoch", header, features, t)
            recorder.record_array("/features", header, features, t)
            recorder.record("/truth", {"seq": k, "t_ns": t, "step": k, "target": target,
                                       "label": label}, t)
            t += 1
        record_hand_state(recorder, len(HAND_STEPS), t)


def record_hand_state(recorder: SessionRecorder, n_signals: int, t: int) -> None:
    confidence = HAND_CONFIDENCE[n_signals]
    recorder.record("/state", {
        "seq": n_signals, "t_ns": t, "best_task": int(np.argmax(confidence)),
        "confident": max(confidence) > 0.9, "n_signals": n_signals,
        "class_counts": [float(n_signals), 0.0],
        "balanced_accuracy": HAND_SELF_ACCURACY[n_signals], "confidence": confidence,
    }, t)
    recorder.record_belief(np.asarray(confidence), GridWorld(2), t)


# -- a real recording, made in-process as the service and the replay source would ---------
REAL_SEED, REAL_STEPS, REAL_GRID = 5, 90, 3


def write_real(path: Path, seed: int = REAL_SEED, steps: int = REAL_STEPS,
               grid: int = REAL_GRID, settings_given: dict[str, Any] | None = None,
               marks_from: int | None = None) -> None:
    """A synthetic-epoch session: the learner, a simulated user and the service's messages.

    Same streams, start cell, feature extraction and message order as a live session
    (``update_ms`` is a made-up, deterministic value: no clock is read);
    ``settings_given``: learner settings (the others their defaults). ``marks_from``: a
    session with a person instead: no ``/truth``, but the operator marks the user's target
    at that step and each new one at the step after the previous one was declared (the
    service's ``target_marked`` events, the last move's step).
    """
    data_rng, user_rng, learner_rng = session_streams(seed)
    data = synthetic_epochs(DEFAULT_SYNTHETIC_ACCURACY, data_rng)
    world = GridWorld(grid)
    user = SimulatedUser(world, "feedback", data.labels, user_rng)
    settings = learner_settings(settings_given or {}, "feedback")
    learner = CalibrationFreeLearner(world, settings, learner_rng)
    state = start_cell(seed, world.n_states)
    assert state == user.start_state
    draws = transition_draws(seed)
    config = {
        "seq": 0, "t_ns": 0, "seed": seed, "grid": grid, "frame": "feedback", "steps": steps,
        "learner": settings.to_dict(),  # every setting, as the service records them
        "dataset": {"description": "synthetic"}, "signal": "epochs",
        "sfreq": float(data.sfreq), "tmin": float(data.tmin), "ch_names": list(data.ch_names),
    }
    extractor = ErrPFeatures(data.sfreq, data.tmin, data.ch_names)
    marked = None  # the target the operator marked last
    with SessionRecorder(path, "real", config) as recorder:

        def record_state(t: int) -> None:
            fields, confidence = state_fields(learner)
            recorder.record("/state", {"seq": t, "t_ns": t, **fields,
                                       "confidence": [float(c) for c in confidence]}, t)
            recorder.record_belief(confidence, world, t)

        for step in range(1, steps + 1):
            t = 10 * step
            proposal = learner.propose(state)
            move = {"seq": step, "t_ns": t, **move_fields(world, step, state, proposal, draws)}
            if step > 1:
                move["update_ms"] = float(1 + step % 7)
            recorder.record("/move", move, t)
            record_state(t)
            if proposal.declares_target:
                recorder.record("/event", {
                    "seq": step, "t_ns": t, "event": "target_reached",
                    "message": f"step {step}: target reached in cell {state}",
                }, t)
            if marks_from is not None and step >= marks_from and user.target != marked:
                marked = user.target
                recorder.record("/event", {
                    "seq": step, "t_ns": t, "event": "target_marked", "config_t_ns": None,
                    "message": f"the operator marked target {marked} at step {step}",
                    "step": step, "target": marked,
                }, t)
            index, label = user.answer(state, proposal.action)
            epoch = data.epochs[index]
            header = {"seq": step, "t_ns": t + 1, "units": "uV", "step": step,
                      "signal": "epochs", "ch_names": list(data.ch_names)}
            recorder.record_array("/epoch", header, epoch, t + 1)
            if step == 1:
                extractor.fit(epoch[None])
            signal = extractor.transform(epoch[None])[0].astype(np.float32)
            recorder.record_array("/features", {"seq": step, "t_ns": t + 1, "step": step},
                                  signal, t + 1)
            if marks_from is None:
                recorder.record("/truth", {"seq": step, "t_ns": t + 2, "step": step,
                                           "target": user.target, "label": label}, t + 2)
            if proposal.declares_target:
                user.new_target()
            learner.observe(state, proposal.action, signal)
            state = world.step(state, proposal.action)
        record_state(10 * steps + 5)


@pytest.fixture(scope="module")
def real(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("real") / "real.mcap"
    write_real(path)
    return path


@pytest.fixture(scope="module")
def real_metrics(real: Path) -> Any:
    return session_metrics(read_recording(real), str(real))


def cut(source: Path, destination: Path, fraction: float) -> Path:
    """A copy of ``source`` cut at ``fraction`` of its bytes (a killed writer's file)."""
    data = source.read_bytes()
    destination.write_bytes(data[: int(len(data) * fraction)])
    return destination


# -- metrics ----------------------------------------------------------------------------


def test_metrics_of_a_hand_built_recording(tmp_path: Path) -> None:
    path = tmp_path / "hand.mcap"
    write_hand_built(path)
    m = session_metrics(read_recording(path), str(path))

    assert (m.steps, m.n_signals, m.configured_steps) == (6, 6, 6)
    assert m.first_target_step == 3
    assert [(t.step, t.cell, t.true_target, t.correct) for t in m.targets] == [
        (3, 3, 3, True), (5, 2, 0, False),
    ]
    assert (m.correct_targets, m.wrong_targets, m.unverified_targets) == (1, 1, 0)
    assert m.steps_per_correct_target == 6.0  # 6 steps / 1 correct target
    assert m.mean_steps_between_targets == 2.0  # targets at steps 3 and 5
    assert m.true_target == [3, 3, 3, 0, 0, 1]
    assert m.confidence_true == [0.5, 0.6, 0.95, 0.5, 0.3, 0.5]
    assert m.confidence_best_other == [0.5, 0.4, 0.2, 0.5, 0.92, 0.5]
    assert m.best_other_task == [0, 0, 1, 1, 2, 3]
    assert m.accuracy_self == [None, None, 0.5, 0.6, 0.75, 0.8]  # after 1..6 signals
    assert m.final_accuracy_self == 0.8
    # update_ms 1, 2, 3, 4, 10: linear-interpolation percentiles
    assert m.update_ms == [1.0, 2.0, 3.0, 4.0, 10.0]
    assert m.latency is not None
    assert (m.latency.n, m.latency.median_ms, m.latency.max_ms) == (5, 3.0, 10.0)
    assert m.latency.p90_ms == pytest.approx(4 + 0.6 * 6)
    assert m.latency.p99_ms == pytest.approx(4 + 0.96 * 6)
    assert m.chance == 0.5 and m.beta == DEFAULT_BETA["feedback"]  # none recorded: the default
    assert not m.truncated and m.warning is None
    # The hand-built moves are not the learner's: the re-run says so.
    assert m.replay_identical is False and "step 1" in (m.replay_note or "")
    # The rule in force at each step is the re-run's: not known where it diverged.
    assert m.calibration_counts is not None and m.calibration_counts_by_rule is None
    assert len(m.accuracy_truth) == 6
    assert all(a is None or 0.0 <= a <= 1.0 for a in m.accuracy_truth)
    json.dumps(m.to_dict(), allow_nan=False)  # JSON-ready


def test_latency_summary_of_no_and_one_value() -> None:
    assert latency_summary([]) is None
    assert latency_summary([5.0]).p99_ms == 5.0  # type: ignore[union-attr]


def test_aggregate_takes_median_min_max_over_sessions(tmp_path: Path) -> None:
    path = tmp_path / "hand.mcap"
    write_hand_built(path)
    first = session_metrics(read_recording(path), rerun=False)
    second = session_metrics(read_recording(path), rerun=False)
    third = session_metrics(read_recording(path), rerun=False)
    second.first_target_step, third.first_target_step = 10, None
    second.correct_targets, third.correct_targets = 3, 5
    result = aggregate([first, second, third])
    assert result["first_target_step"] == {"median": 6.5, "min": 3.0, "max": 10.0, "n": 2}
    assert result["correct_targets"] == {"median": 3.0, "min": 1.0, "max": 5.0, "n": 3}
    assert result["latency_p90_ms"]["median"] == pytest.approx(7.6)
    assert result["_count"] == {"sessions": 3, "truncated": 0}


def test_the_in_process_recording_is_what_the_service_would_record(real: Path) -> None:
    result = replay_check(real)
    assert result.divergence is None
    assert result.moves == REAL_STEPS


def test_accuracy_against_truth_equals_the_self_estimate_when_labels_are_true(
    real: Path, real_metrics: Any
) -> None:
    """Before the first target the user's target is fixed and errs never: the learner's
    labels under the true task are the truth, so where the best task is the true one the
    accuracy against the truth is the recorded self-estimate, exactly."""
    m = real_metrics
    assert m.replay_identical is True
    assert m.first_target_step is not None and m.correct_targets >= 2
    states = [s for _, s in read_recording(real).messages["/state"]]
    target = m.true_target[0]
    same = [
        t for t in range(1, m.first_target_step)
        if states[t]["best_task"] == target and m.accuracy_self[t - 1] is not None
    ]
    assert len(same) >= 5
    for t in same:
        assert m.accuracy_truth[t - 1] == m.accuracy_self[t - 1]
    # And it is a real measurement elsewhere: defined, in [0, 1], better than chance at the end.
    assert all(0 <= a <= 1 for a in m.accuracy_truth[20:])
    assert m.final_accuracy_truth > 0.6


def test_a_truncated_recording_is_measured_as_far_as_it_goes(
    real: Path, real_metrics: Any, tmp_path: Path
) -> None:
    path = cut(real, tmp_path / "cut.mcap", 0.55)
    recording = read_recording(path)
    m = session_metrics(recording, str(path))
    assert m.truncated
    assert m.warning is not None and "truncated at byte" in m.warning
    assert f"ends after the move of step {m.steps}" in m.warning
    assert 0 < m.steps < REAL_STEPS and m.n_signals in (m.steps - 1, m.steps)
    assert m.replay_identical is True  # the prefix it holds is the learner's
    full = real_metrics
    assert m.accuracy_truth == full.accuracy_truth[: m.n_signals]
    n_truths = len(recording.messages["/truth"])
    assert m.confidence_true[:n_truths] == full.confidence_true[:n_truths]
    assert all(c is None for c in m.confidence_true[n_truths:])  # no truth: no true task
    # Targets up to the cut, verified where the cut recording still holds their truth.
    truths = {message["step"] for _, message in recording.messages["/truth"]}
    expected = [
        t if t.step in truths else dataclasses.replace(t, true_target=None, correct=None)
        for t in full.targets if t.step <= m.steps
    ]
    assert m.targets == expected and any(t.correct is not None for t in m.targets)


def test_guidance_recordings_plot_per_class_means(tmp_path: Path) -> None:
    path = tmp_path / "guidance.mcap"
    write_hand_built(path, frame="guidance")
    recording = read_recording(path)
    m = session_metrics(recording, str(path))
    assert m.class_names == ["up", "down", "left", "right"] and m.chance == 0.25
    figures = {f.kind: f for f in session_figures(recording, m, tmp_path / "out", "g")}
    assert set(figures) == set(KINDS)
    assert "guidance" in figures["erp"].title and "per true class" in figures["erp"].title
    assert "feature vectors" in figures["erp"].title  # no raw epochs in this recording


# -- the command ------------------------------------------------------------------------


def test_cfbci_report_writes_metrics_figures_and_html(
    real: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truncated = cut(real, tmp_path / "real-cut.mcap", 0.5)
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("not a recording\n")
    missing = tmp_path / "missing.mcap"
    out = tmp_path / "report"
    files = [real, truncated, not_mcap, missing]
    code = main(["report", *map(str, files), "--out", str(out), "--jobs", "2"])
    captured = capsys.readouterr()
    assert code == 1  # two files could not be reported; the others were

    document = json.loads((out / "metrics.json").read_text())
    assert [s["stem"] for s in document["sessions"]] == ["real", "real-cut"]
    errors = {e["file"]: e["error"] for e in document["errors"]}
    assert set(errors) == {str(not_mcap), str(missing)}
    assert "not an MCAP file" in errors[str(not_mcap)] and str(not_mcap) in errors[str(not_mcap)]
    assert "no such file" in errors[str(missing)]
    for name in (str(not_mcap), str(missing)):
        assert name in captured.err.replace("\n", "")

    full, cut_ = document["sessions"]
    assert not full["truncated"] and full["replay_identical"]
    assert cut_["truncated"] and "truncated at byte" in cut_["warning"]
    assert cut_["warning"] in captured.out.replace("\n", "")
    assert document["aggregate"]["steps"]["n"] == 2
    assert document["aggregate"]["_count"] == {"sessions": 2, "truncated": 1}

    page = (out / "index.html").read_text()
    assert cut_["warning"] in page and "Truncated recording" in page
    assert "not an MCAP file" in page
    for session in document["sessions"]:
        assert [f["kind"] for f in session["figures"]] == list(KINDS)
        for figure in session["figures"]:
            png = out / figure["path"]
            assert png.is_file() and png.read_bytes().startswith(b"\x89PNG")
            assert f'data-file="{png.name}"' in page
            assert base64.b64encode(png.read_bytes()).decode() in page  # embedded
    # The pooled confidence calibration: every step of both sessions with a known target.
    curve = document["confidence_calibration"]
    assert sum(b["steps"] for b in curve) == sum(
        sum(t is not None for t in s["true_target"]) for s in document["sessions"])
    assert all(b["fraction_right"] is None or 0 <= b["fraction_right"] <= 1 for b in curve)
    # Per decision rule, over the sessions the re-run reproduced: here both, so the rules'
    # counts add up to the pooled ones bin by bin.
    by_rule = document["confidence_calibration_by_rule"]
    assert by_rule["sessions"] == 2 and by_rule["rules"]
    assert [b["steps"] for b in curve] == [
        sum(r["curve"][k]["steps"] for r in by_rule["rules"]) for k in range(len(curve))]
    assert (out / "all-sessions_confidence_calibration.png").read_bytes().startswith(b"\x89PNG")
    assert "Confidence calibration (all sessions)" in page
    assert page.count("<figure") == 2 * len(KINDS) + 1
    sources = re.findall(r'src="([^"]*)"', page)
    assert len(sources) == 2 * len(KINDS) + 1
    assert all(src.startswith("data:image/png;base64,") for src in sources)  # self-contained


def test_render_html_of_nothing_processed() -> None:
    page = render_html([SessionReport("x.mcap", "x", error="x.mcap: no such file")],
                       aggregate([]))
    assert "x.mcap: no such file" in page and "<figure" not in page


def test_actions_of_the_hand_built_recording_are_valid_moves() -> None:
    world = GridWorld(2)
    for src, action, dst, *_ in HAND_STEPS:
        assert world.step(src, ACTIONS.index(action)) == dst
