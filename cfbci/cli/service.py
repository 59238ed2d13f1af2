"""``cfbci serve``, ``source``, ``session`` and ``router``: the service, a simulated
source, a whole live session on this machine, and a Zenoh router."""

from __future__ import annotations

import argparse
import time
from dataclasses import fields, replace
from pathlib import Path

from rich.console import Console

from cfbci.cli.options import (
    add_endpoints,
    add_prior_option,
    add_source_options,
    add_zenoh_config,
    checked_prior,
    source_settings,
)
from cfbci.service.limits import LIMIT_HELP, ServiceLimits
from cfbci.service.router import run_router


def add_serve_command(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "serve",
        help="the pipeline service: runs the learner for sources over Zenoh",
        description="Serve calibration-free sessions over Eclipse Zenoh (docs/protocol.md) "
        "until SIGINT or SIGTERM.",
    )
    add_endpoints(
        p, "Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)",
        "Zenoh endpoint to connect to (repeatable)",
    )
    add_zenoh_config(p)
    p.add_argument("--record-dir", type=Path, help="write one <session>.mcap per session here")
    p.add_argument(
        "--prior-dir", type=Path,
        help="the prior store: earlier recordings of each user, <dir>/<user>/<sha256>.mcap, "
        "which configs name and sources upload (default <record-dir>/priors; none without "
        "--record-dir)",
    )
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
    from wire.services import check_service_id

    serve(
        args.listen, args.connect, args.record_dir, limits=limits_from_args(args),
        zenoh_config=args.zenoh_config,
        service_id=None if args.service_id is None else check_service_id(args.service_id),
        prior_dir=args.prior_dir,
    )
    return 0


def add_source_command(commands: argparse._SubParsersAction) -> None:
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
    add_source_options(p)
    add_prior_option(p)
    p.add_argument(
        "--pick-service", action="store_true",
        help="ask the services on the network for their load and name the least loaded one "
        "in the config, so that exactly one serves the session (wire/services.py)",
    )
    p.add_argument(
        "--timeout", type=float, default=30.0,
        help="seconds the service may keep the source waiting before it gives up (default 30)",
    )
    add_endpoints(
        p, "Zenoh endpoint to listen on (repeatable)",
        "Zenoh endpoint of the service, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    add_zenoh_config(p)
    p.set_defaults(run=_run_source)


def _run_source(args: argparse.Namespace, console: Console) -> int:
    from dataclasses import replace

    from acquisition.simulated_source import run_source

    settings = replace(source_settings(args, args.session), timeout=args.timeout,
                       prior=checked_prior(args))
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


def add_session_command(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser(
        "session",
        help="a live session: service and simulated source over an embedded Zenoh network",
        description="Start the service and the simulated source as separate processes on a "
        "loopback Zenoh network, show the session live, record it and summarise it. Every "
        "input (dataset, world and options, the service's limits) is checked before anything "
        "starts. The service's limits are those of cfbci serve, but --max-session-mb, which "
        "defaults to the machine's physical memory.",
    )
    add_source_options(p)
    add_prior_option(p)
    add_limit_options(p)
    p.add_argument(
        "--record", type=Path, help="MCAP recording to write (default runs/<timestamp>.mcap)"
    )
    p.add_argument(
        "--overwrite", action="store_true",
        help="replace the --record file if it exists (else an existing file is an error)",
    )
    p.add_argument("--json", type=Path, help="write the summary as JSON")
    add_endpoints(
        p, "endpoint the service listens on (default a free tcp/127.0.0.1 port; repeatable)",
        "endpoint the service connects to (repeatable)",
    )
    add_zenoh_config(p)
    p.set_defaults(run=_run_session)


def _run_session(args: argparse.Namespace, console: Console) -> int:

    from acquisition.simulated_source import session_config
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
    settings = replace(source_settings(args, session_id_for(record)), prior=checked_prior(args))
    limits = limits_from_args(args)
    if limits.max_session_mb == ServiceLimits().max_session_mb:  # the flag's default
        limits = replace(limits, max_session_mb=own_limits().max_session_mb)
    # Before anything starts: the data load, and the service would admit the config.
    config = session_config(settings)
    check_config(config, limits, ValueError)
    if settings.prior:
        from cfbci.service.priors import check_space
        from replay.prior import read_prior

        check_space(read_prior(settings.prior), config)
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


def add_limit_options(parser: argparse.ArgumentParser) -> None:
    """Add one ``--max-sessions``-style flag per limit, defaulting to `ServiceLimits`."""
    defaults = ServiceLimits()
    for spec in fields(ServiceLimits):
        default = getattr(defaults, spec.name)
        parser.add_argument(
            f"--{spec.name.replace('_', '-')}", type=type(default), default=default,
            help=f"{LIMIT_HELP[spec.name]} (default {default:g})",
        )


def limits_from_args(args: argparse.Namespace) -> ServiceLimits:
    """The limits given by `add_options`' flags."""
    return ServiceLimits(**{spec.name: getattr(args, spec.name) for spec in fields(ServiceLimits)})


def add_router_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci router`` (its options and the function that runs it)."""
    p = commands.add_parser(
        "router",
        help="a Zenoh router joining services and sources (and enforcing a policy)",
        description="Run a router-mode Zenoh session until SIGINT or SIGTERM. Services and "
        "sources in client mode connect to it; with --zenoh-config it can require TLS, "
        "user/password authentication and access control (docs/deployment.md).",
    )
    p.add_argument(
        "--listen", action="append", default=[], metavar="EP",
        help="endpoint to accept connections on, e.g. tls/0.0.0.0:7447 (repeatable; "
        "replaces the file's listen/endpoints)",
    )
    p.add_argument(
        "--connect", action="append", default=[], metavar="EP",
        help="another router to connect to (repeatable)",
    )
    p.add_argument(
        "--zenoh-config", type=Path, metavar="FILE",
        help="Zenoh JSON5 configuration merged over the defaults (router mode, multicast "
        "scouting off)",
    )
    p.set_defaults(run=_run_router)


def _run_router(args: argparse.Namespace, console: Console) -> int:
    try:
        run_router(args.listen, args.connect, args.zenoh_config)
    except RuntimeError as error:
        Console(stderr=True).print(f"[bold red]error:[/] {error}", soft_wrap=True)
        return 1
    return 0
