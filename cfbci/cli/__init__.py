"""The ``cfbci`` command line: ``simulate``, ``bench``, ``serve``, ``source``, ``session``,
``recover``, ``replay``, ``report``, ``sweep``, ``export``."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import replace
from importlib import metadata
from pathlib import Path
from typing import Any

import zenoh
from rich.console import Console

from acquisition.sources import DEFAULT_SYNTHETIC_ACCURACY, SYNTHETIC_KINDS, DataSpec
from acquisition.synthetic import ACCURACY_RANGE
from calibration_free.baseline import DEFAULT_CALIBRATION_TRIALS
from calibration_free.config import LearnerConfig
from calibration_free.frames import FRAMES
from calibration_free.planning import PLANNERS
from calibration_free.task_likelihoods import LIKELIHOODS
from calibration_free.worlds import WORLDS
from cfbci import router
from cfbci.blas import limit_blas_threads
from cfbci.compare import add_compare_command
from cfbci.curves import add_curves_command
from cfbci.export import add_export_command
from cfbci.flood import add_flood_parser
from cfbci.limits import ServiceLimits
from cfbci.limits import add_options as add_limit_options
from cfbci.make_datasets import add_datasets_command
from cfbci.memory import keep_freed_memory
from cfbci.parallel import Scheduler, add_scheduler_options, run_parallel
from cfbci.plane_worlds import (
    PLANE_WORLDS,
    add_live_plane_options,
    add_plane_world_options,
    live_source_fields,
    print_plane_report,
    simulate_plane_world,
)
from cfbci.presets import PRESETS, Preset
from cfbci.simulation import BASELINES, SessionConfig
from cfbci.soak import add_soak_parser
from cfbci.sweep import add_sweep_command
from cfbci.view import add_view_command
from cfbci.world_check import add_world_command
from session.config import learner_settings
from session.plane import PLANE_FRAMES as LIVE_PLANE_WORLDS


def parse_settings(pairs: Sequence[str]) -> dict[str, Any]:
    """``key=value`` pairs (values parsed as JSON when they can be) into a dictionary."""
    settings: dict[str, Any] = {}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects key=value; got {pair!r}")
        try:
            settings[key] = json.loads(raw)
        except json.JSONDecodeError:
            settings[key] = raw
    return settings


def _add_data_options(p: argparse.ArgumentParser) -> None:
    """``--dataset`` and ``--synthetic-accuracy``: where the simulated user's signals come from."""
    p.add_argument(
        "--dataset", type=Path,
        help="dataset file: .mat, .npz, or a session recording .mcap (its epochs, labelled by "
        "its truth; raw epochs if it holds them); default synthetic",
    )
    p.add_argument(
        "--synthetic-accuracy", type=float, default=DEFAULT_SYNTHETIC_ACCURACY,
        help=f"synthetic difficulty as nominal balanced LDA accuracy, in {list(ACCURACY_RANGE)} "
        "(ErrP); for Gaussian signals the Bayes-optimal balanced accuracy",
    )
    p.add_argument(
        "--synthetic", choices=SYNTHETIC_KINDS, default="errp",
        help="synthetic generator: ErrP EEG epochs (feedback), or Gaussian signals with as many "
        "classes as the frame needs (default errp)",
    )
    p.add_argument("--dims", type=int, default=2, help="dimensions of a Gaussian signal")
    p.add_argument(
        "--mixing-decay", type=float, default=0.0,
        help="Gaussian signals seen through a fixed linear mixing whose spectrum decays as "
        "j^-GAMMA (correlated features, as EEG's; the nominal accuracy holds; default 0: none)",
    )


def _add_likelihood_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--likelihood", choices=LIKELIHOODS,
        help="how tasks are scored (the learner setting 'likelihood'; default matching)",
    )


def _learner_settings(args: argparse.Namespace, **defaults: Any) -> dict[str, Any]:
    """``defaults``, then the ``--set`` settings, then ``--likelihood`` if given."""
    given = parse_settings(args.set)
    if "frame" in given:
        raise ValueError("--set frame=...: the frame is set with --frame")
    settings = {**defaults, **given}
    if args.likelihood is not None:
        settings["likelihood"] = args.likelihood
    return settings


def data_spec(args: argparse.Namespace) -> DataSpec:
    """The :class:`DataSpec` of the options of :func:`_add_data_options`."""
    return DataSpec(
        args.dataset, args.synthetic_accuracy, args.synthetic, args.dims, args.mixing_decay
    )


