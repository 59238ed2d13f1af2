"""``cfbci report`` says what it shows: each session's own thresholds, rules, dataset, seed
and learner settings; calibration panels titled for what they count; the aggregate rows of
the sessions' worlds only; figures readable at a paper's width; feature vectors drawn per
channel where their layout is known.

Recordings are made in-process (`test_report`'s writers: the learner and a simulated
user as the service runs them, or hand-built ones whose every value is known).
"""

from __future__ import annotations

import dataclasses
import html
import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.text import Text
from test_report import write_hand_built, write_real

from calibration_free.config import DEFAULT_BETA, LearnerConfig
from calibration_free.learner import first_target_requirement
from calibration_free.puddle import puddle_tasks
from cfbci.cli import main
from cfbci.recordings.report import ReportJob, report_session
from replay.calibration import (
    CalibrationPanel,
    calibration_counts,
    calibration_curve,
    counts_by_rule,
    rule_summary,
)
from replay.figures import (
    SavedFigure,
    accuracy_figure,
    belief_figure,
    calibration_figure,
    confidence_figure,
    erp_figure,
    latency_figure,
)
from replay.html_report import aggregate_table, calibration_section, metrics_table
from replay.metrics import aggregate, session_metrics
from replay.plane_report import cloud_figure, distance_figure, probes_figure
from replay.puddle_report import likelihood_figure, trajectory_figure
from replay.recording import Recording, read_recording
from replay.rerun import recompute

#: The widest a figure is printed in a paper, inches: the text width of a one-column
#: paper (a two-column paper's figure spanning both columns is wider, about 7 in).
PRINT_WIDTH = 6.5
#: The smallest font readable in print, points.
SMALLEST_FONT = 8.0
#: The smallest side of a belief map in print, inches.
SMALLEST_MAP = 1.6
#: Learner settings away from the defaults: a threshold that is not the frame's, and
#: calibrated segments early enough for a 90-step session to have some.
CUSTOM = {"beta": 0.95, "calibration_signals": 30}


