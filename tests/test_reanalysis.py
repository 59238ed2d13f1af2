"""Open-loop re-analysis of a recording, and re-publishing it to a live service.

The recordings are made by a real service (a spawned process) answering a real replay
source over Zenoh on loopback TCP, multicast off; the service is stopped before a
recording is read, so that it is complete. Synchronisation is by messages only; every
wait has a timeout that only guards against a hang.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from live import TIMEOUT, rewrite, service_process

from acquisition.simulated_source import SourceSettings, run_source
from calibration_free.config import LearnerConfig
from cfbci.cli import main
from cfbci.recordings.reanalysis import (
    OWN,
    alternative_settings,
    reanalyse,
    recorded_history,
    rescore,
    segments_of,
)
from replay.recording import Recording, decode_array, read_recording
from replay.rerun import replay_check
from session.config import learner_settings
from wire.zenoh_config import free_tcp_endpoint

#: The learner's defaults, which the recording below runs with.
DEFAULT = LearnerConfig()

# Seed 112: 1 correct target and 1 wrong (the defaults since the first-target requirement).
STEPS, GRID, SEED = 60, 3, 112


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A live session of synthetic raw epochs, recorded by the service."""
    directory = tmp_path_factory.mktemp("recorded")
    endpoint = free_tcp_endpoint()
    with service_process(endpoint, directory):
        settings = SourceSettings("live", seed=SEED, steps=STEPS, grid=GRID, timeout=TIMEOUT)
        run_source(settings, [], [endpoint])
    path = directory / "live.mcap"
    assert not read_recording(path).truncated
    return path


def _recorded_confidences(recording: Recording) -> np.ndarray:
    return np.array([m["confidence"] for _, m in recording.messages["/state"]], np.float32)


def test_own_settings_reproduce_the_recorded_confidences_exactly(recorded: Path) -> None:
    recording = read_recording(recorded)
    history = recorded_history(recording)
    segments = segments_of(history)
    declared = [m["step"] for _, m in recording.messages["/move"] if m["target_reached"]]
    assert declared, "the session must declare a target for the switching to be tested"
    assert [s.last_step for s in segments[: len(declared)]] == declared
    assert [s.declared for s in segments[: len(declared)]] == [
        m["from_state"] for _, m in recording.messages["/move"] if m["target_reached"]
    ]

    own = learner_settings(recording.config["learner"], recording.config["frame"])
    trajectory = rescore(history, own)
    states = [m for _, m in recording.messages["/state"]]
    assert len(trajectory) == len(states) == STEPS + 1
    assert np.array_equal(trajectory.confidence, _recorded_confidences(recording))  # bit for bit
    assert trajectory.best_task.tolist() == [s["best_task"] for s in states]
    assert trajectory.confident.tolist() == [s["confident"] for s in states]

    # Without following the recorded declarations, the beliefs part at the first one.
    ignoring = rescore(dataclasses.replace(history, declared=np.zeros(STEPS, bool)), own)
    first_change = next(
        row for row in range(STEPS + 1)
        if not np.array_equal(ignoring.confidence[row], trajectory.confidence[row])
    )
    assert first_change == declared[0]  # the beliefs after the declaring step's epoch

    result = reanalyse(recorded, [])
    (outcome,) = result.outcomes
    assert outcome.name == OWN and outcome.differs == {}
    assert outcome.identical_to_recording and outcome.first_difference_step is None
    # The recorded run was confident on the cell it then declared, in every segment.
    for segment, confident in zip(result.segments, outcome.segments, strict=True):
        if segment.declared is not None:
            assert confident is not None and confident.task == segment.declared
            truth = {m["step"]: m["target"] for _, m in recording.messages["/truth"]}
            assert confident.correct == (confident.task == truth[confident.step])
    verdicts = [c.correct for c in outcome.segments if c is not None]
    assert True in verdicts and False in verdicts  # seed 112 declares a wrong target too


