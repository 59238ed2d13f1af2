"""A self-contained HTML report of recorded sessions: one file, images embedded.

`write_html` writes ``index.html`` with an aggregate table at the top (the metrics
of the reported sessions' worlds), then one section per session: a warning banner when
the recording is truncated (saying where it ends) or its re-run diverged, its metrics
table (with its seed, dataset and decision rules), its learner settings against the
defaults (the others folded away), and every figure with its caption. The
PNG files are embedded as base64 ``data:`` URIs, so the single file still works when moved
or mailed; each ``<img>`` also names its file in ``data-file``.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from calibration_free.task_decoders import DEFAULT_FOLDS
from replay.calibration import CalibrationPanel
from replay.figures import SavedFigure, rules_text
from replay.metrics import SCALAR_METRICS, SessionMetrics, SessionSettings, metric_applies

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px;
       padding: 0 1em; color: #222; line-height: 1.4; }
h1 { font-size: 1.6em; } h2 { font-size: 1.3em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
th { background: #f0f0f0; }
.warning { background: #fff3cd; border: 1px solid #e0b000; padding: 0.6em 1em;
           margin: 0.8em 0; border-radius: 4px; }
.error { background: #f8d7da; border: 1px solid #c0392b; padding: 0.6em 1em;
         margin: 0.8em 0; border-radius: 4px; }
figure { margin: 1.5em 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { font-size: 0.9em; color: #444; max-width: 60em; }
dl dt { font-weight: bold; margin-top: 0.5em; } dl dd { margin-left: 1.5em; }
tr.changed td { background: #fff3cd; font-weight: bold; }
details { margin: 0.5em 0 1.5em; } summary { cursor: pointer; }
"""

#: The definitions a reader needs, shown under the aggregate table.
DEFINITIONS: dict[str, str] = {
    "Step": "One device action, answered by one epoch (the user's reaction).",
    "Declared target": "The world's declaration action (the grid's goal) performed while "
    "confident; correct when the state was that of the user's target task at that step "
    "(recorded truth; in a grid, the same cell). Without recorded truth (a session with a "
    "person), the operator's marks: from a mark on, the user's target is the marked one "
    "until the next mark; a target declared before the first mark is unverified.",
    "Steps per correct target": "Steps recorded divided by correct targets (first search "
    "included).",
    "Mean steps between targets": "Mean number of steps between successive declared "
    "targets (correct or wrong); the first search is excluded (see first target step).",
    "Decoder accuracy vs truth": "The learner is re-run over the recording; after t signals, "
    "the out-of-fold predictions (the session's n_folds-fold cross-validation, "
    f"{DEFAULT_FOLDS} by default) of its most likely task's decoder for those t signals "
    "(argmax of the cross-validated class probabilities) are compared with the recorded "
    "true labels: mean recall over the true classes present.",
    "Self-estimate": "The same cross-validated balanced accuracy as recorded by the learner, "
    "against the labels its most likely task hypothesises (what the learner can know).",
    "Decision rule": "The confidence rule in force at a step (pairwise: the pairwise-min W "
    "of the scores; normalised: the normalised likelihood, while the evidence is calibrated) "
    "and its threshold, from the session's settings as the re-run of the learner applies "
    "them. A target is declared when the best task's confidence exceeds the threshold (more "
    "before the first target while the history is short: first_target_signals).",
    "Learner settings": "Every setting the session's learner ran with, as recorded; "
    "highlighted, those that differ from this version's defaults for the session's world "
    "and frame.",
    "Update latency": "The learner's time per step recorded by the service: observe the "
    "epoch + propose the next move, ms; median, 90th and 99th percentiles (linear "
    "interpolation) and maximum.",
}


@dataclass
class SessionReport:
    """One recording's part of the report.

    Attributes
    ----------
    file : str
        Path of the recording.
    stem : str
        Unique name of the session in the report (prefix of its PNG files, HTML anchor).
    metrics : SessionMetrics or None
        None when the file could not be processed.
    figures : list of SavedFigure
    error : str or None
        Why the file could not be processed (naming it).
    """

    file: str
    stem: str
    metrics: SessionMetrics | None = None
    figures: list[SavedFigure] = field(default_factory=list)
    error: str | None = None


