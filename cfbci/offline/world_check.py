"""``cfbci world check``: the task hypotheses of a world that no signal can tell apart."""

from __future__ import annotations

import argparse

from rich.console import Console

from calibration_free.frames import FRAMES, Frame
from calibration_free.identifiability import Confusable, confusable_pairs
from calibration_free.world import World
from calibration_free.worlds import WORLDS, make_world


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
    check.set_defaults(run=_run_check)


def describe(world: World, frame: Frame, pair: Confusable) -> str:
    """One line: the two tasks, how they are confused, and the class renaming if any."""
    names = frame.class_names()
    text = f"{world.task_name(pair.task)} / {world.task_name(pair.other)}: {pair.kind}"
    if pair.kind == "symmetric":
        renaming = ", ".join(
            f"{names[k]} -> {names[image]}"
            for k, image in enumerate(pair.permutation)
            if image != k
        )
        text += f" ({renaming})"
    return text


def _run_check(args: argparse.Namespace, console: Console) -> int:
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
