"""``cfbci simulate``, ``sweep``, ``compare``, ``curves`` and ``world check``: offline
sessions, their sweeps and figures."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

from rich.console import Console

from acquisition.sources import DEFAULT_SYNTHETIC_ACCURACY, DataSpec
from calibration_free.baseline import DEFAULT_CALIBRATION_TRIALS
from calibration_free.config import LearnerConfig
from calibration_free.continuous_goals import PROBINGS, SAMPLINGS, ContinuousConfig
from calibration_free.frames import FRAMES, Frame
from calibration_free.identifiability import confusable_pairs
from calibration_free.planning import PLANNERS
from calibration_free.puddle_learner import EXPLORATIONS, PuddleConfig
from calibration_free.worlds import WORLDS, make_world
from cfbci.cli.options import (
    add_data_options,
    add_likelihood_option,
    data_spec,
    learner_settings_of,
    parse_settings,
)
from cfbci.offline.compare import ALTERNATIVES, rank_test
from cfbci.offline.curves import STATISTICS, STEP_AXES, plot_curves, run_series
from cfbci.offline.parallel import Scheduler, run_parallel
from cfbci.offline.plane_worlds import (
    PLANE_WORLDS,
    PlaneJob,
    parse_class_order,
    plane_summary,
    print_plane_report,
    run_plane_job,
)
from cfbci.offline.presets import PRESETS, Preset
from cfbci.offline.simulation import BASELINES, SessionConfig
from cfbci.offline.sweep import SYNTHETIC, parse_grid, print_summary, run_sweep, sweep_cells
from cfbci.offline.world_check import describe
from session.config import learner_settings


def add_simulate_command(commands: argparse._SubParsersAction, chosen: Preset | None) -> None:
    p = commands.add_parser(
        "simulate",
        help="offline closed-loop sessions with a simulated user (no network)",
        description="Run sessions of the calibration-free learner (or the calibrated "
        "baseline) against a simulated user answering from a dataset, and summarise them.",
    )
    add_data_options(p)
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
    add_likelihood_option(p)
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
    from cfbci.offline.frame_sessions import FrameJob, frame_hypotheses_report, run_frame_job

    # The pairs' learners share these settings; their own frames are the pairs'.
    config = learner_settings(learner_settings_of(args, **FRAME_DEFAULTS), LearnerConfig.frame)
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
    """The frame-hypotheses summary (`cfbci.offline.frame_sessions.frame_hypotheses_report`)
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
    from cfbci.offline.simulate import print_report, simulate

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
    settings = learner_settings_of(args, frame=args.frame, **planner)
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

        from cfbci.bench.returning import simulation_prior

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


def add_plane_world_options(parser: argparse.ArgumentParser) -> None:
    """The options of the plane worlds on ``cfbci simulate``."""
    parser.add_argument(
        "--hypotheses", type=int, default=50, help="continuous world: particles (default 50)"
    )
    parser.add_argument(
        "--sampling", choices=SAMPLINGS, default="active",
        help="continuous world: how the particles are resampled (default active)",
    )
    parser.add_argument(
        "--class-order", default=None, metavar="K,K,K,K",
        help="continuous world: dataset class of each direction up,down,right,left "
        "(default 0,1,2,3; the learner never knows it)",
    )
    parser.add_argument(
        "--exploration", choices=EXPLORATIONS, default="planning",
        help="puddle world: exploration strategy (default planning)",
    )


def simulate_plane_world(
    args: argparse.Namespace, data: DataSpec, console: Console
) -> dict[str, Any]:
    """Run ``args.seeds`` sessions of ``args.world``; the JSON report."""
    if args.world == "puddle" and (args.dataset is not None or args.synthetic != "errp"):
        raise ValueError(
            "the puddle world's signals are its own six-class 20-D Gaussian data; leave "
            "--dataset and --synthetic out"
        )
    probing = args.planner or "uncertainty"
    continuous = ContinuousConfig(
        n_hypotheses=args.hypotheses, sampling=args.sampling,
        probing="uncertainty" if probing == "uncertainty" else "random",
    )
    if args.world == "continuous":
        if probing not in PROBINGS:
            raise ValueError(f"the continuous world's --planner is one of {PROBINGS}")
        data.resolve("guidance")  # fail early on a bad dataset
    puddle = PuddleConfig(exploration=args.exploration)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    jobs = [
        PlaneJob(args.world, seed, args.steps, data, continuous, puddle,
                 parse_class_order(args.class_order))
        for seed in seeds
    ]
    scheduler = Scheduler.from_options(args.scheduler, args.jobs)
    sessions = run_parallel(
        run_plane_job, jobs, scheduler=scheduler, description="sessions", console=console
    )
    return {
        "config": _plane_config(args, data), "sessions": sessions,
        "summary": plane_summary(sessions),
    }


