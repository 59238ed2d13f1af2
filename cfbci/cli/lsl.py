"""``cfbci lsl-bridge``, ``cfbci lsl-simulator`` and ``cfbci lsl-check``: EEG over LSL."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import statistics
import threading
from pathlib import Path
from typing import Any

from rich.console import Console

from calibration_free.frames import FRAMES
from cfbci.cli.options import (
    add_data_options,
    add_endpoints,
    add_prior_option,
    add_zenoh_config,
    checked_prior,
    data_spec,
    parse_settings,
)
from session.config import learner_settings


def add_lsl_commands(commands: argparse._SubParsersAction) -> None:
    """Register the LSL subcommands."""
    _add_bridge(commands)
    _add_simulator(commands)
    _add_check(commands)


def _load_liblsl() -> None:
    """Import pylsl (which loads liblsl) or say what this platform needs."""
    try:
        import pylsl  # noqa: F401
    except RuntimeError as error:  # pylsl's "LSL binary library file was not found"
        raise ValueError(
            f"pylsl cannot load liblsl: {error}. pylsl's wheels bundle liblsl for Linux "
            "x86_64 with glibc >= 2.35, macOS and Windows; elsewhere install liblsl (e.g. "
            "conda-forge's liblsl, or a release of github.com/sccn/liblsl) and set "
            "PYLSL_LIB to the library file"
        ) from None


def _stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM (the loops check it and end cleanly)."""
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    return stop


def _add_session_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--session", required=True,
        help="session id: NAME, or USER/NAME in a user's key space (each 1-64 of A-Za-z0-9_-)",
    )
    p.add_argument("--seed", type=int, default=0, help="session seed (default 0)")
    p.add_argument("--grid", type=int, default=5, help="grid side (default 5)")
    p.add_argument("--frame", choices=FRAMES, default="feedback")
    p.add_argument("--moves", default="cfbci-moves",
                   help="name of the bridge's LSL move stream (default cfbci-moves)")
    p.add_argument("--timeout", type=float, default=30.0,
                   help="seconds to find a stream or hear from the other side (default 30)")
    add_endpoints(p, "Zenoh endpoint to listen on (repeatable)",
                   "Zenoh endpoint of the service, e.g. tcp/127.0.0.1:7447 (repeatable)")


def _add_bridge(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "lsl-bridge",
        help="a source cutting epochs from an LSL EEG stream around a stimulus program's "
        "onset markers",
        description="Resolve an EEG stream and a marker stream on LSL, send the session's "
        "config to a running `cfbci serve`, forward its moves to the stimulus program on an "
        "LSL marker outlet, and answer each with the epoch cut around the onset marker of "
        "that step. Gaps in the EEG and late markers are reported; a window broken by one "
        "is asked for again (the move is re-sent with repeat + 1).",
    )
    p.add_argument("--eeg", required=True, metavar="NAME", help="name of the EEG stream")
    p.add_argument("--markers", required=True, metavar="NAME",
                   help="name of the stimulus program's marker stream")
    _add_session_options(p)
    p.add_argument("--steps", type=int, default=500, help="actions in the session (default 500)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a learner setting sent in the config")
    p.add_argument("--tmin", type=float, default=-0.2, help="epoch start, s (default -0.2)")
    p.add_argument("--tmax", type=float, default=1.0, help="epoch end, s (default 1.0)")
    p.add_argument(
        "--baseline", nargs=2, metavar=("START", "END"), default=None,
        help="MNE-style baseline interval in s, 'none' for an end of the epoch (e.g. "
        "--baseline none 0); default: no baseline correction",
    )
    p.add_argument("--onset-marker", default="onset",
                   help="marker word of an action onset: 'WORD' or 'WORD STEP' (default onset)")
    p.add_argument("--gap-tolerance", type=float, default=0.5,
                   help="timestamp jitter tolerated, in sample periods (default 0.5)")
    p.add_argument("--buffer", type=float, default=30.0, help="seconds of EEG kept (default 30)")
    p.add_argument("--late-marker", type=float, default=0.5,
                   help="report onset markers arriving this many s late (default 0.5)")
    p.add_argument(
        "--marker-shift", type=int,
        help="EEG sample periods added to every marker timestamp (default: from the marker "
        "stream's metadata: 1 for mne-lsl's PlayerLSL annotations, else 0)",
    )
    p.add_argument("--photodiode", metavar="CHANNEL",
                   help="take each onset from this photodiode channel's crossing after the "
                   "marker, the channel kept out of the epochs (acquisition/photodiode.py)")
    p.add_argument("--photodiode-threshold", type=float, metavar="LEVEL",
                   help="the crossing level, uV (default: half-way between the channel's "
                   "median before the marker and its pulse)")
    p.add_argument("--photodiode-window", type=float, default=0.1, metavar="SECONDS",
                   help="the one crossing must come within this many s after the marker, else "
                   "the move is shown again (default 0.1)")
    p.add_argument("--json", type=Path, help="write the bridge's report as JSON")
    add_prior_option(p)
    add_zenoh_config(p)
    p.set_defaults(run=_run_bridge)


