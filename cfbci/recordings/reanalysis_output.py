"""Console output of ``cfbci replay FILE.mcap --option ...`` (see
`cfbci.recordings.reanalysis`): the settings compared, a summary table, a per-segment
table and, if asked, every step's beliefs. The alternatives are labelled A, B, ... in the
tables."""

from __future__ import annotations

from rich import box
from rich.console import Console
from rich.table import Table

from cfbci.recordings.reanalysis import ACTING, OWN, RECORDED, Confident, Reanalysis


def _show(confident: Confident | None) -> str:
    if confident is None:
        return "-"
    mark = {True: "✓", False: "✗", None: "?"}[confident.correct]
    return f"{confident.step}→{confident.task}{mark}"


def _labels(result: Reanalysis) -> list[str]:
    """Short column labels: the own settings' name, then A, B, ... for the alternatives."""
    return ["own", *(chr(ord("A") + i) for i in range(len(result.outcomes) - 1))]


def print_reanalysis(result: Reanalysis, console: Console, per_step: bool = False) -> None:
    """The settings and how they differ from the recording's, a summary table, a
    per-segment table and, if asked, the per-step beliefs (alternatives labelled A, B...)."""
    labels = _labels(result)
    console.print("own: the recording's settings", soft_wrap=True)
    for label, outcome in zip(labels[1:], result.outcomes[1:], strict=True):
        changes = ", ".join(f"{k} {old!r} → {new!r}" for k, (old, new) in outcome.differs.items())
        note = ""
        if changes and set(outcome.differs) <= ACTING:
            note = " (settings of the action choice only: no effect open-loop)"
        console.print(
            f"{label}: {outcome.name} — differs from the recording's settings in {changes}{note}"
            if changes else f"{label}: {outcome.name} — no setting differs from the recording's",
            soft_wrap=True,
        )
    summary = Table(
        title=f"open-loop re-analysis of {result.file or result.session}: {result.n_steps} "
        f"steps, {len(result.segments)} segments between recorded targets",
    )
    summary.add_column("setting")
    for column in ("first confident", "segments", "correct", "wrong", "median steps",
                   "= recorded"):
        summary.add_column(column, justify="right")
    for label, outcome in zip(labels, result.outcomes, strict=True):
        figures = outcome.summary(result.segments)
        median = figures["median_steps_to_confidence"]
        summary.add_row(
            label,
            _show(outcome.first_confident),
            f"{figures['segments_confident']}/{len(result.segments)}",
            str(figures["correct"]),
            str(figures["wrong"]),
            "-" if median is None else f"{median:g}",
            "yes" if outcome.identical_to_recording
            else f"no, step {outcome.first_difference_step}",
        )
    console.print(summary)
    console.print(
        "first confident: step→cell, ✓ the user's target at that step, ✗ not, ? no truth; "
        "segments: those with a confident step; correct/wrong: on the target or not; median "
        "steps: from a segment's start to its first confident step; = recorded: beliefs "
        "equal the recorded states (else the first step that differs)",
        soft_wrap=True,
    )
    segments = Table(
        title="first confident step per segment (step→cell)", box=box.SIMPLE_HEAD,
        pad_edge=False,
    )
    for column in ("#", "steps", "target", "decl.", *labels):
        segments.add_column(column, justify="right", no_wrap=True)
    for i, segment in enumerate(result.segments):
        segments.add_row(
            str(segment.index),
            f"{segment.first_step}-{segment.last_step}",
            "?" if segment.target is None else str(segment.target),
            "-" if segment.declared is None else str(segment.declared),
            *(_show(outcome.segments[i]) for outcome in result.outcomes),
        )
    segments.caption = (
        "target: the user's target in the segment (truth); decl.: the cell the recorded "
        "device declared at its end"
    )
    console.print(segments)
    if per_step:
        console.print(_per_step_table(result))
    own = result.outcomes[0]
    if not own.identical_to_recording:
        console.print(
            f"[bold yellow]warning:[/] the recording's own settings do not reproduce its "
            f"recorded states (first difference at step {own.first_difference_step}); was it "
            "recorded by another version of the learner?",
            soft_wrap=True,
        )


def _per_step_table(result: Reanalysis) -> Table:
    """Step, recorded best/confidence, then the re-scored ones of every setting (the own
    settings' only if they differ from the recorded ones)."""
    table = Table(title="beliefs each move was chosen from (best cell, its confidence)")
    table.add_column("step", justify="right")
    shown = [
        (label, o.trajectory)
        for label, o in zip(_labels(result), result.outcomes, strict=True)
        if o.name != OWN or not o.identical_to_recording
    ]
    for name in (RECORDED, *(name for name, _ in shown)):
        table.add_column(f"{name} best", justify="right")
        table.add_column("conf", justify="right")
    recorded = result.recorded
    for step in range(1, result.n_steps + 1):
        row = step - 1
        reference = recorded.best_task[row] if row < len(recorded) else None
        cells = []
        for trajectory in (recorded, *(t for _, t in shown)):
            if row >= len(trajectory):
                cells += ["-", "-"]
                continue
            best = int(trajectory.best_task[row])
            mark = "*" if trajectory.confident[row] else ""
            cells += [
                f"[bold]{best}[/]" if best != reference else str(best),
                f"{trajectory.confidence[row, best]:.3f}{mark}",
            ]
        table.add_row(str(step), *cells)
    table.caption = "* confident; bold: best cell differs from the recorded one"
    return table