def _plane_config(args: argparse.Namespace, data: DataSpec) -> dict[str, Any]:
    config: dict[str, Any] = {"world": args.world, "steps": args.steps}
    if args.world == "continuous":
        config.update(
            dataset=data.describe(), hypotheses=args.hypotheses, sampling=args.sampling,
            planner=args.planner or "uncertainty", class_order=args.class_order,
        )
    else:
        config.update(exploration=args.exploration)
    return config


def add_scheduler_options(parser: argparse.ArgumentParser) -> None:
    """``--jobs`` and ``--scheduler``, as `Scheduler.from_options` reads them."""
    parser.add_argument(
        "--jobs", type=int, default=0,
        help="worker processes of the local Dask cluster (default: one per core; 1: run in "
        "this process)",
    )
    parser.add_argument(
        "--scheduler", metavar="local|tcp://HOST:PORT",
        help="'local': a Dask LocalCluster on loopback with --jobs workers (the default when "
        "--jobs > 1); tcp://HOST:PORT: run on the existing Dask cluster of that scheduler",
    )


def add_sweep_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci sweep``."""
    p = commands.add_parser(
        "sweep",
        help="sessions over the cross product of learner settings, datasets and seeds",
        description="Run `cfbci simulate`'s sessions for every combination of the --grid "
        "settings with every dataset and seed, on Dask, and write one simulate-format JSON "
        "per cell, summary.json, summary.csv and summary.png into --out.",
    )
    p.add_argument(
        "--grid", required=True, metavar="'KEY=V1,V2 KEY=V1,V2'",
        help="learner settings to cross (calibration_free.config.LearnerConfig fields)",
    )
    p.add_argument(
        "--datasets", nargs="+", required=True, metavar="PATH",
        help=f"dataset files (as simulate's --dataset), or {SYNTHETIC!r} for the generator",
    )
    p.add_argument("--seeds", type=int, default=20, help="sessions per cell (default 20)")
    p.add_argument("--first-seed", type=int, default=0, help="seed of the first session")
    p.add_argument("--steps", type=int, default=500, help="actions per session (default 500)")
    p.add_argument("--side", type=int, default=5, help="grid side (default 5)")
    p.add_argument("--frame", choices=FRAMES, default="feedback")
    p.add_argument("--user-error-rate", type=float, default=0.0)
    p.add_argument(
        "--synthetic-accuracy", type=float, default=DEFAULT_SYNTHETIC_ACCURACY,
        help=f"difficulty of the {SYNTHETIC!r} dataset (nominal balanced LDA accuracy)",
    )
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="a learner setting fixed for every cell",
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output directory")
    add_scheduler_options(p)
    p.set_defaults(run=_run_sweep)


def _run_sweep(args: argparse.Namespace, console: Console) -> int:

    if args.seeds < 1 or args.steps < 1:
        raise ValueError("--seeds and --steps must be at least 1")
    grid = parse_grid(args.grid, lambda key, raw: parse_settings([f"{key}={raw}"])[key])
    datasets = [
        DataSpec(None if name == SYNTHETIC else Path(name), args.synthetic_accuracy)
        for name in args.datasets
    ]
    cells = sweep_cells(
        grid, datasets, fixed=parse_settings(args.set), steps=args.steps, side=args.side,
        frame=args.frame, user_error_rate=args.user_error_rate,
    )
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    scheduler = Scheduler.from_options(args.scheduler, args.jobs)
    done, summary = run_sweep(cells, seeds, args.out, scheduler=scheduler, console=console)
    print_summary(done, summary, console)
    console.print(f"sweep: {args.out / 'summary.json'}, {args.out / 'summary.png'}")
    return 0


def run_compare(args: argparse.Namespace, console: Console) -> int:
    """``cfbci compare``: print the test (and write it as JSON if asked)."""
    test = rank_test(args.a, args.b, args.metric, args.alternative)
    side = {"less": "one-sided, A < B", "greater": "one-sided, A > B"}.get(
        test.alternative, "two-sided"
    )
    console.print(
        f"{test.metric}: A median {test.median_a:.4g} (n = {test.n_a}), B median "
        f"{test.median_b:.4g} (n = {test.n_b}); Mann-Whitney U = {test.u_statistic:.1f}, "
        f"{side}: p = {test.p_value:.3g}", soft_wrap=True,
    )
    if args.json:
        args.json.write_text(json.dumps(asdict(test), indent=2) + "\n")
    return 0


def add_compare_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci compare``."""
    p = commands.add_parser(
        "compare",
        help="a Mann-Whitney rank test of a per-session number between two simulate runs",
        description="Tests whether the sessions of run A tend to have smaller (--alternative "
        "less), larger (greater) or different (two-sided) values of --metric than those of "
        "run B; both are cfbci simulate --json files.",
    )
    p.add_argument("a", type=Path, help="simulate JSON of run A")
    p.add_argument("b", type=Path, help="simulate JSON of run B")
    p.add_argument("--metric", required=True, help="a per-session number, e.g. final_distance")
    p.add_argument("--alternative", choices=ALTERNATIVES, default="less")
    p.add_argument("--json", type=Path, help="write the test as JSON")
    p.set_defaults(run=run_compare)


