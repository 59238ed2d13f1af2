"""``cfbci bench ...``: the benchmarks' command group."""

from __future__ import annotations

import argparse
import json
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from rich.console import Console

from acquisition.sources import DEFAULT_SYNTHETIC_ACCURACY
from acquisition.synthetic import ACCURACY_RANGE
from cfbci.bench.continuous import bench_continuous_step, print_continuous
from cfbci.bench.flood import bench_flood, print_flood
from cfbci.bench.prior_steps import bench_prior_steps, print_prior_steps
from cfbci.bench.returning import (
    ARMS,
    DEFAULT_DRIFT,
    SYNTHETIC_ARMS,
    ReturningData,
    bench_returning,
)
from cfbci.bench.soak import bench_soak
from cfbci.bench.soak_report import plot_soak, print_soak
from cfbci.bench.steps import SECONDS_PER_ACTION, bench_simulate, bench_update, print_rows
from cfbci.cli.simulate import add_scheduler_options
from cfbci.offline.parallel import Scheduler


def add_bench_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci bench`` and its benchmarks."""
    p = commands.add_parser("bench", help="benchmarks")
    which = p.add_subparsers(dest="bench", required=True)
    add_bench_parsers(which)  # update, simulate
    add_returning_parser(which)
    latency = which.add_parser(
        "latency",
        help="end-to-end latency over Zenoh (source to service and back) and the learner's share",
        description="Live sessions on an N x N grid (synthetic data, feedback frame, default "
        "learner) on one service in its own process: epoch published to next move received, "
        "the learner's update inside the service, each epoch's queueing delay there, and the "
        "difference (transport and the rest); pooled, per session and the worst session.",
    )
    latency.add_argument("--grid", type=int, default=5, help="grid side N (default 5: T = 25)")
    latency.add_argument(
        "--sessions", type=int, default=1,
        help="concurrent sessions on the one service (default 1)",
    )
    latency.add_argument(
        "--interval", type=float, default=None,
        help="seconds each source waits before answering a move, its user's reaction; the "
        "sources start after random phases in [0, interval) (default: 0, as fast as "
        "possible, for one session; 0.5 for several)",
    )
    latency.add_argument(
        "--burst", action="store_true",
        help="then run the same sessions again all starting at once, reported beside",
    )
    latency.add_argument(
        "--steps", type=int, default=1000, help="measured epochs (default 1000)"
    )
    latency.add_argument("--seed", type=int, default=0, help="session seed (default 0)")
    latency.add_argument(
        "--json", type=Path,
        help="write the figures (ms) as JSON (the burst run's under 'burst_run')",
    )
    latency.set_defaults(run=_run_bench_latency)
    add_soak_parser(which)
    add_flood_parser(which)
    add_timing_parser(which)
    fuzz = which.add_parser(
        "fuzz-recordings",
        help="damaged recordings (bit flips, cuts, garbage) through replay, report, recover "
        "and export: tracebacks, hangs, inputs modified",
        description="Mutate a real recording, seeded (one flipped bit, several, a cut, a cut "
        "with garbage after it, garbage appended, a zeroed block) and run 'cfbci replay', "
        "'report', 'recover' and 'export' on each mutant in a child process killed after "
        "--timeout seconds. Counted: tracebacks, hangs, inputs modified (SHA-256 before and "
        "after), exit statuses docs/recordings.md does not document for the mutant, errors "
        "not said as 'error: ...', recovered copies that do not read back complete; and "
        "the statuses of each command by mutation kind (cfbci/bench/fuzz.py). Exit 1 if any "
        "mutant failed a check.",
    )
    fuzz.add_argument("--mutants", type=int, default=300, help="mutants (default 300)")
    fuzz.add_argument("--seed", type=int, default=0, help="mutation seed (default 0)")
    fuzz.add_argument("--recording", type=Path, action="append", default=[],
                      help="a recording to mutate (repeatable; default: a `cfbci session` "
                      "of --steps steps on a 3 x 3 grid, synthetic raw epochs, recorded first)")
    fuzz.add_argument("--steps", type=int, default=60, help="that session's steps (default 60)")
    fuzz.add_argument("--jobs", type=int, default=2, help="mutants checked at once (default 2)")
    fuzz.add_argument("--timeout", type=float, default=60.0,
                      help="seconds a mutant's four commands may take, else a hang (default 60)")
    fuzz.add_argument("--cli-every", type=int, default=25,
                      help="every N-th mutant also through `cfbci` processes (default 25; 0: "
                      "none)")
    fuzz.add_argument("--json", type=Path, help="write the counts and failures as JSON")
    fuzz.add_argument("--check-file", nargs=2, type=Path, metavar=("FILE", "DIR"),
                      help=argparse.SUPPRESS)  # one mutant's commands, in the child process
    fuzz.set_defaults(run=_run_bench_fuzz)


def _run_bench_fuzz(args: argparse.Namespace, console: Console) -> int:
    from cfbci.bench.fuzz import check_file, fuzz_recordings

    if args.check_file:  # the commands run in this process: the CLI's own entry point
        check_file(args.cli_main, *args.check_file)
        return 0
    return fuzz_recordings(args.recording, args.mutants, args.seed, args.steps, args.jobs,
                           args.timeout, args.cli_every, args.json, console)


def _run_bench_latency(args: argparse.Namespace, console: Console) -> int:
    from cfbci.bench.latency import bench_latency, print_latency

    report = bench_latency(args.steps, args.seed, args.sessions, args.interval, args.grid)
    print_latency(report, console)
    if args.burst:
        report["burst_run"] = bench_latency(
            args.steps, args.seed, args.sessions, args.interval, args.grid, burst=True
        )
        print_latency(report["burst_run"], console)
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def run_bench_update(args: argparse.Namespace, console: Console) -> int:
    """``cfbci bench update``: run, print, and write the JSON if asked."""
    rows = bench_update(
        tuple(args.grids), tuple(sorted(set(args.histories))),
        measured_steps=args.measured_steps, naive_repeats=args.naive_repeats,
        seed=args.seed, console=console,
    )
    print_rows(rows, console)
    report: dict[str, Any] = {"rows": [asdict(r) for r in rows]}
    if args.continuous_history > 0:
        with console.status("continuous-goal step"), ProcessPoolExecutor(
            1, mp_context=get_context("spawn")
        ) as pool:
            continuous = pool.submit(
                bench_continuous_step, args.continuous_history, args.measured_steps,
                seed=args.seed,
            ).result()
        print_continuous(continuous, SECONDS_PER_ACTION, console)
        report["continuous"] = asdict(continuous)
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def run_bench_simulate(args: argparse.Namespace, console: Console) -> int:
    """``cfbci bench simulate`` (``--prior``: `bench_prior_steps`): run, print, and write
    the JSON if asked."""
    if args.prior:
        report = bench_prior_steps(
            args.dataset, args.seeds, args.steps, args.frame, args.grid, console
        )
        print_prior_steps(report, console)
    else:
        report = bench_simulate(
            args.dataset, args.seeds, args.steps, args.frame, args.grid, console
        )
        wall = report["wall_s"]
        console.print(
            f"{len(report['sessions'])} sessions of {report['steps']} steps on {args.dataset} "
            f"({report['frame']}, {args.grid} x {args.grid}): wall time per session median "
            f"{wall['median']:.2f} s (min {wall['min']:.2f}, max {wall['max']:.2f}); "
            f"{report['realtime_factor']:.0f}x faster than real time at "
            f"{SECONDS_PER_ACTION:g} s per action (median over sessions)",
            soft_wrap=True,  # the dataset's path stays on one line, for copying
        )
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def add_bench_parsers(which: argparse._SubParsersAction) -> None:
    """Register ``cfbci bench update`` and ``cfbci bench simulate``."""
    update = which.add_parser(
        "update",
        help="the learner's per-step cost against a naive scikit-learn reference",
    )
    update.add_argument("--grids", type=int, nargs="+", default=[5, 10, 20])
    update.add_argument("--histories", type=int, nargs="+", default=[100, 500, 1000])
    update.add_argument("--measured-steps", type=int, default=30)
    update.add_argument("--naive-repeats", type=int, default=5)
    update.add_argument("--seed", type=int, default=0)
    update.add_argument(
        "--continuous-history", type=int, default=200,
        help="history of the continuous-goal row (50 particles, 1000 candidates; 0: none)",
    )
    update.add_argument("--json", type=Path, help="write the rows as JSON")
    update.set_defaults(run=run_bench_update)
    simulate = which.add_parser(
        "simulate",
        help="wall time of whole offline sessions, and the factor faster than real time",
        description="Sessions of --steps steps (seeds 0..N-1) on a dataset, one after the "
        "other in this process; process start and dataset loading excluded. The factor "
        f"faster than real time is steps x {SECONDS_PER_ACTION:g} s / wall time, median "
        "over sessions.",
    )
    simulate.add_argument("--dataset", type=Path, required=True, help="a labelled dataset")
    simulate.add_argument("--seeds", type=int, default=5, help="sessions (default 5)")
    simulate.add_argument("--steps", type=int, default=500, help="steps (default 500)")
    simulate.add_argument("--frame", choices=["feedback", "guidance"], default="feedback")
    simulate.add_argument("--grid", type=int, default=5, help="grid side (default 5)")
    simulate.add_argument(
        "--prior", action="store_true",
        help="instead, per seed: a day-1 session on half of the dataset, recorded, then the "
        "day-2 session on the other half from scratch and from that prior; the wall time "
        "per step of each and their ratio (feedback frame)",
    )
    simulate.add_argument("--json", type=Path, help="write the figures as JSON")
    simulate.set_defaults(run=run_bench_simulate)


def add_soak_parser(which: argparse._SubParsersAction) -> None:
    """Register ``cfbci bench soak`` among the ``bench`` subcommands."""
    p = which.add_parser(
        "soak",
        help="a service left running: memory and step time over a long session, leaks "
        "across many short ones",
        description="One long session, then many short ones, each part in a fresh service "
        "process over loopback Zenoh (recording on): service RSS and per-step times against "
        "step, and RSS across the short sessions.",
    )
    p.add_argument("--steps", type=int, default=10_000, help="long session (default 10000)")
    p.add_argument("--sessions", type=int, default=200, help="short sessions (default 200)")
    p.add_argument("--session-steps", type=int, default=20, help="steps of a short one (20)")
    p.add_argument("--every", type=int, default=1000, help="steps per row (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument("--record-dir", type=Path, help="keep the recordings here")
    p.add_argument("--json", type=Path, help="write every figure and series as JSON")
    p.add_argument("--png", type=Path, help="write the curves as a PNG figure")
    p.set_defaults(run=run_soak)


def run_soak(args: argparse.Namespace, console: Console) -> int:
    """``cfbci bench soak``: run, print, and write the JSON and the figure if asked."""
    report = bench_soak(
        args.steps, args.sessions, args.session_steps, args.seed, args.every,
        args.record_dir, console,
    )
    print_soak(report, console)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    if args.png:
        plot_soak(report, args.png)
        console.print(f"figure: {args.png}")
    return 0


def add_flood_parser(which: Any) -> None:
    """Register ``cfbci bench flood`` under the ``bench`` subcommands."""
    p = which.add_parser(
        "flood",
        help="a real session while a hostile client floods the service",
        description="One real session (synthetic data) against a recording service, first "
        "alone (the reference), then while a hostile client floods the service with "
        "malformed and adversarial messages; checks the session's decisions and "
        "recording, reports its queueing delay and latency, the service's peak memory "
        "and its exit on SIGTERM.",
    )
    p.add_argument("--steps", type=int, default=300, help="steps of the real session")
    p.add_argument("--grid", type=int, default=5, help="grid side of the real session")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--rounds", type=int, default=100_000,
        help="most rounds of hostile messages (15 each; the flood stops with the session)",
    )
    p.add_argument("--json", type=Path, help="write the figures as JSON")
    p.set_defaults(run=_run_flood)


def _run_flood(args: Any, console: Console) -> int:
    """The reference (the same session, no flood), then the flood, in the same run."""
    reports = {
        "reference": bench_flood(args.steps, args.grid, args.seed, 0),
        "flood": bench_flood(args.steps, args.grid, args.seed, args.rounds),
    }
    for name, report in reports.items():
        console.rule(name)
        print_flood(report, console)
    if args.json:
        figures = {name: asdict(report) for name, report in reports.items()}
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    ok = all(
        report.decisions_equal_simulation and report.replay_identical
        and report.peak_rss_mb <= report.rss_bound_mb and report.exit_code == 0
        for report in reports.values()
    )
    return 0 if ok else 1


def add_timing_parser(which: argparse._SubParsersAction) -> None:
    """Register ``cfbci bench timing``."""
    p = which.add_parser(
        "timing",
        help="the stimulus page's onsets against Chromium's own trace clock, and the loop's "
        "latency to the frame",
        description="One session of the lab loop on loopback (serve, lsl-bridge, lsl-simulator "
        "--onsets, view --stimulus with its subject page in headless Chromium): each onset "
        "marker's LSL timestamp against the time of the same frame in a trace of Chromium's "
        "(CLOCK_MONOTONIC, pylsl's clock), its drift, the refresh rate, the invalid onsets "
        "and the latency from an epoch's last sample at the bridge to the frame showing the "
        "next move (cfbci/bench/timing.py). Needs chromium, chromium-driver and selenium.",
    )
    p.add_argument("--onsets", type=int, default=200, help="steps of the session (default 200)")
    p.add_argument("--interval", type=float, default=0.25,
                   help="the page's inter-action interval, s (default 0.25)")
    p.add_argument("--seed", type=int, default=0, help="session seed (default 0)")
    p.add_argument("--skew-ms", type=float, default=0.0,
                   help="a deliberate error: the page answers the clock's round trips this "
                   "many ms early, so every marker is that late against the trace (a check "
                   "that the reference is independent; default 0)")
    p.add_argument("--json", type=Path, help="write the figures as JSON")
    p.set_defaults(run=_run_bench_timing)


def _run_bench_timing(args: argparse.Namespace, console: Console) -> int:
    from cfbci.bench.timing import bench_timing, missing

    needs = missing()
    if needs is not None:
        Console(stderr=True).print(f"error: {needs}", soft_wrap=True, highlight=False)
        return 2
    try:
        report, basis = bench_timing(args.onsets, args.interval, args.seed, args.skew_ms)
    except RuntimeError as error:  # a part failed: its log is in the message
        Console(stderr=True).print(f"error: {error}", soft_wrap=True, highlight=False)
        return 1
    error, latency = report["onset_error_ms"], report["move_to_frame_ms"]
    console.print(
        f"{report['steps']} steps, {basis['onsets']} valid onsets, "
        f"{report['invalid_onsets']} invalid; refresh {report['refresh_hz']:.1f} Hz\n"
        f"onset error against Chromium's trace: median {error['median']:.3f} ms, p99 "
        f"{error['p99']:.3f} ms, max {error['max']:.3f} ms (signed mean "
        f"{basis['mean_error_ms']:+.3f} ms); drift {report['drift_ms_per_hour']:+.2f} ms/h\n"
        f"move to frame: median {latency['median']:.1f} ms, p99 {latency['p99']:.1f} ms "
        f"(over {basis['latencies']} steps), of which the service (epoch in, move out): "
        f"median {basis['service_ms']['median']:.1f} ms, p99 {basis['service_ms']['p99']:.1f} "
        f"ms; its move to the frame: median "
        f"{basis['move_to_frame_from_service_ms']['median']:.1f} ms, p99 "
        f"{basis['move_to_frame_from_service_ms']['p99']:.1f} ms\n"
        f"pylsl.local_clock() - CLOCK_MONOTONIC: at most {basis['clock_difference_ms']:.4f} ms",
        highlight=False, soft_wrap=True,
    )
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def add_returning_parser(which: argparse._SubParsersAction) -> None:
    """Register ``cfbci bench returning``."""
    p = which.add_parser(
        "returning",
        help="a returning user's day 2: from scratch, and from day 1's recording as a prior",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--dataset", type=Path, help="a labelled dataset file, halved")
    source.add_argument("--synthetic", choices=("errp",),
                        help="synthetic ErrP subjects (two draws each)")
    p.add_argument("--synthetic-accuracy", type=float, default=DEFAULT_SYNTHETIC_ACCURACY,
                   help=f"nominal balanced accuracy, in {list(ACCURACY_RANGE)} (default "
                   f"{DEFAULT_SYNTHETIC_ACCURACY})")
    p.add_argument("--drift", type=float, default=DEFAULT_DRIFT,
                   help="the drift arm's day-to-day drift D: day 2 100 D ms later and 1 - D "
                   f"times the amplitude (synthetic; default {DEFAULT_DRIFT})")
    p.add_argument("--split", choices=("stratified", "order"), default="stratified",
                   help="a dataset's halves: seeded per user, or in recording order")
    p.add_argument("--arms", nargs="+", metavar="ARM",
                   help=f"the arms to run (their references too): {', '.join(ARMS)}, and for "
                   f"synthetic data {', '.join(SYNTHETIC_ARMS)} and population (the other "
                   "users' day-1 recordings as one weak prior); default all but population")
    p.add_argument("--prior-weight", type=float, default=1.0,
                   help="the weight of a day-1 epoch relative to one of today's (default 1)")
    p.add_argument("--seeds", type=int, default=20, help="users (default 20)")
    p.add_argument("--first-seed", type=int, default=0, help="the first user's seed")
    p.add_argument("--steps", type=int, default=500, help="steps per session (default 500)")
    p.add_argument("--recordings", type=Path,
                   help="where day 1's recordings go (default: a temporary folder, removed)")
    add_scheduler_options(p)
    p.add_argument("--json", type=Path, help="write the report as JSON")
    p.set_defaults(run=run_bench_returning)


def run_bench_returning(args: argparse.Namespace, console: Console) -> int:
    """``cfbci bench returning``."""
    if args.seeds < 1 or args.steps < 1:
        raise ValueError("--seeds and --steps must be at least 1")
    if args.dataset is not None and not args.dataset.is_file():
        raise ValueError(f"--dataset {args.dataset}: no such file")
    data = ReturningData(args.dataset, args.synthetic_accuracy, args.drift, args.split)
    arms = data.chosen_arms(args.arms)
    if not args.prior_weight > 0:
        raise ValueError(f"--prior-weight must be > 0; got {args.prior_weight}")
    data.day(args.first_seed, 1)  # fail early, in this process, on bad data
    users = list(range(args.first_seed, args.first_seed + args.seeds))
    scheduler = Scheduler.from_options(args.scheduler, args.jobs)
    with tempfile.TemporaryDirectory(prefix="cfbci-returning-") as scratch:
        directory = args.recordings or Path(scratch)
        directory.mkdir(parents=True, exist_ok=True)
        report = bench_returning(data, users, args.steps, directory, scheduler, console, arms,
                                 args.prior_weight)
    print_returning(report, console)
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def print_returning(report: dict[str, Any], console: Console) -> None:
    """One line per arm: the summary's figures with the paired differences against the
    arm's reference, and the prior check's decisions."""
    console.print(f"cfbci bench returning - {report['config']['data']}", soft_wrap=True)
    day1 = report["day1"]
    console.print(
        f"day 1: first target {day1['median_first_target_step']:g} (median), correct "
        f"{day1['mean_correct_targets']:.2f}, wrong rate {100 * day1['wrong_target_rate']:.1f} %",
        soft_wrap=True,
    )
    for arm, summary in report["arms"].items():
        figures = {
            "first_target_step": f"first target {summary['median_first_target_step']:g}",
            "correct_targets": f"correct {summary['mean_correct_targets']:.2f}",
            "wrong_targets": f"wrong rate {100 * summary['wrong_target_rate']:.1f} %",
        }
        parts = []
        for key, text in figures.items():
            if "paired" in summary:
                paired_figure = summary["paired"][key]
                low, high = paired_figure["interval_95"]
                text += f" (d {paired_figure['mean']:+.1f} [{low:+.1f}, {high:+.1f}])"
            parts.append(text)
        falls = summary["fallbacks"]
        if falls["sessions"]:
            parts.append(
                f"prior trusted {falls['trusted']}/{falls['sessions']} (steps "
                f"{falls['trusted_at']}), fell back {falls['fell_back']} (steps "
                f"{falls['fell_back_at']}; 0: the power premise), testing {falls['testing']}"
                + (f", no prior {falls['no_prior']}" if falls["no_prior"] else "")
            )
        console.print(f"{arm}: " + ", ".join(parts), soft_wrap=True, highlight=False)
    console.print(
        "d: mean per-seed difference against scratch (drift: against drift_scratch) and its "
        "95 % t-interval; wrong targets in the d are counts. On a small dataset an epoch recurs "
        "within a session and its copies can fall on both sides of the learner's "
        "cross-validation: compare arms, not absolute figures.",
        soft_wrap=True,
    )