def _format(value: object, digits: int = 3) -> str:
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.0f}"
    return str(value)


def _cell(value: object) -> str:
    """A table cell of a value, numbers right-aligned."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    cls = ' class="num"' if number else ""
    return f"<td{cls}>{html.escape(_format(value))}</td>"


def _table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = ["<tr>" + "".join(_cell(value) for value in row) + "</tr>" for row in rows]
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def aggregate_table(aggregate: dict[str, dict[str, float | int | None]]) -> str:
    """The aggregate table: one row per scalar metric, median / min / max / n."""
    rows = [
        [f"{name} ({meaning})", *(aggregate[name][k] for k in ("median", "min", "max", "n"))]
        for name, meaning in SCALAR_METRICS.items()
        if name in aggregate
    ]
    return _table(["metric", "median", "min", "max", "sessions"], rows)


def metrics_table(metrics: SessionMetrics) -> str:
    """One session's metrics, name and value: those of its world
    (`replay.metrics.metric_applies`)."""
    latency = metrics.latency
    settings = metrics.settings
    rules = metrics.decision_rules()
    # (the scalar metric a row shows, or None for a row of every world; name; value)
    rows: list[tuple[str | None, str, object]] = [
        (None, "session", metrics.session),
        (None, "file", metrics.file),
        *([(None, "seed", settings.seed), (None, "dataset", dataset_text(settings.dataset))]
          if settings is not None else []),
        (None, "world / frame / signal",
         f"{metrics.world_text} / {metrics.frame} / {metrics.signal}"),
        *([(None, "decision rule > threshold (steps)",
            ", ".join(f"{rule} > {threshold:g} ({steps})" for rule, threshold, steps in rules)
            if rules else rules_text(metrics))] if metrics.beta is not None else []),
        (None, "steps recorded (configured)", f"{metrics.steps} ({metrics.configured_steps})"),
        *([(None, "truth the targets are judged by", metrics.truth)]
          if metrics.truth is not None else []),
        ("first_target_step", "first target step", metrics.first_target_step),
        ("correct_targets", "targets correct / wrong / unverified",
         f"{metrics.correct_targets} / {metrics.wrong_targets} / {metrics.unverified_targets}"),
        ("steps_per_correct_target", "steps per correct target",
         metrics.steps_per_correct_target),
        ("mean_steps_between_targets", "mean steps between targets",
         metrics.mean_steps_between_targets),
        ("final_accuracy_truth", "decoder balanced accuracy vs truth, last step",
         metrics.final_accuracy_truth),
        ("final_accuracy_self", "decoder balanced accuracy, self-estimate, last step",
         metrics.final_accuracy_self),
        ("final_accuracy_truth", "chance level", metrics.chance),
        ("final_distance", "the best particle's distance to the goal, last step",
         metrics.final_distance),
        (None, "update latency median / p90 / p99 / max (ms)",
         "–" if latency is None else
         f"{latency.median_ms:.2f} / {latency.p90_ms:.2f} / {latency.p99_ms:.2f} / "
         f"{latency.max_ms:.2f} (n = {latency.n})"),
        ("final_taught_likelihood", "taught task's normalised likelihood at the updates",
         ", ".join(f"{v:.3g} @{k}" for k, v in zip(metrics.update_steps or [],
                                                    metrics.taught_likelihood or [], strict=True)
                   if v is not None) or "–"),
        ("goals_reached", "restarts (goal cell reached)", metrics.goals_reached),
        (None, "re-run identical to the recording", metrics.replay_identical),
        (None, "truncated", metrics.truncated),
    ]
    return _table(["metric", "value"], [
        [name, value] for metric, name, value in rows
        if metric is None or metric_applies(metric, metrics.world)])


def dataset_text(dataset: dict[str, object]) -> str:
    """The recorded ``dataset`` object as ``key: value`` pairs (a value repeating the
    description left out)."""
    description = dataset.get("description")
    return "; ".join(f"{key}: {_format(value)}" for key, value in dataset.items()
                     if key == "description" or value != description) or "–"


def settings_section(settings: SessionSettings) -> str:
    """The learner settings of a session: those that differ from the defaults named in a
    line, then every setting with its default in a folded table, the differing ones
    highlighted (``tr.changed``)."""
    if not settings.defaults:
        intro = ("The recorded learner settings are not valid in this version: they are "
                 "shown as recorded, without defaults.")
    elif settings.non_default:
        intro = "Learner settings that differ from the defaults: " + ", ".join(
            f"{name} = {_format(settings.learner[name])} (default "
            f"{_format(settings.defaults[name])})" for name in settings.non_default) + "."
    else:
        intro = "Every learner setting is the default for the session's world and frame."
    rows = []
    for name, value in settings.learner.items():
        default = settings.defaults.get(name)
        cls = ' class="changed"' if name in settings.non_default else ""
        rows.append(f"<tr{cls}><td>{html.escape(name)}</td>{_cell(value)}{_cell(default)}</tr>")
    return (
        f"<p>{html.escape(intro)}</p><details><summary>All {len(settings.learner)} learner "
        "settings (value, default)</summary><table><tr><th>setting</th><th>value</th>"
        f"<th>default</th></tr>{''.join(rows)}</table></details>"
    )


def _image(figure: SavedFigure) -> str:
    data = base64.b64encode(figure.path.read_bytes()).decode("ascii")
    return (
        f'<img src="data:image/png;base64,{data}" alt="{html.escape(figure.title)}" '
        f'data-file="{html.escape(figure.path.name)}">'
    )



def shortened_banner(metrics: SessionMetrics) -> str:
    """The warning of a recording cut short (its writer did not close it) or damaged (a
    region unreadable: the report covers the steps before it, or all of them when the
    damage broke none), as HTML."""
    warning = html.escape(metrics.warning or "")
    if metrics.damage is None:
        return (f"<b>Truncated recording</b> (its writer did not close it): {warning}. "
                "The report covers what it holds.")
    notes = "; ".join(html.escape(note) for note in metrics.damage.get("notes", []))
    covers = ("the steps before the damage" if metrics.damage.get("stop") is not None
              else "every step (the damage broke none)")
    return (f"<b>Damaged recording</b>: {warning}" + (f"; {notes}" if notes else "")
            + f". The report covers {covers}.")

def session_section(report: SessionReport, first_figure: int) -> str:
    """The HTML section of one session; figures numbered from ``first_figure``."""
    anchor = html.escape(report.stem)
    if report.metrics is None:
        return (
            f'<section id="{anchor}"><h2>{html.escape(report.file)}</h2>'
            f'<div class="error"><b>Not processed:</b> {html.escape(report.error or "")}</div>'
            "</section>"
        )
    metrics = report.metrics
    parts = [f'<section id="{anchor}"><h2>Session {html.escape(metrics.session)} '
             f'<small>({html.escape(report.file)})</small></h2>']
    if metrics.truncated or metrics.damage is not None:
        parts.append(f'<div class="warning">{shortened_banner(metrics)}</div>')
    if metrics.replay_identical is False or (
        metrics.replay_identical is None and metrics.replay_note
    ):
        parts.append(
            '<div class="warning"><b>The re-run of the learner differs from the recording'
            f"</b> (decoder accuracy vs truth may not be the session's): "
            f"{html.escape(metrics.replay_note or '')}</div>"
        )
    parts.append(metrics_table(metrics))
    if metrics.settings is not None:
        parts.append(settings_section(metrics.settings))
    for number, figure in enumerate(report.figures, start=first_figure):
        parts.append(
            f'<figure id="{anchor}-{figure.kind}">{_image(figure)}<figcaption>'
            f"<b>Figure {number}. {html.escape(figure.title)}.</b> "
            f"{html.escape(figure.caption)}</figcaption></figure>"
        )
    parts.append("</section>")
    return "\n".join(parts)


def calibration_section(figure: SavedFigure, panels: Sequence[CalibrationPanel]) -> str:
    """The confidence calibration, all steps pooled and per decision rule: a text naming
    the rules and thresholds of the panels, the figure, and a table with two columns
    (steps, fraction right) per panel, titled for what it counts, and each rule's steps
    above its threshold."""

    def cell(steps: int, right: float | None) -> str:
        return f"<td>{steps}</td><td>{'-' if right is None else f'{right:.3f}'}</td>"

    head = "".join(f'<th colspan="2">{html.escape(p.title)}</th>' for p in panels)
    sub = "<th>steps</th><th>fraction right</th>" * len(panels)
    rows = "".join(
        f"<tr><td>{bins[0].low:.1f}-{bins[0].high:.1f}</td>"
        + "".join(cell(b.steps, b.fraction_right) for b in bins) + "</tr>"
        for bins in zip(*(p.curve for p in panels), strict=True)
    )
    above = "".join(
        "<td></td><td></td>" if p.above_threshold is None
        else cell(p.above_threshold[0],
                  p.above_threshold[1] / p.above_threshold[0] if p.above_threshold[0] else None)
        for p in panels
    )
    if any(p.above_threshold is not None for p in panels):
        rows += f"<tr><td>steps above the rule's threshold</td>{above}</tr>"
    rules = [p for p in panels if p.rule is not None]
    text = (
        "Per step, the best task's confidence before the step's action, binned, against "
        "whether that task was the user's target then: a calibrated confidence of 0.8 is "
        "right 80 % of the time."
    )
    if rules:
        text += (" The steps each decision rule decided also have their own panel (the "
                 "sessions the re-run reproduced): " + "; ".join(
                     f"the {p.rule} rule, threshold {p.threshold:g}, {p.steps} steps"
                     for p in rules) + ".")
    return (
        f"<h2>Confidence calibration (all sessions)</h2><p>{html.escape(text)}</p>"
        f'<figure id="confidence-calibration">{_image(figure)}</figure>'
        f"<table><tr><th>confidence</th>{head}</tr><tr><th></th>{sub}</tr>{rows}</table>"
    )


def render_html(
    reports: Sequence[SessionReport],
    aggregate: dict[str, dict[str, float | int | None]],
    calibration: tuple[SavedFigure, Sequence[CalibrationPanel]] | None = None,
) -> str:
    """The whole report as one HTML document (``calibration``: the calibration figure and
    its panels)."""
    done = [r for r in reports if r.metrics is not None]
    failed = [r for r in reports if r.metrics is None]
    shortened = [r for r in done if r.metrics is not None
                 and (r.metrics.truncated or r.metrics.damage is not None)]
    damaged = sum(r.metrics is not None and r.metrics.damage is not None for r in shortened)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        "<title>cfbci session report</title>",
        f"<style>{_STYLE}</style></head><body>",
        "<h1>Calibration-free BCI: session report</h1>",
        f"<p>{len(done)} session(s) reported"
        + (f", {len(shortened) - damaged} cut short" if len(shortened) > damaged else "")
        + (f", {damaged} damaged" if damaged else "")
        + (f", {len(failed)} file(s) not processed" if failed else "")
        + ".</p>",
    ]
    for report in failed:
        parts.append(f'<div class="error"><b>Not processed:</b> {html.escape(report.error or "")}'
                     "</div>")
    for report in shortened:
        assert report.metrics is not None
        parts.append(f'<div class="warning">{shortened_banner(report.metrics)}</div>')
    parts.append("<h2>Aggregate over sessions</h2>")
    parts.append(aggregate_table(aggregate))
    if calibration is not None:
        parts.append(calibration_section(*calibration))
    parts.append("<h3>Definitions</h3><dl>")
    for term, text in DEFINITIONS.items():
        parts.append(f"<dt>{html.escape(term)}</dt><dd>{html.escape(text)}</dd>")
    parts.append("</dl><h3>Sessions</h3><ul>")
    for report in reports:
        name = report.metrics.session if report.metrics else report.file
        parts.append(f'<li><a href="#{html.escape(report.stem)}">{html.escape(name)}</a> '
                     f"({html.escape(report.file)})</li>")
    parts.append("</ul>")
    number = 1
    for report in reports:
        parts.append(session_section(report, number))
        number += len(report.figures)
    parts.append("</body></html>")
    return "\n".join(parts)


def write_html(
    out_dir: Path,
    reports: Sequence[SessionReport],
    aggregate: dict[str, dict[str, float | int | None]],
    calibration: tuple[SavedFigure, Sequence[CalibrationPanel]] | None = None,
) -> Path:
    """Write ``out_dir/index.html`` (see the module docstring); return its path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "index.html"
    path.write_text(render_html(reports, aggregate, calibration), encoding="utf-8")
    return path