def test_alternative_settings_rescore_the_same_history_differently(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "reanalysis.json"
    code = main([
        "replay", str(recorded), "--option", "eps=0.2", "--option", "shrinkage=0.3",
        "--compare", "balanced_confusion=false", "--compare", f"eps={DEFAULT.eps}, decoder=lda",
        "--per-step", "--json", str(out),
    ])
    assert code == 0
    text = capsys.readouterr().out
    assert "A: eps=0.2, shrinkage=0.3 — differs from the recording's settings in eps " \
        f"{DEFAULT.eps} → 0.2, shrinkage {DEFAULT.resolved_shrinkage!r} → 0.3" in text
    assert f"C: eps={DEFAULT.eps}, decoder=lda — no setting differs from the recording's" in text
    report = json.loads(out.read_text())
    own, changed, unbalanced, same = report["settings"]
    assert own["name"] == OWN and own["identical_to_recording"] and own["differs"] == {}
    assert changed["differs"] == {
        "eps": {"recorded": DEFAULT.eps, "this": 0.2},
        "shrinkage": {"recorded": DEFAULT.resolved_shrinkage, "this": 0.3},
    }
    assert unbalanced["differs"] == {"balanced_confusion": {"recorded": True, "this": False}}
    for other in (changed, unbalanced):
        assert not other["identical_to_recording"]
        assert 1 < other["first_difference_step"] <= STEPS
    assert same["identical_to_recording"] and same["segments"] == own["segments"]
    # Every setting sees the recording's segments; per-step beliefs line up with /state.
    assert report["steps"] == STEPS and len(report["per_step"]) == STEPS
    recording = read_recording(recorded)
    states = [m for _, m in recording.messages["/state"]]
    for row, state in zip(report["per_step"], states, strict=False):
        assert row["recorded"]["best_task"] == row[OWN]["best_task"] == state["best_task"]
        assert row[OWN]["confidence"] == state["confidence"][state["best_task"]]
    trajectories = {o["name"]: [r[o["name"]]["confidence"] for r in report["per_step"]]
                    for o in report["settings"]}
    assert trajectories[changed["name"]] != trajectories[OWN]
    assert trajectories[unbalanced["name"]] != trajectories[OWN]


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--option", "foo=1"], "unknown learner setting(s) ['foo']"),
        (["--option", "beta=abc"], "learner setting 'beta' must be a number"),
        (["--option", "beta=1.5"], "beta"),
        (["--option", "decoder=nope"], "decoder must be one of"),
        (["--option", "beta"], "--option expects KEY=VALUE"),
        (["--compare", "eps=0.2 =3"], "--compare expects KEY=VALUE"),
        (["--option", "frame=guidance"], "differs from the config's frame"),
        (["--option", "eps=0.2", "--publish"], "--publish re-publishes the recording"),
        (["--speed", "2"], "only apply with --publish"),
    ],
)
def test_bad_options_are_clear_errors(
    recorded: Path, arguments: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["replay", str(recorded), *arguments]) == 2
    assert message in " ".join(capsys.readouterr().err.split())


def test_alternative_settings_are_checked_like_the_service_does() -> None:
    config = {"learner": {"eps": 0.1}, "frame": "feedback"}
    assert alternative_settings(config, {"decoder": "student_t"}).decoder == "student_t"
    assert alternative_settings(config, {"shrinkage": 1}).shrinkage == 1  # ints are floats
    with pytest.raises(ValueError, match="n_folds' must be an integer"):
        alternative_settings(config, {"n_folds": 5.0})
    with pytest.raises(ValueError, match="at least one key=value"):
        alternative_settings(config, {})


def test_publish_to_a_live_service_reproduces_the_recorded_moves(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    original = read_recording(recorded)
    altered = read_recording(recorded)
    moves = [m for _, m in altered.messages["/move"]]
    moves[24]["action"] = "goal" if moves[24]["action"] != "goal" else "up"
    rewrite(altered, tmp_path / "altered.mcap")

    endpoint = free_tcp_endpoint()
    record_dir = tmp_path / "service"
    runs = {"fast": "0", "paced": "4", "bad": "inf"}
    with service_process(endpoint, record_dir):
        for session, speed in runs.items():
            source = tmp_path / "altered.mcap" if session == "bad" else recorded
            code = main([
                "replay", str(source), "--publish", "--connect", endpoint, "--speed", speed,
                "--session", session, "--json", str(tmp_path / f"{session}.json"),
            ])
            assert code == (1 if session == "bad" else 0), session
    out = capsys.readouterr().out
    assert "moves equal the recorded moves: yes (60 moves)" in out
    assert "moves equal the recorded moves: no" in out

    for session in ("fast", "paced"):
        report = json.loads((tmp_path / f"{session}.json").read_text())
        assert report["moves_equal"] and report["states_equal"], report
        assert (report["epochs"], report["truths"]) == (STEPS, STEPS)
        assert (report["moves_received"], report["states_received"]) == (STEPS, STEPS + 1)
        assert report["speed"] == (4.0 if session == "paced" else None)

        republished = read_recording(record_dir / f"{session}.mcap")
        assert not republished.truncated
        assert republished.config["dataset"]["replayed_from"] == str(recorded)
        assert republished.config["seed"] == SEED
        # The same epochs and truth went out, with fresh sequence numbers and times ...
        for topic in ("/epoch", "/truth"):
            sent, kept = republished.messages[topic], original.messages[topic]
            assert [m["seq"] for _, m in sent] == list(range(STEPS))
            assert [m["t_ns"] for _, m in sent] != [m["t_ns"] for _, m in kept]
        assert [decode_array(m).tobytes() for _, m in republished.messages["/epoch"]] == [
            decode_array(m).tobytes() for _, m in original.messages["/epoch"]
        ]
        assert [(m["step"], m["target"], m["label"]) for _, m in republished.messages["/truth"]] \
            == [(m["step"], m["target"], m["label"]) for _, m in original.messages["/truth"]]
        # ... and the service made the recorded decisions.
        assert replay_check(record_dir / f"{session}.mcap").divergence is None
        assert np.array_equal(_recorded_confidences(republished), _recorded_confidences(original))

    bad = json.loads((tmp_path / "bad.json").read_text())
    assert not bad["moves_equal"] and bad["moves_received"] == STEPS
    divergence = bad["moves_divergence"]
    assert (divergence["step"], divergence["field"]) == (25, "action")