def _baseline(values: list[str] | None) -> tuple[float | None, float | None] | None:
    if values is None:
        return None
    try:
        ends = [None if v.lower() == "none" else float(v) for v in values]
    except ValueError:
        raise ValueError(f"--baseline expects two times in s or 'none'; got {values}") from None
    return ends[0], ends[1]


def _run_bridge(args: argparse.Namespace, console: Console) -> int:
    _load_liblsl()
    from acquisition.lsl_bridge import BridgeSettings, run_bridge
    from acquisition.photodiode import PhotodiodeRule

    if args.steps < 1 or args.timeout <= 0 or args.buffer <= 0:
        raise ValueError("--steps must be at least 1, --timeout and --buffer positive")
    learner = parse_settings(args.set)
    learner_settings(learner, args.frame)  # fail early on a bad setting, as the service would
    settings = BridgeSettings(
        session=args.session, eeg=args.eeg, markers=args.markers, moves=args.moves,
        seed=args.seed, steps=args.steps, grid=args.grid, frame=args.frame, learner=learner,
        tmin=args.tmin, tmax=args.tmax, baseline=_baseline(args.baseline),
        onset_marker=args.onset_marker, gap_tolerance=args.gap_tolerance,
        buffer_seconds=args.buffer, late_marker=args.late_marker, timeout=args.timeout,
        marker_shift=args.marker_shift, prior=checked_prior(args),
        photodiode=args.photodiode and PhotodiodeRule(
            args.photodiode, args.photodiode_threshold, args.photodiode_window),
    )
    stop = _stop_on_signals()
    try:
        summary = run_bridge(settings, args.listen, args.connect, lambda: not stop.is_set(),
                             args.zenoh_config)
    except (TimeoutError, RuntimeError) as error:
        Console(stderr=True).print(f"[bold red]error:[/] {error}")
        return 1
    report = summary.to_json()
    latency = report["latency_ms"]
    console.print(
        f"session {summary.session!r}: {len(summary.epochs)} epochs published; "
        f"{len(summary.gaps)} gaps, {len(summary.refused)} windows refused, "
        f"{len(summary.late_markers)} late markers, {len(summary.ignored_markers)} markers "
        f"ignored, {len(summary.reconnects)} reconnections"
    )
    for figures, since in ((latency, "arrival"), (report["age_ms"], "timestamp")):
        if figures:
            console.print(
                f"from a window's last sample's {since} to its epoch published: median "
                f"{figures['median']:.2f} ms, p99 {figures['p99']:.2f} ms, max "
                f"{figures['max']:.2f} ms"
            )
    if args.photodiode and summary.epochs:
        delays = [1e3 * (e["onset"] - e["marker"]) for e in summary.epochs]
        console.print(f"photodiode onsets after their markers: median "
                      f"{statistics.median(delays):.1f} ms, min {min(delays):.1f}, max "
                      f"{max(delays):.1f} ms")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def _drop(text: str) -> Any:
    from acquisition.lsl_simulator import Drop

    try:
        step, offset, count = (int(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected STEP:OFFSET:COUNT; got {text!r}") from None
    if step < 1 or count < 1:
        raise argparse.ArgumentTypeError(f"STEP and COUNT must be at least 1; got {text!r}")
    return Drop(step, offset, count)


def _late(text: str) -> tuple[int, float]:
    step, _, seconds = text.partition(":")
    try:
        late = int(step), float(seconds)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected STEP:SECONDS; got {text!r}") from None
    if late[0] < 1 or not late[1] >= 0:
        raise argparse.ArgumentTypeError(f"STEP must be at least 1, SECONDS >= 0: {text!r}")
    return late


def _add_simulator(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "lsl-simulator",
        help="an EEG amplifier, stimulus program and simulated user on LSL (for the bridge)",
        description="Stream continuous synthetic EEG on an LSL outlet; answer every move of "
        "the bridge's move stream by sending an onset marker after --onset-delay and writing "
        "the simulated user's epoch into the EEG at that time; publish the truth on Zenoh. "
        "Runs until the move stream ends, SIGINT or SIGTERM.",
    )
    add_data_options(p)
    _add_session_options(p)
    p.add_argument("--user-error-rate", type=float, default=0.0)
    p.add_argument("--eeg", default="cfbci-sim-eeg", help="EEG outlet name")
    p.add_argument("--markers", default="cfbci-sim-markers", help="marker outlet name")
    p.add_argument("--onset-delay", type=float, default=1.0,
                   help="seconds from a move to its onset (default 1)")
    p.add_argument("--drop", type=_drop, action="append", default=[], metavar="STEP:OFFSET:COUNT",
                   help="leave COUNT samples out of the stream, from OFFSET samples after the "
                   "onset of STEP's epoch (a test of gaps; repeatable)")
    p.add_argument("--late-onset", type=_late, action="append", default=[],
                   metavar="STEP:SECONDS",
                   help="send the onset marker of STEP's epoch SECONDS after its onset (a test "
                   "of late markers; repeatable)")
    p.add_argument("--restart-after", type=int, metavar="STEP",
                   help="close the EEG outlet once STEP's epoch is streamed and open it again")
    p.add_argument("--outage", type=float, default=1.0,
                   help="seconds the EEG outlet stays closed (default 1)")
    p.add_argument("--written", type=Path, metavar="FILE.npz",
                   help="save every epoch written into the stream (for lsl-check)")
    p.add_argument("--onsets", metavar="NAME",
                   help="listen: make no onsets, take them from this marker stream (a "
                   "stimulus program's, e.g. cfbci view --stimulus) and the moves from the "
                   "service; the EEG stream opens once that stream is found, and runs "
                   "|tmin| + --marker-latency behind real time")
    p.add_argument("--photodiode", type=float, metavar="SECONDS",
                   help="a display's delay: each epoch's onset this long after its marker, "
                   "marked by a pulse on a 'Photodiode' channel (for lsl-bridge --photodiode)")
    p.add_argument("--marker-latency", type=float, default=0.3, metavar="SECONDS",
                   help="with --onsets: how late an onset marker may arrive (default 0.3)")
    add_zenoh_config(p)
    p.set_defaults(run=_run_simulator)


def _run_simulator(args: argparse.Namespace, console: Console) -> int:
    _load_liblsl()
    from acquisition.lsl_simulator import SimulatorSettings, run_simulator
    from acquisition.lsl_written import save_written

    if args.onset_delay <= 0 or args.outage <= 0 or args.timeout <= 0:
        raise ValueError("--onset-delay, --outage and --timeout must be positive")
    if args.photodiode is not None and not 0 <= args.photodiode <= 0.5:
        raise ValueError(f"--photodiode (a display's delay) must be in 0..0.5 s; got "
                         f"{args.photodiode}")
    if not args.marker_latency > 0:
        raise ValueError(f"--marker-latency must be positive; got {args.marker_latency}")
    if args.onsets is not None and (args.drop or args.late_onset or args.restart_after):
        raise ValueError("--drop, --late-onset and --restart-after test the simulator's own "
                         "onsets: they do not go with --onsets")
    if args.synthetic != "errp":  # the other generators make feature vectors
        raise ValueError("the LSL simulator streams EEG: it needs the synthetic ErrP generator "
                         f"or a dataset of raw epochs, not --synthetic {args.synthetic}")
    settings = SimulatorSettings(
        session=args.session, data=data_spec(args),
        seed=args.seed, grid=args.grid, frame=args.frame, user_error_rate=args.user_error_rate,
        eeg=args.eeg, markers=args.markers, moves=args.moves, onset_delay=args.onset_delay,
        drops=tuple(args.drop), late_markers=tuple(args.late_onset),
        restart_after=args.restart_after, outage=args.outage,
        timeout=args.timeout, onsets=args.onsets, marker_latency=args.marker_latency,
        photodiode=args.photodiode,
    )
    stop = _stop_on_signals()
    try:
        simulation = run_simulator(settings, args.listen, args.connect,
                                   lambda: not stop.is_set(), args.zenoh_config)
    except TimeoutError as error:
        Console(stderr=True).print(f"[bold red]error:[/] {error}")
        return 1
    written = simulation.written
    steps = {w.step for w in written}
    correct = sum(ok for _, ok in simulation.targets)
    first = simulation.targets[0][0] if simulation.targets else "-"
    console.print(f"session {args.session!r}: {len(written)} epochs written for "
                  f"{len(steps)} steps ({len(written) - len(steps)} repeats); first target at "
                  f"step {first}, {correct} correct, {len(simulation.targets) - correct} wrong")
    if simulation.late:
        console.print(f"{len(simulation.late)} onset markers came too late to be written "
                      f"(steps {[step for step, _ in simulation.late]}): raise --marker-latency")
    if args.written:
        save_written(args.written, simulation)
    return 0


def _add_check(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "lsl-check",
        help="compare a recording's epochs with what lsl-simulator wrote, sample for sample",
    )
    p.add_argument("written", type=Path, help="the simulator's --written file (.npz)")
    p.add_argument("recording", type=Path, help="the service's recording (.mcap)")
    p.set_defaults(run=_run_check)


def _run_check(args: argparse.Namespace, console: Console) -> int:
    from acquisition.lsl_written import check_recording

    result = check_recording(args.written, args.recording)
    for mismatch in result.mismatches:
        console.print(mismatch)
    console.print(f"{result.equal} of {result.recorded} recorded epochs equal, sample for sample "
                  "(float32), the epochs written for their steps")
    return 0 if result.recorded and result.equal == result.recorded else 1
