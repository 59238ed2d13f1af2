"""``cfbci view``: the command of the live view in the browser (the server is
:mod:`cfbci.view_server`, imported when the command runs).

``cfbci view --connect EP [--port 8080]`` serves the operator view at ``/`` and the
subject view at ``/subject?session=ID``.
"""

from __future__ import annotations

import argparse
import logging


def add_view_command(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``cfbci view``; return its parser (the CLI adds the shared
    ``--zenoh-config`` option to it)."""
    p = commands.add_parser(
        "view",
        help="live view of sessions in a web browser (operator and subject pages)",
        description="Serve the operator view (/) and the subject view (/subject?session=ID) "
        "of the sessions on Zenoh, until SIGINT or SIGTERM.",
    )
    p.add_argument("--connect", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint to connect to, e.g. the service's (repeatable)")
    p.add_argument("--listen", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint to listen on (default without --zenoh-config: a free "
                   "tcp/127.0.0.1 port)")
    p.add_argument("--host", default="127.0.0.1",
                   help="HTTP address to bind (default 127.0.0.1; 0.0.0.0 for other machines)")
    p.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080; 0: any)")
    p.set_defaults(run=_run_view)
    return p


def _print_addresses(host: str, port: int) -> None:
    base = f"http://{host}:{port}"
    print(f"operator view: {base}/   subject view: {base}/subject?session=ID", flush=True)


def _run_view(args: argparse.Namespace, _: object) -> int:
    from cfbci.view_server import run_view

    zenoh_config = getattr(args, "zenoh_config", None)
    if not args.connect and not args.listen and zenoh_config is None:
        raise ValueError(
            "give at least one --connect endpoint (the service's or a router's), --listen "
            "or --zenoh-config"
        )
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be in 0..65535; got {args.port}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("aiohttp.access").setLevel(logging.WARNING)  # not every file served
    run_view(args.listen, args.connect, zenoh_config, host=args.host, port=args.port,
             on_ready=_print_addresses)
    return 0