def _add_simulate(commands: argparse._SubParsersAction, chosen: Preset | None) -> None:
    p = commands.add_parser(
        "simulate",
        help="offline closed-loop sessions with a simulated user (no network)",
        description="Run sessions of the calibration-free learner (or the calibrated "
        "baseline) against a simulated user answering from a dataset, and summarise them.",
    )
    _add_data_options(p)
    p.add_argument("--seeds", type=int, default=20, help="number of sessions (default 20)")
    p.add_argument("--first-seed", type=int, default=0, help="seed of the first session")
    p.add_argument("--steps", type=int, default=500, help="actions per session (default 500)")
    p.add_argument("--grid", type=int, default=5, help="grid side (default 5)")
    p.add_argument(
        "--world", choices=(*WORLDS, *PLANE_WORLDS), default="grid",
        help="grid (N x N, --grid), line (5 states), pick-and-place (624 states); in the "
        "plane: continuous (goal points, cardinal frame) or puddle (660 tasks, mixed frame)",
    )
    p.add_argument(
        "--frame", choices=(*FRAMES, "hypotheses"), default="feedback",
        help="the user's frame, or 'hypotheses': (task, frame) pairs, the frame unknown to the "
        "learner (the teacher's frame alternates with the seed: even feedback, odd guidance)",
    )
    p.add_argument(
        "--shuffle-labels", action="store_true",
        help="--frame hypotheses: answer with signals drawn regardless of the label (the "
        "shuffled-label control)",
    )
    p.add_argument(
        "--planner", choices=PLANNERS,
        help="how actions are chosen while not confident (default: the learner's, "
        "'information'; the plane worlds' probing: 'uncertainty')",
    )
    _add_likelihood_option(p)
    p.add_argument("--baseline", choices=BASELINES, help="run the calibrated baseline instead")
    p.add_argument(
        "--calibration-trials", type=int, default=DEFAULT_CALIBRATION_TRIALS,
        help="calibration actions of the baseline (default 400)",
    )
    p.add_argument("--user-error-rate", type=float, default=0.0)
    p.add_argument(
        "--prior", type=Path, nargs="+", metavar="FILE.mcap",
        help="earlier recordings of the user: the learner starts from the signals and the "
        "labels adopted at their targets (grid, line and pick-and-place worlds)",
    )
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="any other learner setting (see calibration_free.config.LearnerConfig)",
    )
    add_scheduler_options(p)
    add_plane_world_options(p)
    p.add_argument("--json", type=Path, help="write the report as JSON")
    p.add_argument("--trace", type=Path, help="write one JSON line per step")
    p.add_argument(
        "--preset", choices=PRESETS,
        help="the settings of one of the thesis's experiments (see --list-presets); explicit "
        "options override it",
    )
    p.add_argument("--list-presets", action="store_true", help="list the presets and exit")
    p.set_defaults(run=_run_simulate)
    if chosen is not None:
        p.set_defaults(**chosen.defaults())


