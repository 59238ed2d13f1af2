"""``cfbci priors list|add|delete``: a service's prior store (`cfbci.service.priors`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.console import Console


def add_priors_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci priors`` and its three subcommands."""
    p = commands.add_parser(
        "priors",
        help="a service's prior store: list, add or delete users' priors",
        description="The prior store of `cfbci serve` (default <record-dir>/priors): each "
        "user's earlier recordings, <prior-dir>/<user>/<sha256>.mcap, which configs name by "
        "their SHA-256 (sessions with a one-chunk id: the user .anonymous). A person's prior "
        "is their data: `delete` removes it from the store (the recordings of the sessions "
        "that used it hold a copy too, docs/how-to/returning-user.md).",
    )
    actions = p.add_subparsers(dest="action", required=True)
    listing = actions.add_parser("list", help="the priors in the store, per user")
    listing.add_argument("--user", help="only this user's priors")
    adding = actions.add_parser(
        "add", help="copy recordings into a user's store (for example the service's own "
        "recordings of that user); prints their SHA-256, which a config names",
    )
    adding.add_argument("--user", required=True, help="the user (session ids USER/NAME)")
    adding.add_argument("files", type=Path, nargs="+", metavar="FILE.mcap")
    deleting = actions.add_parser("delete", help="delete priors from a user's store")
    deleting.add_argument("--user", required=True, help="the user whose priors they are")
    deleting.add_argument("sha256", nargs="+", help="the priors' SHA-256 (see `list`)")
    for action in (listing, adding, deleting):
        action.add_argument(
            "--prior-dir", type=Path, required=True,
            help="the store (cfbci serve's --prior-dir, default <record-dir>/priors)",
        )
    p.set_defaults(run=_run_priors)


def _run_priors(args: argparse.Namespace, console: Console) -> int:
    from cfbci.service.priors import add_prior, delete_prior, stored_priors

    if args.action == "list":
        priors = stored_priors(args.prior_dir, args.user)
        for prior in priors:
            console.print(f"{prior.user}  {prior.sha256}  {prior.size} bytes", highlight=False)
        console.print(f"{len(priors)} prior{'s' * (len(priors) != 1)} in {args.prior_dir}",
                      highlight=False, soft_wrap=True)
    elif args.action == "add":
        for path in args.files:
            prior = add_prior(args.prior_dir, args.user, path)
            console.print(f"{prior.sha256}  {path} -> {prior.path}", highlight=False,
                          soft_wrap=True)
    else:
        for sha256 in args.sha256:
            console.print(f"deleted {delete_prior(args.prior_dir, args.user, sha256)}",
                          highlight=False, soft_wrap=True)
    return 0