def run_curves(args: argparse.Namespace, console: Console) -> int:
    """``cfbci curves``: read the runs, draw them, print the figure's path."""
    runs = {path.stem: run_series(path, args.metric) for path in args.runs}
    if len(runs) != len(args.runs):
        raise ValueError("two runs have the same file name: their labels would clash")
    plot_curves(runs, args.metric, args.statistic, args.out, log_y=args.log_y)
    console.print(
        f"wrote {args.out} ({len(runs)} runs, {args.metric}, {args.statistic})", soft_wrap=True
    )
    return 0


def add_curves_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci curves``."""
    p = commands.add_parser(
        "curves",
        help="the mean (or median) curve of a per-session series of several simulate runs",
    )
    p.add_argument("runs", type=Path, nargs="+", help="simulate JSON files (label: file name)")
    p.add_argument("--metric", required=True, choices=sorted(STEP_AXES))
    p.add_argument("--statistic", choices=STATISTICS, default="mean")
    p.add_argument("--log-y", action="store_true", help="a log scale for the values")
    p.add_argument("--out", type=Path, required=True, help="the figure (.png, .pdf, .svg)")
    p.set_defaults(run=run_curves)


def add_world_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci world check``."""
    p = commands.add_parser("world", help="properties of the worlds")
    which = p.add_subparsers(dest="world_command", required=True)
    check = which.add_parser(
        "check",
        help="list the pairs of tasks no signal can tell apart (identical, or symmetric under "
        "a renaming of the classes); exit 1 if there is any",
    )
    check.add_argument("--world", choices=WORLDS, default="grid")
    check.add_argument("--grid", type=int, default=5, help="grid side (grid world)")
    check.add_argument(
        "--actions", type=int, choices=(2, 3),
        help="line world: 3 (right, left, no-move; default) or 2 (without no-move)",
    )
    check.add_argument(
        "--frame", choices=(*FRAMES, "all"), default="all", help="frame(s) to check"
    )
    check.add_argument(
        "--eps", type=float, default=0.1, help="the frame's assumed user error rate"
    )
    check.set_defaults(run=_run_world_check)


def _run_world_check(args: argparse.Namespace, console: Console) -> int:
    world = make_world(args.world, grid=args.grid, actions=args.actions)
    frames = FRAMES if args.frame == "all" else (args.frame,)
    flagged = 0
    for kind in frames:
        frame = Frame(world, kind, args.eps)
        pairs = confusable_pairs(frame)
        flagged += len(pairs)
        head = (
            f"{world.name} world, {world.n_tasks} tasks, actions {', '.join(world.action_names)}"
            f"; {kind} frame:"
        )
        if not pairs:
            console.print(f"{head} clear (every pair of tasks can be told apart)")
            continue
        console.print(f"{head} {len(pairs)} pair(s) no signal can tell apart")
        for pair in pairs:
            console.print(f"  {describe(world, frame, pair)}")
    return 1 if flagged else 0
