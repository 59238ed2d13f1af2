"""``cfbci recover``, ``replay``, ``report`` and ``export``: what is done with a
recording."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rich.console import Console

from cfbci.cli.options import add_endpoints, add_zenoh_config, parse_settings
from cfbci.cli.simulate import add_scheduler_options
from cfbci.offline.parallel import Scheduler
from cfbci.outputs import new_file, new_folder
from cfbci.recordings.export import FORMATS, damage_lines, export_fif
from replay.recording import read_recording


def add_recover_command(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "recover",
        help="rewrite a (possibly truncated or damaged) recording as a clean, indexed MCAP file",
        description="Read every intact message of a session recording, even one whose "
        "writer was killed or whose bytes are damaged (every chunk whose CRC and lengths "
        "check, around damaged ones; see docs/recordings.md), and write them to a clean, "
        "indexed MCAP file; say where the input is cut and which byte ranges were dropped. "
        "The input is only read. Exit 0 when nothing was dropped but a killed writer's cut "
        "(the input complete, or truncated), 3 when damaged records were dropped (or the "
        "input's summary was damaged), 2 on an error (not an MCAP file, no such file).",
    )
    p.add_argument("file", type=Path, help="the recording (.mcap) to recover")
    p.add_argument(
        "--out", type=Path, help="the clean copy to write (default <stem>.recovered.mcap)"
    )
    _add_overwrite(p, "the clean copy")
    p.set_defaults(run=_run_recover)


def _add_overwrite(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument(
        "--overwrite", action="store_true",
        help=f"replace an existing {what} (a link is replaced, never written through); "
        "without it, an existing one is an error and nothing is written",
    )


def _print_damage(recording: Any, console: Console, limit: int = 10) -> None:
    """Each damaged region of a recording (at most ``limit``), one line each."""
    for damage in recording.damage[:limit]:
        console.print(f"damaged: {damage.describe()}", soft_wrap=True, markup=False)
    if len(recording.damage) > limit:
        console.print(f"damaged: ... {len(recording.damage) - limit} more regions",
                      soft_wrap=True)


def _run_recover(args: argparse.Namespace, console: Console) -> int:
    from replay.recording import read_recording, recover

    source: Path = args.file
    out: Path = args.out or source.with_name(f"{source.stem}.recovered.mcap")
    if out.resolve() == source.resolve():
        raise ValueError(f"--out {out} is the input file; give another path")
    # a ValueError naming the file if it is not MCAP
    recording = read_recording(source, salvage=True)
    with new_file(out, args.overwrite) as written:
        n_messages = recover(source, written)
    console.print(f"recovered {n_messages} messages of session {recording.session!r} into {out}",
                  soft_wrap=True, markup=False)
    if recording.truncated:
        console.print(f"input truncated: {recording.warning}", soft_wrap=True, markup=False)
    elif recording.complete:
        console.print(f"input complete: closed by its writer (data ends at byte "
                      f"{recording.end_offset})")
    if recording.damage:
        lost = sum(d.messages for d in recording.damage)
        console.print(f"input damaged: {len(recording.damage)} region"
                      f"{'s' * (len(recording.damage) != 1)} dropped ({lost} message"
                      f"{'s' * (lost != 1)} apparently lost), every intact chunk around them "
                      "kept", soft_wrap=True)
        _print_damage(recording, console)
    if recording.dropped:
        console.print(f"dropped {recording.dropped} intact messages whose channel is defined "
                      "only in a damaged chunk (or not JSON)", soft_wrap=True)
    if recording.config and not recording.messages.get("/config") and recording.damage:
        console.print("the /config message was in a damaged chunk: rebuilt from the "
                      "cfbci.config metadata record, which holds the same", soft_wrap=True)
    return 3 if recording.damage or recording.dropped else 0


def add_replay_command(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "replay",
        help="check a recording by re-running the learner, re-score it with other settings, "
        "or re-publish it to a running service",
        description="Three uses of a session recording. (1) Plain: rebuild the learner from "
        "the recording's configuration and seeds, feed it the recorded epochs, and compare "
        "every move, state and target event with the recording; exit 0 when identical and "
        "the file complete (closed by its writer, undamaged), 1 at the first divergence, 3 "
        "when identical as far as a cut or damaged file goes (its whole steps compared, a "
        "step cut between its messages only in what the file holds; the output says where "
        "the file ends or is damaged and what was not compared; docs/recordings.md), 2 on "
        "an error (not a recording). (2) --option/--compare: open-loop re-analysis: learners "
        "with other settings observe the recorded states, actions and epochs in order (they "
        "choose no action; they switch task where the recording declared a target) and the "
        "report compares when each becomes confident, on which cell, and whether it is the "
        "user's target, with the recording's own settings (which must reproduce the recorded "
        "confidences exactly; exit 1 if not). (3) --publish: send the recorded config, "
        "epochs and truth to a running `cfbci serve` over Zenoh, open-loop, and check that "
        "its moves equal the recorded ones (exit 1 if not).",
    )
    p.add_argument("file", type=Path, help="the recording (.mcap)")
    analysis = p.add_argument_group("open-loop re-analysis")
    analysis.add_argument(
        "--option", action="append", default=[], metavar="KEY=VALUE",
        help="a learner setting (any calibration_free.config.LearnerConfig field) to change; "
        "several --option form one alternative setting",
    )
    analysis.add_argument(
        "--compare", action="append", default=[], metavar="'KEY=VALUE [KEY=VALUE ...]'",
        help="one more alternative setting: KEY=VALUE pairs separated by spaces or commas "
        "(repeatable; each --compare is re-scored on its own, besides --option's)",
    )
    analysis.add_argument(
        "--per-step", action="store_true",
        help="also print every step's recorded and re-scored best cell and its confidence",
    )
    publish = p.add_argument_group("re-publishing to a running service (--publish)")
    publish.add_argument(
        "--publish", action="store_true",
        help="re-publish the session over Zenoh to a running `cfbci serve`",
    )
    publish.add_argument(
        "--speed", type=float, default=None,
        help="pace factor of the recorded inter-epoch gaps (default 1; 2 = twice as fast; "
        "0 or inf: each epoch as soon as the service's move arrives)",
    )
    publish.add_argument(
        "--session", default=None,
        help="session id to publish under (default <recorded session>-replay)",
    )
    publish.add_argument(
        "--timeout", type=float, default=None,
        help="seconds without a message from the service before giving up (default 30)",
    )
    add_endpoints(
        publish, "Zenoh endpoint to listen on (repeatable)",
        "Zenoh endpoint of the service, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    add_zenoh_config(publish)
    p.add_argument("--json", type=Path, help="write the result as JSON")
    p.set_defaults(run=_run_replay)


def _alternatives(options: Sequence[str], compares: Sequence[str]) -> list[dict[str, Any]]:
    """The alternative settings of ``--option`` (one) and ``--compare`` (one each)."""
    import re

    groups = ([("--option", list(options))] if options else []) + [
        ("--compare", [pair for pair in re.split(r"[\s,]+", spec) if pair]) for spec in compares
    ]
    alternatives = []
    for flag, pairs in groups:
        bad = [pair for pair in pairs if "=" not in pair or pair.startswith("=")]
        if bad or not pairs:
            raise ValueError(
                f"{flag} expects KEY=VALUE (a LearnerConfig field); got {bad or pairs}"
            )
        alternatives.append(parse_settings(pairs))
    return alternatives


def _run_replay(args: argparse.Namespace, console: Console) -> int:
    publish_only = {
        "--speed": args.speed is not None, "--session": args.session is not None,
        "--timeout": args.timeout is not None, "--listen": bool(args.listen),
        "--connect": bool(args.connect), "--zenoh-config": args.zenoh_config is not None,
    }
    analysis = {"--option": bool(args.option), "--compare": bool(args.compare),
                "--per-step": args.per_step}
    if args.publish:
        clash = [flag for flag, given in analysis.items() if given]
        if clash:
            raise ValueError(f"--publish re-publishes the recording as it is; {clash} apply "
                             "to the open-loop re-analysis")
        return _replay_publish(args, console)
    misplaced = [flag for flag, given in publish_only.items() if given]
    if misplaced:
        raise ValueError(f"{misplaced} only apply with --publish")
    if any(analysis.values()):
        return _replay_reanalyse(args, console)

    from replay.rerun import replay_check

    _refuse_overwriting(args.file, args.json)
    result = replay_check(args.file)
    if args.json:
        args.json.write_text(json.dumps(result.to_json(args.file), indent=2, default=str)
                             + "\n")
    counts = f"{result.moves} moves, {result.states} states, {result.events} events"
    if result.divergence is not None:
        console.print(result.divergence.describe(), soft_wrap=True, markup=False)
    elif result.complete:
        console.print(f"identical: {counts}")
    else:
        console.print(f"identical as far as the file goes: {counts} compared (steps 1-"
                      f"{result.steps_compared} of {result.steps_configured} whole)",
                      soft_wrap=True)
    if not result.complete:
        if result.warning:
            console.print(f"file: {result.warning}", soft_wrap=True, markup=False)
        for note in result.notes:
            console.print(f"note: {note}", soft_wrap=True, markup=False)
    return result.status


def _refuse_overwriting(source: Path, *outputs: Path | None) -> None:
    """A ValueError if an output would overwrite the input recording."""
    for out in outputs:
        if out is not None and out.resolve() == source.resolve():
            raise ValueError(f"{out} is the input recording; give another output path")


def _replay_reanalyse(args: argparse.Namespace, console: Console) -> int:
    from cfbci.recordings.reanalysis import reanalyse
    from cfbci.recordings.reanalysis_output import print_reanalysis

    result = reanalyse(args.file, _alternatives(args.option, args.compare))
    print_reanalysis(result, console, per_step=args.per_step)
    if args.json:
        args.json.write_text(json.dumps(result.to_json(), indent=2) + "\n")
    return 0 if result.outcomes[0].identical_to_recording else 1


def _replay_publish(args: argparse.Namespace, console: Console) -> int:
    from cfbci.recordings.publish import DEFAULT_TIMEOUT, check_speed, print_publish, run_publish

    speed = check_speed(1.0 if args.speed is None else args.speed)
    timeout = DEFAULT_TIMEOUT if args.timeout is None else args.timeout
    if timeout <= 0:
        raise ValueError(f"--timeout must be positive; got {timeout}")
    try:
        result = run_publish(
            args.file, args.listen, args.connect, args.zenoh_config, session_id=args.session,
            speed=speed, timeout=timeout,
        )
    except (TimeoutError, RuntimeError) as error:
        Console(stderr=True).print(f"[bold red]error:[/] {error}")
        return 1
    print_publish(result, console)
    if args.json:
        args.json.write_text(json.dumps(result.to_json(), indent=2) + "\n")
    return 0 if result.moves_equal else 1


def add_report_command(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "report",
        help="metrics, figures and an HTML report of session recordings",
        description="Measure every recording (targets, decoder accuracy against the truth by "
        "re-running the learner, latency, confidence), draw its figures and write "
        "DIR/metrics.json, DIR/<session>_<figure>.png and a self-contained DIR/index.html. "
        "Truncated recordings are reported as far as they go, damaged ones as far as their "
        "steps go (docs/recordings.md), each said. Exit 0 when every file was reported, 1 "
        "when some could not be (the others are), 3 when all were but some are damaged "
        "(records dropped; a truncated file alone is 0).",
    )
    p.add_argument("files", type=Path, nargs="+", metavar="FILE", help="recordings (.mcap)")
    p.add_argument(
        "--out", type=Path, required=True, metavar="DIR",
        help="output folder: new, or empty (one holding files needs --overwrite)",
    )
    _add_overwrite(p, "report's files in DIR")
    add_scheduler_options(p)
    p.set_defaults(run=_run_report)


def _run_report(args: argparse.Namespace, console: Console) -> int:
    from cfbci.recordings.report import print_summary, run_report

    for name in ("metrics.json", "index.html"):
        for source in args.files:
            _refuse_overwriting(source, args.out / name)
    scheduler = Scheduler.from_options(args.scheduler, args.jobs)
    with new_folder(args.out, args.overwrite) as staging:
        reports = run_report(args.files, staging, scheduler=scheduler, console=console)
    print_summary(reports, console)
    errors = [r.error for r in reports if r.error]
    for error in errors:
        Console(stderr=True).print(f"[bold red]error:[/] {error}", soft_wrap=True)
    console.print(f"report: {args.out / 'index.html'} (metrics {args.out / 'metrics.json'})")
    damaged = [r for r in reports if r.metrics is not None and r.metrics.damage]
    return 1 if errors else 3 if damaged else 0


def add_export_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci export``."""
    p = commands.add_parser(
        "export",
        help="write a recording's raw epochs and truth labels in another format (MNE .fif)",
        description="Export the raw epochs a session recording holds, labelled by its truth "
        "(events named correct/error, or by the world's guidance actions: up/down/left/right "
        "on a grid, e.g. pick-and-place/grasp elsewhere), as MNE Epochs "
        "(-epo.fif, EEG in volts). A recording of feature vectors cannot be exported. A "
        "truncated recording gives the epochs it holds, a damaged one those of its intact "
        "chunks (docs/recordings.md); the input is only read. Exit 0 when exported (a "
        "truncated input said), 3 when exported from a damaged input (records dropped), 2 "
        "on an error.",
    )
    p.add_argument("file", type=Path, help="the recording (.mcap)")
    p.add_argument("--format", choices=FORMATS, default="fif", help="output format (fif)")
    p.add_argument("--out", type=Path, help="output file (default <stem>-epo.fif beside FILE)")
    _add_overwrite(p, "output file")
    p.set_defaults(run=_run_export)


def _run_export(args: argparse.Namespace, console: Console) -> int:
    out = args.out or args.file.with_name(f"{args.file.stem}-epo.fif")
    _refuse_overwriting(args.file, out)
    with new_file(out, args.overwrite) as written:
        epochs = export_fif(args.file, written)
    console.print(
        f"exported {len(epochs.labels)} epochs ({len(epochs.ch_names)} channels, "
        f"{epochs.epochs.shape[2]} samples at {epochs.sfreq:g} Hz from {epochs.tmin:g} s) "
        f"to {out}", soft_wrap=True, markup=False,
    )
    recording = read_recording(args.file, salvage=True)
    for line in damage_lines(recording):
        console.print(line, soft_wrap=True, markup=False)
    return 3 if recording.damage or recording.dropped else 0
