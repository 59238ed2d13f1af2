"""The ``cfbci`` command line: one module per command group, and nothing else parses
arguments.

- :mod:`cfbci.cli.simulate`: ``simulate``, ``sweep``, ``compare``, ``curves``, ``world check``;
- :mod:`cfbci.cli.bench`: ``bench ...``;
- :mod:`cfbci.cli.service`: ``serve``, ``source``, ``session``, ``router``;
  :mod:`cfbci.cli.priors`: ``priors list|add|delete``;
- :mod:`cfbci.cli.recordings`: ``recover``, ``replay``, ``report``, ``export``;
- :mod:`cfbci.cli.lsl`: ``lsl-bridge``, ``lsl-simulator``, ``lsl-check``;
- :mod:`cfbci.cli.view`: ``view``; :mod:`cfbci.cli.datasets`: ``datasets ...``;
- :mod:`cfbci.cli.options`: the options several commands share.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from importlib import metadata

import zenoh
from rich.console import Console

from cfbci.blas import limit_blas_threads
from cfbci.cli.bench import add_bench_command
from cfbci.cli.datasets import add_datasets_command
from cfbci.cli.lsl import add_lsl_commands
from cfbci.cli.options import add_zenoh_config
from cfbci.cli.priors import add_priors_command
from cfbci.cli.recordings import (
    add_export_command,
    add_recover_command,
    add_replay_command,
    add_report_command,
)
from cfbci.cli.service import (
    add_router_command,
    add_serve_command,
    add_session_command,
    add_source_command,
)
from cfbci.cli.simulate import (
    add_compare_command,
    add_curves_command,
    add_simulate_command,
    add_sweep_command,
    add_world_command,
)
from cfbci.cli.view import add_view_command
from cfbci.memory import keep_freed_memory
from cfbci.offline.presets import PRESETS, Preset


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
    add_simulate_command(commands, chosen)
    add_bench_command(commands)
    add_serve_command(commands)
    add_source_command(commands)
    add_session_command(commands)
    add_priors_command(commands)
    add_recover_command(commands)
    add_replay_command(commands)
    add_report_command(commands)
    add_router_command(commands)
    add_sweep_command(commands)
    add_export_command(commands)
    add_compare_command(commands)
    add_curves_command(commands)
    add_datasets_command(commands)
    add_zenoh_config(add_view_command(commands))
    add_world_command(commands)
    add_lsl_commands(commands)
    # A command that runs other commands in its process (the recordings' fuzz bench) takes
    # the entry point from here, so that no command module imports this one.
    parser.set_defaults(cli_main=main)
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