@pytest.fixture(scope="module")
def custom(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("custom") / "custom.mcap"
    write_real(path, settings_given=CUSTOM)
    return path


@pytest.fixture(scope="module")
def custom_metrics(custom: Path) -> Any:
    return session_metrics(read_recording(custom), str(custom))


@pytest.fixture(scope="module")
def reported(custom: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``cfbci report`` of the custom recording: the output folder."""
    out = tmp_path_factory.mktemp("report") / "report"
    assert main(["report", str(custom), "--out", str(out), "--jobs", "1"]) == 0
    return out


def hand_metrics(tmp_path: Path, **fields: Any) -> tuple[Recording, Any]:
    path = tmp_path / "hand.mcap"
    write_hand_built(path, **fields)
    recording = read_recording(path)
    return recording, session_metrics(recording, str(path), rerun=False)


def png(tmp_path: Path) -> SavedFigure:
    """A saved figure (any PNG: the HTML only embeds it)."""
    path = tmp_path / "x.png"
    Figure(figsize=(1, 1)).savefig(path)
    return SavedFigure("confidence_calibration", path, "", "")


def calibration_paragraph(page: str) -> str:
    """The text under the calibration heading, up to its figure."""
    match = re.search(r"Confidence calibration \(all sessions\)</h2>(.*?)<figure", page, re.S)
    assert match is not None
    return html.unescape(re.sub(r"<[^>]+>", "", match.group(1)))


# -- thresholds: the sessions' own, from their configuration and the re-run ----------------


def test_each_steps_rule_and_threshold_are_the_re_runs_and_drawn_as_such(
    custom: Path, custom_metrics: Any
) -> None:
    m = custom_metrics
    assert m.replay_identical is True and m.beta == CUSTOM["beta"]
    _, states, _ = recompute(read_recording(custom))
    assert m.decision_rule == [s["rule"] for s in states[: m.steps]]
    assert m.decision_threshold == [s["threshold"] for s in states[: m.steps]]
    # Both rules, each with the session's threshold (none of them the frame's default).
    assert set(zip(m.decision_rule, m.decision_threshold, strict=True)) == {
        ("pairwise", 0.95), ("normalised", LearnerConfig().calibrated_beta)}
    # The confidence a target needs: the threshold, more before the first target (the
    # first state, before any signal, has none recorded by the re-run).
    first = m.first_target_step
    signals = LearnerConfig().frame_first_target_signals
    assert m.target_requirement[0] is None
    for k in range(2, m.steps + 1):
        threshold = m.decision_threshold[k - 1]
        expected = first_target_requirement(threshold, k - 1, signals) if k <= first else (
            threshold)
        assert m.target_requirement[k - 1] == pytest.approx(expected)

    figure = confidence_figure(m)
    [ax] = figure.axes
    requirement = np.asarray(m.target_requirement, dtype=float)
    drawn = [line for line in ax.get_lines() if len(line.get_ydata()) == m.steps and np.allclose(
        np.asarray(line.get_ydata(), dtype=float), requirement, equal_nan=True)]
    assert len(drawn) == 1
    assert all(not np.allclose(line.get_ydata(), DEFAULT_BETA["feedback"])
               for line in ax.get_lines())  # the default is not the session's
    legend = " ".join(t.get_text() for t in figure.legends[0].get_texts())
    assert "0.95" in legend and "0.995" in legend


def test_the_report_states_the_sessions_thresholds_never_a_typed_one(
    reported: Path, custom_metrics: Any
) -> None:
    page = (reported / "index.html").read_text()
    paragraph = calibration_paragraph(page)
    assert "0.95" in paragraph and "0.995" in paragraph
    assert "0.9 " not in paragraph and "0.9;" not in paragraph and "0.93" not in paragraph
    # The session's table names its rules with their thresholds and steps.
    rules = dict.fromkeys(zip(custom_metrics.decision_rule, custom_metrics.decision_threshold,
                              strict=True))
    row = re.search(r"<td>decision rule &gt; threshold \(steps\)</td><td>([^<]*)</td>", page)
    assert row is not None
    for rule, threshold in rules:
        steps = sum(r == rule for r in custom_metrics.decision_rule)
        assert f"{rule} &gt; {threshold:g} ({steps})" in row.group(1)
    document = json.loads((reported / "metrics.json").read_text())
    session = document["sessions"][0]
    assert session["decision_threshold"] == custom_metrics.decision_threshold
    assert session["beta"] == CUSTOM["beta"]


def test_the_calibration_text_names_only_the_rules_that_decided(tmp_path: Path) -> None:
    counts = counts_by_rule([0.95, 0.5], [True, False], [("pairwise", 0.92)] * 2)
    panels = [CalibrationPanel(calibration_curve(counts[0].counts)),
              *[CalibrationPanel.of_rule_summary(rule_summary(c)) for c in counts]]
    paragraph = calibration_paragraph(calibration_section(png(tmp_path), panels))
    assert "0.92" in paragraph
    assert "0.995" not in paragraph and "normalised" not in paragraph


def test_a_recording_whose_settings_cannot_be_read_has_its_frames_default_threshold(
    tmp_path: Path,
) -> None:
    _, m = hand_metrics(tmp_path, frame="guidance", learner={"no_such_setting": 1})
    assert m.beta == DEFAULT_BETA["guidance"]


# -- the calibration panels: titled for what they count ------------------------------------


def test_calibration_panels_are_titled_for_the_steps_they_count(tmp_path: Path) -> None:
    confidence = [0.95, 0.5, 0.6, 0.99, 0.3, 0.97]
    right = [True, False, True, True, False, True]
    rules = [("pairwise", 0.93)] * 4 + [("normalised", 0.995)] * 2
    counts = counts_by_rule(confidence, right, rules)
    pooled = CalibrationPanel(calibration_curve(calibration_counts(confidence, right)))
    panels = [pooled, *[CalibrationPanel.of_rule_summary(rule_summary(c)) for c in counts]]
    page = html.unescape(calibration_section(png(tmp_path), panels))
    # Four steps decided by the pairwise rule, two of them above its threshold.
    assert "steps decided by the pairwise rule (threshold 0.93): 4" in page
    assert "steps decided by the normalised rule (threshold 0.995): 2" in page
    assert "all steps: 6" in page
    assert "pairwise > 0.93" not in page
    titles = [" ".join(ax.get_title().split()) for ax in calibration_figure(panels).axes
              if ax.get_visible()]
    assert titles == ["all steps: 6", "steps decided by the pairwise rule (threshold 0.93): 4",
                      "steps decided by the normalised rule (threshold 0.995): 2"]


# -- dataset, seed and learner settings ------------------------------------------------------


def test_each_sessions_dataset_seed_and_learner_settings_are_reported(reported: Path) -> None:
    document = json.loads((reported / "metrics.json").read_text())
    settings = document["sessions"][0]["settings"]
    recorded = LearnerConfig.from_dict({"frame": "feedback", **CUSTOM}).to_dict()
    assert settings["seed"] == 5
    assert settings["dataset"] == {"description": "synthetic"}
    assert settings["learner"] == recorded
    assert settings["defaults"] == LearnerConfig().to_dict()
    assert settings["non_default"] == sorted(CUSTOM)

    page = (reported / "index.html").read_text()
    assert re.search(r"<td>seed</td><td class=\"num\">5</td>", page)
    assert re.search(r"<td>dataset</td><td>description: synthetic</td>", page)
    for name, value in CUSTOM.items():  # highlighted, with the default beside
        default = LearnerConfig().to_dict()[name]
        assert re.search(rf'<tr class="changed"><td>{name}</td><td[^>]*>{value:g}</td>'
                         rf"<td[^>]*>{default:g}</td></tr>", page), name
    table = re.search(r"<details>(.*?)</details>", page, re.S)
    assert table is not None
    for name in recorded:
        assert f"<td>{name}</td>" in table.group(1)
    assert '<tr class="changed"><td>eps</td>' not in page


# -- the aggregate: each world's metrics only ------------------------------------------------


def test_the_aggregate_leaves_out_the_metrics_of_worlds_not_reported(tmp_path: Path) -> None:
    _, grid = hand_metrics(tmp_path)
    result = aggregate([grid])
    for name in ("final_distance", "final_taught_likelihood", "goals_reached"):
        assert name not in result
    table = aggregate_table(result)
    assert "continuous world" not in table and "puddle world" not in table
    assert "first_target_step" in table  # the grid's own, even where undefined

    puddle = dataclasses.replace(grid, world="puddle", goals_reached=2,
                                 final_taught_likelihood=0.5)
    assert "correct_targets" not in puddle.scalars()
    assert "final_distance" not in puddle.scalars()
    both = aggregate([grid, puddle])
    assert both["correct_targets"]["n"] == 1 and both["goals_reached"]["n"] == 1
    assert both["steps"]["n"] == 2 and "final_distance" not in both


def test_a_sessions_table_shows_the_metrics_of_its_world(tmp_path: Path) -> None:
    _, grid = hand_metrics(tmp_path)
    puddle = dataclasses.replace(grid, world="puddle", beta=None, goals_reached=2,
                                 update_steps=[3, 6], taught_likelihood=[0.25, 0.5])
    plane = dataclasses.replace(grid, world="continuous", beta=None, final_distance=0.125)
    tables = {m.world: metrics_table(m) for m in (grid, puddle, plane)}
    for name in ("targets correct", "decoder balanced accuracy", "chance level",
                 "decision rule"):
        assert name in tables["grid"]
        assert name not in tables["puddle"] and name not in tables["continuous"]
    assert "0.25 @3, 0.5 @6" in tables["puddle"] and "restarts" in tables["puddle"]
    assert "distance to the goal" in tables["continuous"] and "0.125" in tables["continuous"]
    assert "distance" not in tables["grid"] and "restarts" not in tables["grid"]


# -- figures readable at a paper's width ------------------------------------------------------


def line_recording() -> tuple[Recording, Any]:
    """A hand-built line-world session (2 tasks, states 0 and 4): its recording, measured."""
    config = {"seed": 0, "world": "line", "frame": "feedback", "steps": 4, "learner": {},
              "dataset": {"description": "hand-built"}, "signal": "features"}
    path = [(2, 1), (1, 0), (0, 0), (0, 1)]  # (from_state, to_state); declared at step 3
    messages: dict[str, list[tuple[int, dict[str, Any]]]] = {"/move": [], "/state": [],
                                                           "/truth": [], "/epoch": []}
    for k, (src, dst) in enumerate(path, start=1):
        messages["/move"].append((k, {"step": k, "from_state": src, "to_state": dst,
                                      "target_reached": k == 3}))
        confidence = [0.5 + 0.1 * k, 0.5 - 0.1 * k]
        messages["/state"].append((k, {"n_signals": k - 1, "best_task": 0,
                                       "confidence": confidence}))
        messages["/truth"].append((k, {"step": k, "target": 0, "label": 0}))
    recording = Recording("line", config, messages, False, 0, None, "line.mcap")
    return recording, session_metrics(recording, rerun=False)


def plane_recording(grid_metrics: Any) -> tuple[Recording, Any]:
    """A hand-built continuous-world session: 10 probes, 6 particles."""
    rng = np.random.default_rng(1)
    moves = [(k, {"step": k, "to_state": rng.uniform(size=2).tolist()}) for k in range(1, 11)]
    states = [(k, {"points": rng.uniform(size=(6, 2)).tolist(), "best_task": k % 6,
                   "confidence": rng.uniform(size=6).tolist()}) for k in range(11)]
    truth = [(k, {"step": k, "target": [0.3, 0.7]}) for k in range(1, 11)]
    recording = Recording("plane", {"world": "continuous", "frame": "cardinal", "steps": 10},
                          {"/move": moves, "/state": states, "/truth": truth}, False, 0, None,
                          "plane.mcap")
    metrics = dataclasses.replace(grid_metrics, world="continuous", grid=None, beta=None,
                                  distance=[0.5 / k for k in range(1, 11)])
    return recording, metrics


def puddle_recording(grid_metrics: Any) -> tuple[Recording, Any]:
    """A hand-built puddle-world session: 12 moves of task 3."""
    rng = np.random.default_rng(2)
    points = rng.uniform(size=(13, 2))
    moves = [(k, {"step": k, "from_state": points[k - 1].tolist(),
                  "to_state": points[k].tolist()}) for k in range(1, 13)]
    recording = Recording("puddle", {"world": "puddle", "frame": "mixed", "steps": 12},
                          {"/move": moves}, False, 0, None, "puddle.mcap")
    n_tasks = len(puddle_tasks())
    metrics = dataclasses.replace(
        grid_metrics, world="puddle", grid=None, beta=None, n_tasks=n_tasks,
        true_target=[3] * 12, confidence_true=[0.1 * k / 12 for k in range(1, 13)],
        confidence_best_other=[0.05] * 12, update_steps=[4, 8, 12],
        taught_likelihood=[0.03, 0.06, 0.1], restarts=[6])
    return recording, metrics


def undrawn_tick_labels(figure: Figure) -> set[int]:
    """The ``id`` of every tick label outside its axis's view (kept, not drawn)."""
    ids = set()
    for ax in figure.axes:
        for axis in (ax.xaxis, ax.yaxis):
            low, high = sorted(axis.get_view_interval())
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                if not low - 1e-9 <= tick.get_loc() <= high + 1e-9:
                    ids |= {id(tick.label1), id(tick.label2)}
    return ids


def check_readable(figure: Figure, name: str) -> None:
    """Every text of ``figure`` at least `SMALLEST_FONT` points, within the figure
    and clear of the others, and every belief map at least `SMALLEST_MAP` inches a
    side, once printed `PRINT_WIDTH` wide (or less)."""
    figure.draw_without_rendering()
    scale = min(1.0, PRINT_WIDTH / figure.get_figwidth())
    undrawn = undrawn_tick_labels(figure)
    texts = [t for t in figure.findobj(Text) if t.get_visible() and t.get_text().strip()
             and id(t) not in undrawn]
    small = sorted({(t.get_text(), t.get_fontsize() * scale) for t in texts
                    if t.get_fontsize() * scale < SMALLEST_FONT - 1e-9})
    assert not small, f"{name}: texts under {SMALLEST_FONT} pt in print: {small[:5]}"
    page = figure.bbox
    boxes = [(t.get_text(), t.get_window_extent().shrunk(0.98, 0.9)) for t in texts]
    outside = [text for text, box in boxes
               if box.x0 < page.x0 - 1 or box.x1 > page.x1 + 1 or box.y0 < page.y0 - 1
               or box.y1 > page.y1 + 1]
    assert not outside, f"{name}: texts cut at the figure's edge: {outside}"
    clashes = [(a, b) for i, (a, box) in enumerate(boxes) for b, other in boxes[i + 1:]
               if box.overlaps(other)]
    assert not clashes, f"{name}: texts over one another: {clashes[:5]}"
    for ax in figure.axes:
        if ax.images and ax.get_visible():
            box = ax.get_window_extent()
            side = min(box.width, box.height) / figure.dpi * scale
            assert side >= SMALLEST_MAP, f"{name}: a map {side:.2f} in a side in print"


def test_figures_are_readable_at_a_papers_width(
    tmp_path: Path, custom: Path, custom_metrics: Any
) -> None:
    recording, grid = hand_metrics(tmp_path)
    real_recording, real = read_recording(custom), custom_metrics
    (tmp_path / "layout").mkdir()
    laid_out, laid_out_metrics = hand_metrics(
        tmp_path / "layout", n_features=34,
        feature_layout={"ch_names": ["channel 1", "channel 2"], "n_times": 17})
    line, line_metrics = line_recording()
    plane, plane_metrics = plane_recording(grid)
    puddle, puddle_metrics = puddle_recording(grid)
    counts = counts_by_rule([0.95, 0.5, 0.99], [True, False, True],
                            [("pairwise", 0.93)] * 2 + [("normalised", 0.995)])
    panels = [CalibrationPanel(calibration_curve(
        calibration_counts([0.95, 0.5, 0.99], [True, False, True]))),
        *[CalibrationPanel.of_rule_summary(rule_summary(c)) for c in counts]]
    figures = {
        "confidence": confidence_figure(real),
        "belief (2 x 2)": belief_figure(recording, grid),
        "belief (3 x 3)": belief_figure(real_recording, real),
        "ranking": belief_figure(line, line_metrics),
        "accuracy": accuracy_figure(real),
        "erp (features)": erp_figure(recording, grid)[0],
        "erp (raw)": erp_figure(real_recording, real)[0],
        "erp (features per channel)": erp_figure(laid_out, laid_out_metrics)[0],
        "latency": latency_figure(real),
        "calibration": calibration_figure(panels),
        "distance": distance_figure(plane_metrics),
        "particles": cloud_figure(plane, plane_metrics),
        "probes": probes_figure(plane, plane_metrics),
        "likelihood": likelihood_figure(puddle_metrics),
        "trajectory": trajectory_figure(puddle, puddle_metrics),
    }
    for name, figure in figures.items():
        check_readable(figure, name)


# -- feature vectors drawn per channel --------------------------------------------------------


def class_lines(figure: Figure) -> list[Line2D]:
    """The class-mean and difference curves of an ERP figure (not its zero lines)."""
    return [line for ax in figure.axes for line in ax.get_lines()
            if len(line.get_xdata()) > 2 and line.get_label() and
            not line.get_label().startswith("_")]


def test_features_are_drawn_per_channel_where_the_layout_is_known(tmp_path: Path) -> None:
    layout = {"ch_names": ["C3", "C4"], "n_times": 3}
    recording, m = hand_metrics(tmp_path, n_features=6, feature_layout=layout)
    figure, what = erp_figure(recording, m)
    panels = [ax for ax in figure.axes if ax.get_visible()]
    assert [ax.get_title() for ax in panels] == ["C3 (features 0-2)", "C4 (features 3-5)"]
    lines = class_lines(figure)
    assert len(lines) == 2 * 3  # correct, error and difference in each channel
    assert all(list(line.get_xdata()) == [0, 1, 2] for line in lines)  # no line across
    assert "per channel" in what


def test_features_without_a_layout_are_drawn_as_one_vector(tmp_path: Path) -> None:
    recording, m = hand_metrics(tmp_path, n_features=6)
    figure, _ = erp_figure(recording, m)
    lines = class_lines(figure)
    assert len(lines) == 3 and all(len(line.get_xdata()) == 6 for line in lines)


def test_a_layout_that_does_not_fit_the_features_is_not_used(tmp_path: Path) -> None:
    recording, m = hand_metrics(tmp_path, n_features=6,
                                feature_layout={"ch_names": ["C3", "C4"], "n_times": 4})
    lines = class_lines(erp_figure(recording, m)[0])
    assert len(lines) == 3 and all(len(line.get_xdata()) == 6 for line in lines)


S4 = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "errp-features-s4" / "s4.mat"


@pytest.mark.skipif(not S4.is_file(), reason=f"{S4} is absent (see datasets/README.md)")
def test_a_recording_of_s4_is_drawn_per_channel(tmp_path: Path) -> None:
    """The pinned s4.mat (checked by its sha256) holds 2 channels x 17 samples per vector:
    its recordings' features are drawn per channel, though their config says nothing of it."""
    path = tmp_path / "s4-like.mcap"
    write_hand_built(path, n_features=34, dataset={"description": str(S4), "path": str(S4)})
    report = report_session(ReportJob(str(path), str(tmp_path / "out"), "s4-like"))
    [erp] = [f for f in report.figures if f.kind == "erp"]
    assert "per channel" in erp.caption
    # Another file at the path (not the pinned one) says nothing of its layout.
    other = tmp_path / "s4.mat"
    other.write_bytes(S4.read_bytes()[:-1] + b"\0")
    path2 = tmp_path / "other.mcap"
    write_hand_built(path2, n_features=34, dataset={"path": str(other)})
    report = report_session(ReportJob(str(path2), str(tmp_path / "out"), "other"))
    [erp] = [f for f in report.figures if f.kind == "erp"]
    assert "per channel" not in erp.caption
