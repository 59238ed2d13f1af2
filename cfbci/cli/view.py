"""``cfbci view``: the command of the live view in the browser (the server is
:mod:`cfbci.view.server`, imported when the command runs).

``cfbci view --connect EP [--port 8080]`` serves the operator view at ``/`` and the
subject view at ``/subject?session=ID``, to this machine only by default, and to a browser
that has the access token only: it prints both addresses with the token
(``?token=...``). The token is ``--token``, else the environment variable
:data:`cfbci.view.TOKEN_ENV`, else a random one made at start.
"""

from __future__ import annotations

import argparse
import logging
import os
import secrets

from cfbci.view import TOKEN_ENV


def add_view_command(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``cfbci view``; return its parser (the CLI adds the shared
    ``--zenoh-config`` option to it)."""
    p = commands.add_parser(
        "view",
        help="live view of sessions in a web browser (operator and subject pages)",
        description="Serve the operator view (/) and the subject view (/subject?session=ID) "
        "of the sessions on Zenoh, until SIGINT or SIGTERM. Every page needs the access "
        "token, which the addresses printed at start carry (?token=...).",
    )
    p.add_argument("--connect", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint to connect to, e.g. the service's (repeatable)")
    p.add_argument("--listen", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint to listen on (default without --zenoh-config: a free "
                   "tcp/127.0.0.1 port)")
    p.add_argument("--host", default="127.0.0.1",
                   help="HTTP address to bind (default 127.0.0.1: this machine only; "
                   "0.0.0.0 for other machines, with --allow-host for the name they use)")
    p.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080; 0: any)")
    p.add_argument("--token", metavar="TOKEN",
                   help=f"access token of the pages (default: ${TOKEN_ENV}, else a random "
                   "one; at least 16 characters of A-Z a-z 0-9 . _ ~ -). The environment "
                   "keeps it out of the process list")
    p.add_argument("--allow-host", action="append", default=[], metavar="NAME[:PORT]",
                   help="one more host name the pages may be reached under (repeatable; "
                   "always allowed: the bound address, localhost, 127.0.0.1 and [::1], on "
                   "the view's port; without PORT: the view's)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                   help="one more origin http(s)://NAME[:PORT] whose pages may use the view, "
                   "e.g. a reverse proxy's (repeatable)")
    p.add_argument("--hide-truth", action="store_true",
                   help="take in no truth messages: the pages never show the user's target, "
                   "nor whether a declared target was the user's")
    p.set_defaults(run=_run_view)
    return p


def _token(args: argparse.Namespace) -> tuple[str, str]:
    """The access token and where it came from."""
    if args.token is not None:
        return args.token, "--token"
    if os.environ.get(TOKEN_ENV):
        return os.environ[TOKEN_ENV], TOKEN_ENV
    return secrets.token_urlsafe(32), "the random token"


def _run_view(args: argparse.Namespace, _: object) -> int:
    from cfbci.view.server import Access, check_token, run_view

    zenoh_config = getattr(args, "zenoh_config", None)
    if not args.connect and not args.listen and zenoh_config is None:
        raise ValueError(
            "give at least one --connect endpoint (the service's or a router's), --listen "
            "or --zenoh-config"
        )
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be in 0..65535; got {args.port}")
    token, source = _token(args)
    check_token(token, source)
    access = Access(token, tuple(args.allow_host), tuple(args.allow_origin))

    def print_addresses(base: str) -> None:
        print(f"operator view: {base}/?token={token}", flush=True)
        print(f"subject view: {base}/subject?session=ID&token={token}", flush=True)

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("aiohttp.access").setLevel(logging.WARNING)  # not every file served
    run_view(args.listen, args.connect, zenoh_config, access=access, host=args.host,
             port=args.port, hide_truth=args.hide_truth, on_ready=print_addresses)
    return 0
