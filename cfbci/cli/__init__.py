"""The ``cfbci`` command line: one module per command group, and nothing else parses
arguments.

- `cfbci.cli.simulate`: ``simulate``, ``sweep``, ``compare``, ``curves``, ``world check``;
- `cfbci.cli.bench`: ``bench ...``;
- `cfbci.cli.service`: ``serve``, ``source``, ``session``, ``router``;
  `cfbci.cli.priors`: ``priors list|add|delete``;
  `cfbci.cli.control`: ``control pause|resume|end|target``;
- `cfbci.cli.recordings`: ``recover``, ``replay``, ``report``, ``export``;
- `cfbci.cli.lsl`: ``lsl-bridge``, ``lsl-simulator``, ``lsl-check``;
- `cfbci.cli.view`: ``view``; `cfbci.cli.datasets`: ``datasets ...``;
- `cfbci.cli.options`: the options several commands share.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from importlib import import_module, metadata

import zenoh
from rich.console import Console

from cfbci.blas import limit_blas_threads
from cfbci.memory import keep_freed_memory
from cfbci.offline.presets import PRESETS, Preset

#: The command groups, in the order of ``cfbci --help``: the commands each adds, and the
#: module and function that add them. A command line builds, and so imports, only its
#: own group (``cfbci datasets path`` and ``cfbci --version`` start without the
#: scientific stack); ``--help`` and an unknown command build them all.
COMMAND_GROUPS: tuple[tuple[tuple[str, ...], str], ...] = (
    (("simulate",), "cfbci.cli.simulate:add_simulate_command"),
    (("bench",), "cfbci.cli.bench:add_bench_command"),
    (("serve",), "cfbci.cli.service:add_serve_command"),
    (("source",), "cfbci.cli.service:add_source_command"),
    (("session",), "cfbci.cli.service:add_session_command"),
    (("priors",), "cfbci.cli.priors:add_priors_command"),
    (("recover",), "cfbci.cli.recordings:add_recover_command"),
    (("replay",), "cfbci.cli.recordings:add_replay_command"),
    (("report",), "cfbci.cli.recordings:add_report_command"),
    (("router",), "cfbci.cli.service:add_router_command"),
    (("control",), "cfbci.cli.control:add_control_command"),
    (("sweep",), "cfbci.cli.simulate:add_sweep_command"),
    (("export",), "cfbci.cli.recordings:add_export_command"),
    (("compare",), "cfbci.cli.simulate:add_compare_command"),
    (("curves",), "cfbci.cli.simulate:add_curves_command"),
    (("datasets",), "cfbci.cli.datasets:add_datasets_command"),
    (("view",), "cfbci.cli.view:add_view_command"),
    (("world",), "cfbci.cli.simulate:add_world_command"),
    (("lsl-bridge", "lsl-simulator", "lsl-check"), "cfbci.cli.lsl:add_lsl_commands"),
)


def _add_group(commands: argparse._SubParsersAction, target: str, chosen: Preset | None) -> None:
    module, function = target.split(":")
    add = getattr(import_module(module), function)
    if function == "add_simulate_command":
        add(commands, chosen)
    elif function == "add_view_command":
        from cfbci.cli.options import add_zenoh_config

        add_zenoh_config(add(commands))
    else:
        add(commands)


def _own_command(argv: Sequence[str] | None) -> str | None:
    """The command a command line names (its first word after the global options), "" for
    ``--version`` alone, None when the whole parser is needed (no or an unknown command)."""
    words = list(sys.argv[1:] if argv is None else argv)
    while words and words[0].startswith("-"):
        option = words.pop(0)
        if option == "--blas-threads" and words:
            words.pop(0)
        elif option in ("--version",):
            return ""
        elif option in ("-h", "--help"):
            return None
    known = {name for names, _ in COMMAND_GROUPS for name in names}
    return words[0] if words and words[0] in known else None


def build_parser(
    chosen: Preset | None = None, only: str | None = None
) -> argparse.ArgumentParser:
    """The ``cfbci`` parser; with ``chosen``, its settings are ``simulate``'s defaults; with
    ``only``, the parser of that command's group alone (``""``: of none)."""
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
    for names, target in COMMAND_GROUPS:
        if only is None or only in names:
            _add_group(commands, target, chosen)
    # A command that runs other commands in its process (the recordings' fuzz bench) takes
    # the entry point from here, so that no command module imports this one.
    parser.set_defaults(cli_main=main)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cfbci`` console script."""
    only = _own_command(argv)
    args = build_parser(only=only).parse_args(argv)
    if getattr(args, "preset", None):  # parse again, the preset's settings as defaults
        args = build_parser(PRESETS[args.preset], only).parse_args(argv)
    keep_freed_memory()
    console = Console(stderr=False)
    try:
        limit_blas_threads(args.blas_threads)
        return args.run(args, console)
    except (ValueError, FileNotFoundError, FileExistsError, IsADirectoryError,
            NotADirectoryError) as error:  # an output that exists: see cfbci.outputs
        # soft_wrap: a long path is never broken across lines (it can be copied)
        Console(stderr=True).print(f"[bold red]error:[/] {error}", soft_wrap=True)
        return 2
    except zenoh.ZError as error:  # e.g. nobody at the endpoints, or credentials refused
        Console(stderr=True).print(
            f"[bold red]error:[/] Zenoh: {error}\n(check the endpoints, and the credentials "
            "and certificates of --zenoh-config)", soft_wrap=True,
        )
        return 1

