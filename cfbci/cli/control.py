"""``cfbci control pause|resume|end|target``: the operator's commands on a running session,
as the browser view's operator page sends them (`wire.operator`)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from rich.console import Console

from cfbci.cli.options import add_endpoints, add_zenoh_config


def _target(text: str) -> Any:
    """A target on the command line: a task index, or ``X,Y`` (a point of the plane)."""
    try:
        values = [float(v) for v in text.split(",")] if "," in text else [int(text)]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"a target is a task index (an integer >= 0) or a point X,Y; got {text!r}"
        ) from None
    if len(values) == 1 and values[0] >= 0:
        return values[0]
    if len(values) == 2:
        return values
    raise argparse.ArgumentTypeError(
        f"a target is a task index (an integer >= 0) or a point X,Y; got {text!r}"
    )


def add_control_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci control`` and its four commands."""
    p = commands.add_parser(
        "control",
        help="the operator's commands on a running session: pause, resume, end, target",
        description="Send an operator's command to the service running SESSION and print "
        "its answer (docs/protocol.md, \"Operator controls\"). pause: the session's "
        "timeouts stop, the sources show no move; resume: it goes on; end: it ends now "
        "(session_ended, the recording closed); target: the target the subject chose "
        "(recorded as the session's truth; the learner never reads it). Exit 1 when the "
        "service refuses the command or does not answer.",
    )
    actions = p.add_subparsers(dest="action", required=True)
    for name, text in (("pause", "pause the session"), ("resume", "resume a paused session"),
                       ("end", "end the session now")):
        actions.add_parser(name, help=text).add_argument("session", help="the session id")
    marking = actions.add_parser("target", help="mark the target the subject chose")
    marking.add_argument("session", help="the session id")
    marking.add_argument(
        "target", type=_target,
        help="a task index (a grid's cell, row * side + col), or X,Y in the continuous world",
    )
    for action in actions.choices.values():
        add_endpoints(action, "Zenoh endpoint to listen on (repeatable)",
                      "Zenoh endpoint to connect to: the service's or a router's (repeatable)")
        add_zenoh_config(action)
        action.add_argument("--timeout", type=float, default=10.0, metavar="S",
                            help="seconds to wait for the service's answer (default 10)")
        action.add_argument("--json", action="store_true",
                            help="print the answering event's fields as JSON")
    p.set_defaults(run=_run_control)


def _run_control(args: argparse.Namespace, console: Console) -> int:
    import zenoh

    from wire.operator import control_fields, send_command
    from wire.zenoh_config import peer_config

    if not args.listen and not args.connect and args.zenoh_config is None:
        raise ValueError("give at least one --listen or --connect endpoint (or --zenoh-config)")
    target = getattr(args, "target", None)
    control_fields(args.action, target)  # a bad command fails before any network
    with zenoh.open(peer_config(args.listen, args.connect, args.zenoh_config)) as session:
        try:
            answer = send_command(session, args.session, args.action, target, args.timeout)
        except TimeoutError as error:
            Console(stderr=True).print(f"[bold red]error:[/] {error}", soft_wrap=True)
            return 1
    if args.json:
        console.print_json(json.dumps(answer))
    else:
        console.print(f"{answer['event']}: {answer['message']}", highlight=False, soft_wrap=True)
    return 0
