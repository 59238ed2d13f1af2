"""``cfbci report FILE.mcap [...] --out DIR``: metrics, figures and an HTML report of sessions.

Every recording is one job (`report_session`, run on Dask by
`cfbci.offline.parallel.run_parallel`; on an existing cluster its workers must see the
recordings and the output directory at the same paths): read it (a truncated file gives
what it holds), measure it (`replay.metrics`, which re-runs the learner), and draw its
figures (`replay.figures`, ``DIR/<stem>_<kind>.png``; the feature vectors of a pinned
data set per channel, `pinned_feature_layout`, where the recording does not say their
layout). This process then writes
``DIR/metrics.json`` (per session and aggregate) and ``DIR/index.html``
(`replay.html_report`), and prints a summary. A file that cannot be processed (missing,
not MCAP, no configuration, ...) is reported by name; the others are still processed.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from rich import box
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from acquisition.fetch import DATASETS
from cfbci.offline.parallel import Scheduler, run_parallel
from replay.calibration import (
    CalibrationBin,
    CalibrationPanel,
    calibration_curve,
    pool_counts,
    pool_counts_by_rule,
    rule_summary,
)
from replay.extent import usable_part
from replay.figures import FeatureLayout, calibration_figure, save_figures, session_figures
from replay.html_report import SessionReport, write_html
from replay.metrics import SIMULATED_TRUTH, aggregate, session_metrics
from replay.plane_report import plane_figures, plane_metrics
from replay.puddle_report import puddle_figures, puddle_metrics
from replay.recording import read_recording
from session.plane import is_plane

#: File stem of the pooled figures of a report (``<stem>_confidence_calibration.png``).
CALIBRATION_STEM = "all-sessions"
#: The feature layout of the pinned data sets (`acquisition.fetch.DATASETS`) whose
#: vectors have one (datasets/README.md): s4.mat's 34 features are 2 fronto-central
#: channels x 17 samples, channel-major (its channels' names are not in the file).
PINNED_FEATURE_LAYOUTS: dict[str, FeatureLayout] = {
    "s4": FeatureLayout(("channel 1", "channel 2"), 17),
}


def pinned_feature_layout(config: dict[str, Any]) -> FeatureLayout | None:
    """The feature layout of the recording's data set when it is a pinned one with a known
    layout (`PINNED_FEATURE_LAYOUTS`): the file at the config's ``dataset`` ``path``
    has its sha256. None otherwise (no such file, another file, raw epochs)."""
    if config.get("signal") != "features":
        return None
    path = config.get("dataset", {}).get("path")
    if not isinstance(path, str) or not Path(path).is_file():
        return None
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return next((layout for name, layout in PINNED_FEATURE_LAYOUTS.items()
                 if DATASETS[name].sha256 == digest), None)


@dataclass(frozen=True)
class ReportJob:
    """One recording to report: its path, the output directory and its unique stem."""

    path: str
    out_dir: str
    stem: str


def unique_stems(paths: list[Path]) -> list[str]:
    """A file-name-safe, distinct stem per path (``name``, ``name-2``, ...)."""
    stems: list[str] = []
    for path in paths:
        base = re.sub(r"[^A-Za-z0-9_.-]", "-", path.stem) or "session"
        stem, n = base, 1
        while stem in stems:
            n += 1
            stem = f"{base}-{n}"
        stems.append(stem)
    return stems


def report_session(job: ReportJob) -> SessionReport:
    """Measure and draw one recording (a module-level function: a Dask worker's job).

    Never raises for a bad file: the returned report then holds the error, naming the file.
    """
    path = Path(job.path)
    try:
        extent = usable_part(read_recording(path, salvage=True))  # what its steps hold
        recording = extent.recording
        if not recording.config:
            detail = f" ({recording.warning})" if recording.warning else ""
            raise ValueError(f"{path}: the recording holds no session configuration{detail}")
        if extent.stop is not None:  # reported, like a cut file, up to the damage
            recording = replace(recording, truncated=True)
        if recording.config.get("world") == "puddle":  # likelihood and trajectory
            metrics = puddle_metrics(recording, str(path))
            figures = puddle_figures(recording, metrics, Path(job.out_dir), job.stem)
        elif is_plane(recording.config):  # the continuous world: particles and probe points
            metrics = plane_metrics(recording, str(path))
            figures = plane_figures(recording, metrics, Path(job.out_dir), job.stem)
        else:
            metrics = session_metrics(recording, str(path))
            figures = session_figures(recording, metrics, Path(job.out_dir), job.stem,
                                      pinned_feature_layout(recording.config))
    except Exception as error:  # one bad file must not stop the others: report it
        message = str(error)
        if str(path) not in message:
            message = f"{path}: {type(error).__name__}: {message}"
        return SessionReport(str(path), job.stem, error=message)
    if recording.damage or recording.dropped:
        metrics.damage = {"regions": [d.to_json() for d in recording.damage],
                          "dropped_messages": recording.dropped, **extent.to_json(),
                          "notes": extent.notes()}
    return SessionReport(str(path), job.stem, metrics, figures)


def metrics_document(reports: list[SessionReport], out_dir: Path) -> dict[str, Any]:
    """The content of ``metrics.json``: aggregate, sessions (with figure files), errors."""
    done = [r.metrics for r in reports if r.metrics is not None]
    sessions = []
    for report in reports:
        if report.metrics is None:
            continue
        sessions.append({
            "stem": report.stem,
            "scalars": report.metrics.scalars(),
            "figures": [
                {**asdict(f), "path": str(f.path.relative_to(out_dir))} for f in report.figures
            ],
            **report.metrics.to_dict(),
        })
    counts = [m.calibration_counts for m in done if m.calibration_counts is not None]
    by_rule = [m.calibration_counts_by_rule for m in done
               if m.calibration_counts_by_rule is not None]
    return {
        "aggregate": aggregate(done),
        "confidence_calibration": [asdict(b) for b in calibration_curve(pool_counts(counts))]
        if counts else None,
        "confidence_calibration_by_rule": {
            "sessions": len(by_rule),
            "rules": [rule_summary(pooled) for pooled in pool_counts_by_rule(by_rule)],
        } if by_rule else None,
        "sessions": sessions,
        "errors": [{"file": r.file, "error": r.error} for r in reports if r.error],
    }


def _cell(value: Any, digits: int = 3) -> str:
    if value is None:
        return "–"
    return f"{value:.{digits}g}" if isinstance(value, float) else str(value)


def print_summary(reports: list[SessionReport], console: Console) -> None:
    """A table of the sessions' main metrics, then truncation and re-run warnings.

    Columns: steps recorded, first target step, correct/wrong targets, steps per correct
    target, mean steps between targets, final decoder balanced accuracy against the truth
    and self-estimated, median and 99th percentile of the update latency (ms).
    """
    table = Table(
        box=box.SIMPLE_HEAD,
        caption="first: step of the first target; ✓/✗: correct/wrong targets; gap: mean steps "
        "between targets; acc: decoder balanced accuracy at the last step vs truth/self-"
        "estimate; ms: learner update, median/p99; *: truncated; !: re-run differs",
        caption_justify="left",
    )
    table.add_column("session", no_wrap=True)
    for name in ("steps", "first", "✓/✗", "steps/✓", "gap", "acc", "ms"):
        table.add_column(name, justify="right", no_wrap=True)
    for report in reports:
        m = report.metrics
        if m is None:  # printed as an error by the caller
            continue
        mark = "[yellow]*[/]" if m.truncated else ""
        mark += "[yellow]![/]" if m.replay_identical is False else ""
        latency = "–" if m.latency is None else (
            f"{m.latency.median_ms:.1f}/{m.latency.p99_ms:.1f}"
        )
        table.add_row(
            f"{report.stem}{mark}", str(m.steps), _cell(m.first_target_step),
            f"{m.correct_targets}/{m.wrong_targets}", _cell(m.steps_per_correct_target),
            _cell(m.mean_steps_between_targets),
            f"{_cell(m.final_accuracy_truth, 2)}/{_cell(m.final_accuracy_self, 2)}", latency,
        )
    console.print(table)
    done = [r.metrics for r in reports if r.metrics is not None]
    if len(done) > 1:
        summary = aggregate(done)
        parts = []
        for name, label in (("first_target_step", "first target"),
                            ("steps_per_correct_target", "steps/correct"),
                            ("final_accuracy_truth", "acc truth"),
                            ("latency_median_ms", "update ms p50")):
            values = summary.get(name)
            if values and values["n"]:
                parts.append(f"{label} {_cell(values['median'])} "
                             f"[{_cell(values['min'])}–{_cell(values['max'])}]")
        line = f"median [min–max] over {len(done)} sessions: " + ", ".join(parts)
        console.print(escape(line), soft_wrap=True)
    for report in reports:
        if report.metrics is not None and report.metrics.truncated:
            console.print(f"[yellow]warning:[/] truncated recording: "
                          f"{escape(report.metrics.warning or '')}", soft_wrap=True)
        if report.metrics is not None and report.metrics.damage:
            for note in [report.metrics.warning or "", *report.metrics.damage["notes"]]:
                console.print(f"[yellow]warning:[/] damaged recording {escape(report.file)}: "
                              f"{escape(note)}", soft_wrap=True)
        if report.metrics is not None and report.metrics.truth not in (None, SIMULATED_TRUTH):
            console.print(f"{escape(report.file)}: truth: {escape(report.metrics.truth or '')}",
                          soft_wrap=True)
        if report.metrics is not None and report.metrics.replay_identical is False:
            console.print(f"[yellow]warning:[/] {report.file}: the re-run differs from the "
                          f"recording: {report.metrics.replay_note}", soft_wrap=True)


def run_report(
    files: list[Path], out_dir: Path, *, scheduler: Scheduler, console: Console
) -> list[SessionReport]:
    """Report every file into ``out_dir`` (see the module docstring), the files' jobs run
    where ``scheduler`` says; return the reports."""
    out_dir.mkdir(parents=True, exist_ok=True)
    stems = unique_stems(files)
    work = [ReportJob(str(f), str(out_dir), s) for f, s in zip(files, stems, strict=True)]
    reports = run_parallel(
        report_session, work, scheduler=scheduler, description="reporting", console=console
    )
    document = metrics_document(reports, out_dir)
    (out_dir / "metrics.json").write_text(json.dumps(document, indent=1) + "\n")
    calibration = None
    if document["confidence_calibration"] is not None:
        by_rule = document["confidence_calibration_by_rule"]
        rules = [CalibrationPanel.of_rule_summary(rule) for rule in by_rule["rules"]] if (
            by_rule is not None) else []
        betas = {r.metrics.beta for r in reports
                 if r.metrics is not None and r.metrics.calibration_counts is not None}
        # The pooled steps' threshold, where they have one: every session's, every rule's.
        thresholds = betas | {p.threshold for p in rules}
        panels = [CalibrationPanel(
            [CalibrationBin(**b) for b in document["confidence_calibration"]],
            threshold=thresholds.pop() if len(thresholds) == 1 else None), *rules]
        figure = calibration_figure(panels)
        caption = ("Pooled over the sessions, all steps and each decision rule's: bars, the "
                   "fraction of steps in each confidence bin whose best task was the user's "
                   "target (labels: steps); dashed, a calibrated confidence.")
        [saved] = save_figures([("confidence_calibration", figure, caption)], out_dir,
                               CALIBRATION_STEM)
        calibration = (saved, panels)
    write_html(out_dir, reports, document["aggregate"], calibration)
    return reports