def _simulate_frame_hypotheses(args: argparse.Namespace, console: Console) -> int:
    """``--frame hypotheses``: (task, frame) pairs, the user's frame unknown."""
    from calibration_free.frame_hypotheses import FRAME_DEFAULTS
    from cfbci.frame_sessions import FrameJob, frame_hypotheses_report, run_frame_job

    # The pairs' learners share these settings; their own frames are the pairs'.
    config = learner_settings(_learner_settings(args, **FRAME_DEFAULTS), LearnerConfig.frame)
    data = data_spec(args)
    data.resolve("guidance")  # fail early on a bad dataset
    jobs = [
        FrameJob(seed, args.world, args.grid, config, data, args.steps, args.shuffle_labels)
        for seed in range(args.first_seed, args.first_seed + args.seeds)
    ]
    sessions = run_parallel(
        run_frame_job, jobs, scheduler=Scheduler.from_options(args.scheduler, args.jobs),
        description="sessions", console=console,
    )
    summary = frame_hypotheses_report(sessions, args.steps, config.frame_beta)
    _print_frame_hypotheses(summary, config.frame_beta, console)
    if args.json:
        report = {"config": {"world": args.world, "frame": "hypotheses",
                             "learner": config.to_dict(), "dataset": data.describe(),
                             "shuffle_labels": args.shuffle_labels},
                  "sessions": sessions, "summary": summary}
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def _print_frame_hypotheses(summary: dict[str, Any], beta: float, console: Console) -> None:
    """The frame-hypotheses summary (:func:`cfbci.frame_sessions.frame_hypotheses_report`)
    as two tables, over every session and per teacher frame, with what each row means."""
    from rich.table import Table

    groups = [("all sessions", summary)] + [
        (f"{key.removesuffix('_teacher')} teacher", group)
        for key, group in summary.items() if key.endswith("_teacher")
    ]
    rows = (  # label, how a group's value is shown, what it means
        ("sessions", lambda g: str(g["sessions"]), "sessions run"),
        ("decided", lambda g: str(g["sessions_confident"]),
         f"sessions with a confident pair: its confidence W above {beta:g} and its decoder "
         "above chance"),
        ("first decision right", lambda g: str(g["first_confident_correct"]),
         "sessions whose first confident pair was the user's task and frame"),
        ("teacher's frame won", lambda g: str(g["winning_frame_is_teachers"]),
         "sessions whose best pair at the end had the teacher's frame"),
        ("user's pair by step 100", lambda g: f"{g['user_pair_confident_by_step_100']:.1%}",
         "the user's pair decided by step 100"),
        (f"W > {beta:g} by step 100", lambda g: f"{g['user_pair_w_above_beta_by_step_100']:.1%}",
         "the thesis's measure: the user's pair's W alone above the threshold by step 100"),
        ("median first decision", lambda g: f"{g['median_first_confident_step']:g}",
         "step of the first confident pair (never: the steps + 1)"),
        ("undecided", lambda g: f"{g['undecided']:.1%}", "sessions with no confident pair"),
    )
    table = Table(title="frame hypotheses: the (task, frame) pairs the learner decided on")
    table.add_column("")
    for name, _ in groups:
        table.add_column(name, justify="right")
    for label, shown, _ in rows:
        table.add_row(label, *(shown(group) for _, group in groups))
    console.print(table)
    steps = list(summary["mean_user_pair_w"])
    if steps:
        confidence = Table(title="mean confidence W of the user's pair after step ...")
        confidence.add_column("")
        for step in steps:
            confidence.add_column(step, justify="right")
        for name, group in groups:
            confidence.add_row(name, *(f"{group['mean_user_pair_w'][s]:.3f}" for s in steps))
        console.print(confidence)
    console.print("\n".join(f"{label}: {meaning}" for label, _, meaning in rows[1:]) + (
        "\nW: a pair's pairwise confidence, the least over the other pairs of L / (L + "
        "L_other), L its likelihood"), soft_wrap=True, highlight=False)


