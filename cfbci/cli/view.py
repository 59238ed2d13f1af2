"""``cfbci view``: the command of the live view in the browser (the server is
`cfbci.view.server`, imported when the command runs).

``cfbci view --connect EP [--port 8080]`` serves the operator view at ``/`` and the
subject view at ``/subject?session=ID``, to this machine only by default, and to a browser
that has the access token only: it prints both addresses with the token
(``?token=...``). The token is ``--token``, else the environment variable
`cfbci.view.TOKEN_ENV`, else a random one made at start. With ``--stimulus`` the
subject page is the stimulus program of ``cfbci lsl-bridge`` (`cfbci.view.stimulus`).
"""

from __future__ import annotations

import argparse
import logging
import os
import secrets
from pathlib import Path
from typing import TYPE_CHECKING

from cfbci.view import TOKEN_ENV

if TYPE_CHECKING:
    from cfbci.view.stimulus import StimulusSettings


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
    _add_stimulus_options(p)
    p.set_defaults(run=_run_view)
    return p


def _add_stimulus_options(p: argparse.ArgumentParser) -> None:
    group = p.add_argument_group(
        "stimulus", "the subject page as the stimulus program of cfbci lsl-bridge: it shows "
        "the moves of the bridge's LSL move stream and sends each onset, timed by the frame "
        "that showed it, as an LSL marker (docs/tutorials/lab-session.md)",
    )
    group.add_argument("--stimulus", action="store_true",
                       help="make the subject page the stimulus program")
    group.add_argument("--moves", default="cfbci-moves", metavar="NAME",
                       help="the bridge's LSL move stream (default cfbci-moves)")
    group.add_argument("--onsets", default="cfbci-onsets", metavar="NAME",
                       help="name of the LSL onset marker outlet, the bridge's --markers "
                       "(default cfbci-onsets)")
    group.add_argument("--interval", type=float, default=3.0, metavar="SECONDS",
                       help="least time from one onset to the next (default 3)")
    group.add_argument("--grid", type=int, default=5, metavar="N", help="grid side (default 5)")
    group.add_argument("--no-fixation", action="store_true",
                       help="no fixation cross at the centre of the grid")
    group.add_argument("--target", type=int, metavar="CELL",
                       help="show the subject this cell as the target (default: none)")
    group.add_argument("--frame-tolerance", type=float, default=1.5, metavar="PERIODS",
                       help="a frame interval beside an onset longer than this many refresh "
                       "periods makes the onset invalid: the move is shown again (default 1.5)")
    group.add_argument("--photodiode-patch", action="store_true",
                       help="a square in the bottom-left corner, black, white for 3 frames "
                       "from each onset's frame: for a photodiode (lsl-bridge --photodiode)")
    group.add_argument("--onset-log", type=Path, metavar="FILE.jsonl",
                       help="append every onset (valid or not) to this JSON Lines file")


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
             port=args.port, hide_truth=args.hide_truth, on_ready=print_addresses,
             stimulus=_stimulus(args))
    return 0


def _stimulus(args: argparse.Namespace) -> StimulusSettings | None:
    """The stimulus settings of ``--stimulus`` (checked), or None without it."""
    if not args.stimulus:
        return None
    from cfbci.view.stimulus import StimulusSettings

    return StimulusSettings(
        moves=args.moves, onsets=args.onsets, interval=args.interval, grid=args.grid,
        fixation=not args.no_fixation, target=args.target,
        frame_tolerance=args.frame_tolerance, onset_log=args.onset_log,
        photodiode_patch=args.photodiode_patch,
    )
