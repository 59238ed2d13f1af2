"""``cfbci report`` of a session with a person: no ``/truth``, the operator's marks instead.

The recordings are written in-process as the service would record them (`write_real`):
the same session twice, once with the simulated user's ``/truth`` and once with, in its
place, the ``target_marked`` events of an operator who marks the user's target at a step
and each new target at the step after the previous one was declared (what ``cfbci
control target`` records, docs/protocol.md, "Operator controls").
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import pytest
from test_report import write_real

from cfbci.cli import main
from cfbci.recordings.reanalysis import recorded_history
from replay.metrics import (
    SIMULATED_TRUTH,
    SessionMetrics,
    operator_marks,
    session_metrics,
    session_truth,
)
from replay.recording import read_recording
from replay.rerun import replay_check

SEED, STEPS, GRID = 5, 90, 3


def _metrics(path: Path, marks_from: int | None) -> SessionMetrics:
    write_real(path, SEED, STEPS, GRID, marks_from=marks_from)
    return session_metrics(read_recording(path), str(path))


@pytest.fixture(scope="module")
def by_truth(tmp_path_factory: pytest.TempPathFactory) -> SessionMetrics:
    return _metrics(tmp_path_factory.mktemp("truth") / "truth.mcap", None)


def test_marks_from_the_first_step_judge_every_target_as_the_truth_does(
    tmp_path: Path, by_truth: SessionMetrics
) -> None:
    path = tmp_path / "marked.mcap"
    marked = _metrics(path, marks_from=1)
    recording = read_recording(path)
    assert not recording.messages.get("/truth")
    marks = operator_marks(recording)
    declared = [t.step for t in by_truth.targets]
    assert len(declared) >= 2  # the session has targets to judge, the later ones re-marked
    assert [step for step, _ in marks] == [1] + [s + 1 for s in declared if s < STEPS]
    assert marked.targets == by_truth.targets
    assert marked.unverified_targets == 0
    assert (marked.correct_targets, marked.wrong_targets) == (
        by_truth.correct_targets, by_truth.wrong_targets)
    assert marked.true_target == by_truth.true_target
    assert marked.confidence_true == by_truth.confidence_true
    assert marked.calibration_counts == by_truth.calibration_counts
    assert by_truth.truth == SIMULATED_TRUTH
    assert marked.truth is not None and marked.truth.startswith(
        f"the operator's marks ({len(marks)} marks, the first at step 1: every step has one")
    # The marks give targets, not the epochs' classes: no accuracy against the truth.
    assert marked.accuracy_truth == [None] * STEPS and marked.final_accuracy_truth is None
    assert marked.accuracy_self == by_truth.accuracy_self
    # The learner never reads a mark: the recording replays as the service ran it.
    assert replay_check(path).divergence is None and marked.replay_identical


def test_steps_before_the_first_mark_have_no_truth_and_their_targets_are_unverified(
    tmp_path: Path, by_truth: SessionMetrics
) -> None:
    first = by_truth.targets[0].step + 1  # marked only after the first declared target
    marked = _metrics(tmp_path / "late.mcap", marks_from=first)
    assert marked.true_target[: first - 1] == [None] * (first - 1)
    assert marked.true_target[first - 1:] == by_truth.true_target[first - 1:]
    before = [t for t in marked.targets if t.step < first]
    after = [t for t in marked.targets if t.step >= first]
    assert len(before) == 1 and before[0].true_target is None and before[0].correct is None
    assert after == [t for t in by_truth.targets if t.step >= first] and after
    assert marked.unverified_targets == 1
    assert marked.correct_targets == sum(t.correct is True for t in after)
    assert marked.wrong_targets == sum(t.correct is False for t in after)
    assert f"the first at step {first}: steps 1 to {first - 1} have no truth" in (
        marked.truth or "")


def test_a_mark_holds_until_the_next_one_whatever_the_declarations(tmp_path: Path) -> None:
    """An operator who marks once: every later step's truth is that mark."""
    path = tmp_path / "marked.mcap"
    write_real(path, SEED, STEPS, GRID, marks_from=1)
    recording = read_recording(path)
    events = recording.messages["/event"]
    first_mark = next(m for _, m in events if m["event"] == "target_marked")
    recording.messages["/event"] = [
        (t, m) for t, m in events if m["event"] != "target_marked" or m is first_mark]
    truth, text = session_truth(recording, list(range(1, STEPS + 1)))
    assert {step: fields["target"] for step, fields in truth.items()} == {
        step: first_mark["target"] for step in range(1, STEPS + 1)}
    assert text.startswith("the operator's marks (1 mark, the first at step 1")


def test_cfbci_report_states_the_truth_it_judged_targets_by(
    tmp_path: Path, by_truth: SessionMetrics, capsys: pytest.CaptureFixture[str]
) -> None:
    first = by_truth.targets[0].step + 1
    marked, simulated = tmp_path / "marked.mcap", tmp_path / "simulated.mcap"
    write_real(marked, SEED, STEPS, GRID, marks_from=first)
    write_real(simulated, SEED, STEPS, GRID)
    out = tmp_path / "report"
    assert main(["report", str(marked), str(simulated), "--out", str(out), "--jobs", "1"]) == 0
    printed = capsys.readouterr().out.replace("\n", "")
    document = json.loads((out / "metrics.json").read_text())
    sessions = {s["stem"]: s for s in document["sessions"]}
    n_marks = len(operator_marks(read_recording(marked)))
    assert sessions["marked"]["truth"].startswith(f"the operator's marks ({n_marks} marks")
    assert sessions["simulated"]["truth"] == SIMULATED_TRUTH
    assert sessions["marked"]["unverified_targets"] == 1
    assert sessions["marked"]["correct_targets"] + sessions["marked"]["wrong_targets"] == sum(
        t.step >= first for t in by_truth.targets)
    assert f"truth: the operator's marks ({n_marks} marks" in printed
    page = (out / "index.html").read_text()
    assert "truth the targets are judged by" in page
    assert html.escape(f"the operator's marks ({n_marks} marks") in page
    assert html.escape(SIMULATED_TRUTH) in page


def test_the_reanalysis_takes_the_users_targets_from_the_marks(tmp_path: Path) -> None:
    """``cfbci replay --compare`` scores its settings against the user's target of every
    step: from the operator's marks where there is no ``/truth``, the same targets as the
    simulated user's truth when the marks follow it from step 1 (None before a first mark)."""
    truth, marked, late = (tmp_path / f"{n}.mcap" for n in ("truth", "marked", "late"))
    write_real(truth, SEED, STEPS, GRID)
    write_real(marked, SEED, STEPS, GRID, marks_from=1)
    targets = recorded_history(read_recording(truth)).targets
    assert None not in targets
    assert recorded_history(read_recording(marked)).targets == targets
    first = 10
    write_real(late, SEED, STEPS, GRID, marks_from=first)
    late_targets = recorded_history(read_recording(late)).targets
    assert late_targets[: first - 1] == [None] * (first - 1)
    assert None not in late_targets[first - 1:]