def _run_simulate(args: argparse.Namespace, console: Console) -> int:
    from cfbci.simulate import print_report, simulate

    if args.list_presets:
        for known in PRESETS.values():
            console.print(known.describe(), soft_wrap=True, highlight=False)
        return 0
    if args.preset and PRESETS[args.preset].dataset and args.dataset is None:
        raise ValueError(
            f"preset {args.preset!r} needs --dataset {PRESETS[args.preset].dataset}"
        )
    if args.seeds < 1 or args.steps < 1:
        raise ValueError("--seeds and --steps must be at least 1")
    if args.class_order is not None and args.world != "continuous":
        raise ValueError(
            "--class-order is an option of --world continuous only; to permute a "
            "dataset's classes in another world, write them permuted to a file (README, "
            "\"Finger guidance under another BLAS thread count and a permuted class order\")"
        )
    if args.prior and (args.world in PLANE_WORLDS or args.frame == "hypotheses"):
        raise ValueError("--prior starts the learner of the grid, line and pick-and-place "
                         "worlds; not the plane worlds' nor --frame hypotheses'")
    if args.world in PLANE_WORLDS:
        report = simulate_plane_world(args, data_spec(args), console)
        print_plane_report(report, console)
        if args.json:
            args.json.write_text(json.dumps(report, indent=2) + "\n")
        return 0
    if args.frame == "hypotheses":
        return _simulate_frame_hypotheses(args, console)
    planner = {} if args.planner is None else {"planner": args.planner}
    settings = _learner_settings(args, frame=args.frame, **planner)
    config = SessionConfig(
        steps=args.steps,
        grid=args.grid,
        learner=learner_settings(settings, args.frame),
        baseline=args.baseline,
        calibration_trials=args.calibration_trials,
        user_error_rate=args.user_error_rate,
        world=args.world,
    )
    data = data_spec(args)
    if args.prior:
        from dataclasses import replace

        from cfbci.bench_returning import simulation_prior

        config = replace(config, prior=simulation_prior(args.prior, data, args.frame))
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    scheduler = Scheduler.from_options(args.scheduler, args.jobs)
    report = simulate(
        config, data, seeds, scheduler=scheduler, console=console, trace_path=args.trace
    )
    print_report(report, console)
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def _add_bench(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser("bench", help="benchmarks")
    which = p.add_subparsers(dest="bench", required=True)
    from cfbci.bench import add_bench_parsers  # update, simulate

    add_bench_parsers(which)
    from cfbci.bench_returning import add_returning_parser  # returning

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
        "the statuses of each command by mutation kind (cfbci/bench_fuzz.py). Exit 1 if any "
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
    from cfbci.bench_fuzz import check_file, fuzz_recordings

    if args.check_file:
        check_file(main, *args.check_file)
        return 0
    return fuzz_recordings(args.recording, args.mutants, args.seed, args.steps, args.jobs,
                           args.timeout, args.cli_every, args.json, console)


def _run_bench_latency(args: argparse.Namespace, console: Console) -> int:
    from cfbci.latency import bench_latency, print_latency

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


def _add_endpoints(p: argparse.ArgumentParser, listen_help: str, connect_help: str) -> None:
    p.add_argument("--listen", action="append", default=[], metavar="EP", help=listen_help)
    p.add_argument("--connect", action="append", default=[], metavar="EP", help=connect_help)


def _add_zenoh_config(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    p.add_argument(
        "--zenoh-config", type=Path, metavar="FILE",
        help="Zenoh JSON5 configuration merged over the defaults (peer mode, multicast "
        "scouting off); --listen/--connect replace its endpoints (docs/deployment.md)",
    )


def _add_serve(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "serve",
        help="the pipeline service: runs the learner for sources over Zenoh",
        description="Serve calibration-free sessions over Eclipse Zenoh (docs/protocol.md) "
        "until SIGINT or SIGTERM.",
    )
    _add_endpoints(
        p, "Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)",
        "Zenoh endpoint to connect to (repeatable)",
    )
    _add_zenoh_config(p)
    p.add_argument("--record-dir", type=Path, help="write one <session>.mcap per session here")
    p.add_argument(
        "--service-id", help="this service's id among several on one network ([A-Za-z0-9_-], "
        "1-64; default <host>-<pid>): sources that --pick-service name it in their config",
    )
    add_limit_options(p)
    p.set_defaults(run=_run_serve)


def _run_serve(args: argparse.Namespace, console: Console) -> int:
    from cfbci.service import serve

    if not args.listen and not args.connect and args.zenoh_config is None:
        raise ValueError("give at least one --listen or --connect endpoint (or --zenoh-config)")
    from cfbci.limits import from_args
    from wire.services import check_service_id

    serve(
        args.listen, args.connect, args.record_dir, limits=from_args(args),
        zenoh_config=args.zenoh_config,
        service_id=None if args.service_id is None else check_service_id(args.service_id),
    )
    return 0


def _add_source_options(p: argparse.ArgumentParser) -> None:
    _add_data_options(p)
    p.add_argument("--seed", type=int, default=0, help="session seed (default 0)")
    p.add_argument("--steps", type=int, default=500, help="actions in the session (default 500)")
    p.add_argument("--grid", type=int, help="grid side, grid world only (default 5)")
    p.add_argument("--world", choices=(*WORLDS, *LIVE_PLANE_WORLDS), default="grid",
                   help="the world (default grid)")
    p.add_argument("--frame", choices=(*FRAMES, *LIVE_PLANE_WORLDS.values()), default="feedback")
    add_live_plane_options(p)
    _add_likelihood_option(p)
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="a learner setting sent in the config (see calibration_free.config.LearnerConfig)",
    )
    p.add_argument(
        "--interval", type=float, default=0.0,
        help="seconds between a move and the user's epoch (default 0)",
    )
    p.add_argument(
        "--user-error-rate", type=float, default=0.0,
        help="probability that the simulated user's label is wrong (default 0)",
    )


def _grid(args: argparse.Namespace) -> int:
    """The grid side: ``--grid``, which only the grid world takes (default 5)."""
    if args.grid is not None and args.world != "grid":
        raise ValueError(f"--grid applies to --world grid only; this world is {args.world!r}")
    return 5 if args.grid is None else args.grid


def _source_settings(args: argparse.Namespace, session: str) -> Any:
    from acquisition.simulated_source import SourceSettings

    if args.steps < 1 or args.interval < 0:
        raise ValueError("--steps must be at least 1 and --interval at least 0")
    learner = _learner_settings(args)
    plane = live_source_fields(args.world, args.frame, learner, args.class_order)  # fail early
    return SourceSettings(
        session=session, data=data_spec(args), seed=args.seed,
        steps=args.steps, grid=_grid(args), frame=args.frame, learner=learner,
        interval=args.interval, user_error_rate=args.user_error_rate, world=args.world,
        pick_service=getattr(args, "pick_service", False), **plane,
    )


def _add_source(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "source",
        help="the simulated source: a simulated user answering a running service",
        description="Run one session of a simulated user against a running `cfbci serve` "
        "over Zenoh. Exit status: 0 when the session has ended; 1 when the service rejected "
        "it or kept the source waiting longer than --timeout (the reason on one line of "
        "stderr); 2 on bad options or data.",
    )
    p.add_argument(
        "--session", required=True,
        help="session id: NAME, or USER/NAME in a user's key space (each 1-64 of A-Za-z0-9_-)",
    )
    _add_source_options(p)
    p.add_argument(
        "--pick-service", action="store_true",
        help="ask the services on the network for their load and name the least loaded one "
        "in the config, so that exactly one serves the session (wire/services.py)",
    )
    p.add_argument(
        "--timeout", type=float, default=30.0,
        help="seconds the service may keep the source waiting before it gives up (default 30)",
    )
    _add_endpoints(
        p, "Zenoh endpoint to listen on (repeatable)",
        "Zenoh endpoint of the service, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    _add_zenoh_config(p)
    p.set_defaults(run=_run_source)


def _run_source(args: argparse.Namespace, console: Console) -> int:
    from dataclasses import replace

    from acquisition.simulated_source import run_source

    settings = replace(_source_settings(args, args.session), timeout=args.timeout)
    try:
        summary = run_source(settings, args.listen, args.connect, args.zenoh_config)
    except (TimeoutError, RuntimeError) as error:  # as replay --publish and lsl-bridge
        Console(stderr=True).print(f"[bold red]error:[/] {error}", soft_wrap=True)
        return 1
    console.print(
        f"session {summary.session!r}: {summary.steps} steps, first target "
        f"{summary.first_target_step or '-'}, correct {summary.correct_targets}, "
        f"wrong {summary.wrong_targets}"
    )
    return 0


def _add_session(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "session",
        help="a live session: service and simulated source over an embedded Zenoh network",
        description="Start the service and the simulated source as separate processes on a "
        "loopback Zenoh network, show the session live, record it and summarise it. Every "
        "input (dataset, world and options, the service's limits) is checked before anything "
        "starts. The service's limits are those of cfbci serve, but --max-session-mb, which "
        "defaults to the machine's physical memory.",
    )
    _add_source_options(p)
    add_limit_options(p)
    p.add_argument(
        "--record", type=Path, help="MCAP recording to write (default runs/<timestamp>.mcap)"
    )
    p.add_argument(
        "--overwrite", action="store_true",
        help="replace the --record file if it exists (else an existing file is an error)",
    )
    p.add_argument("--json", type=Path, help="write the summary as JSON")
    _add_endpoints(
        p, "endpoint the service listens on (default a free tcp/127.0.0.1 port; repeatable)",
        "endpoint the service connects to (repeatable)",
    )
    _add_zenoh_config(p)
    p.set_defaults(run=_run_session)


def _run_session(args: argparse.Namespace, console: Console) -> int:
    import time

    from acquisition.simulated_source import session_config
    from cfbci.limits import from_args
    from cfbci.live import (
        default_recording,
        own_limits,
        print_summary,
        run_live_session,
        session_id_for,
        write_json,
    )
    from cfbci.service.admission import check_config

    record = args.record or default_recording()
    settings = _source_settings(args, session_id_for(record))
    limits = from_args(args)
    if limits.max_session_mb == ServiceLimits().max_session_mb:  # the flag's default
        limits = replace(limits, max_session_mb=own_limits().max_session_mb)
    # Before anything starts: the data load, and the service would admit the config.
    check_config(session_config(settings), limits, ValueError)
    start = time.monotonic()
    try:
        result = run_live_session(
            settings, record, listen=args.listen, connect=args.connect, console=console,
            zenoh_config=args.zenoh_config, overwrite=args.overwrite, limits=limits,
        )
    except FileExistsError as error:
        Console(stderr=True).print(f"[bold red]error:[/] {error}")
        return 2
    except (TimeoutError, RuntimeError) as error:
        Console(stderr=True).print(f"[bold red]error:[/] {error}")
        return 1
    print_summary(result, console, time.monotonic() - start)
    if args.json:
        write_json(result, args.json)
    return 0


def _add_recover(commands: argparse._SubParsersAction) -> None:
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
    p.set_defaults(run=_run_recover)


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
    n_messages = recover(source, out)
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


def _add_replay(commands: argparse._SubParsersAction) -> None:
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
    _add_endpoints(
        publish, "Zenoh endpoint to listen on (repeatable)",
        "Zenoh endpoint of the service, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    _add_zenoh_config(publish)
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
    from cfbci.reanalysis import reanalyse
    from cfbci.reanalysis_output import print_reanalysis

    result = reanalyse(args.file, _alternatives(args.option, args.compare))
    print_reanalysis(result, console, per_step=args.per_step)
    if args.json:
        args.json.write_text(json.dumps(result.to_json(), indent=2) + "\n")
    return 0 if result.outcomes[0].identical_to_recording else 1


def _replay_publish(args: argparse.Namespace, console: Console) -> int:
    from cfbci.publish import DEFAULT_TIMEOUT, check_speed, print_publish, run_publish

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


def _add_report(commands: argparse._SubParsersAction) -> None:
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
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output directory")
    add_scheduler_options(p)
    p.set_defaults(run=_run_report)


def _run_report(args: argparse.Namespace, console: Console) -> int:
    from cfbci.report import print_summary, run_report

    for name in ("metrics.json", "index.html"):
        for source in args.files:
            _refuse_overwriting(source, args.out / name)
    scheduler = Scheduler.from_options(args.scheduler, args.jobs)
    reports = run_report(args.files, args.out, scheduler=scheduler, console=console)
    print_summary(reports, console)
    errors = [r.error for r in reports if r.error]
    for error in errors:
        Console(stderr=True).print(f"[bold red]error:[/] {error}", soft_wrap=True)
    console.print(f"report: {args.out / 'index.html'} (metrics {args.out / 'metrics.json'})")
    damaged = [r for r in reports if r.metrics is not None and r.metrics.damage]
    return 1 if errors else 3 if damaged else 0


def build_parser(chosen: Preset | None = None) -> argparse.ArgumentParser:
    """The ``cfbci`` parser; with ``chosen``, its settings are ``simulate``'s defaults."""
    parser = argparse.ArgumentParser(
        prog="cfbci", description="Calibration-free brain-computer interface."
    )
    parser.add_argument("--version", action="version", version=metadata.version("cfbci"))
    parser.add_argument(
        "--blas-threads", type=int, default=1, metavar="N",
        help="BLAS threads of this process and its children (default 1: the learner's "
        "products are small, and threads wait for each other; more changes results by "
        "rounding only)",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    _add_simulate(commands, chosen)
    _add_bench(commands)
    _add_serve(commands)
    _add_source(commands)
    _add_session(commands)
    _add_recover(commands)
    _add_replay(commands)
    _add_report(commands)
    router.add_parser(commands)
    add_sweep_command(commands)
    add_export_command(commands)
    add_compare_command(commands)
    add_curves_command(commands)
    add_datasets_command(commands)
    _add_zenoh_config(add_view_command(commands))
    add_world_command(commands)
    from cfbci.lsl_commands import add_lsl_commands  # here: it imports this module's helpers

    add_lsl_commands(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cfbci`` console script."""
    args = build_parser().parse_args(argv)
    if getattr(args, "preset", None):  # parse again, the preset's settings as defaults
        args = build_parser(PRESETS[args.preset]).parse_args(argv)
    keep_freed_memory()
    console = Console(stderr=False)
    try:
        limit_blas_threads(args.blas_threads)
        return args.run(args, console)
    except (ValueError, FileNotFoundError) as error:
        # soft_wrap: a long path is never broken across lines (it can be copied)
        Console(stderr=True).print(f"[bold red]error:[/] {error}", soft_wrap=True)
        return 2
    except zenoh.ZError as error:  # e.g. nobody at the endpoints, or credentials refused
        Console(stderr=True).print(
            f"[bold red]error:[/] Zenoh: {error}\n(check the endpoints, and the credentials "
            "and certificates of --zenoh-config)", soft_wrap=True,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
