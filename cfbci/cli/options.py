"""Options several commands share: data, learner settings, endpoints, Zenoh
configuration, and the simulated source's session."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from acquisition.sources import DEFAULT_SYNTHETIC_ACCURACY, SYNTHETIC_KINDS, DataSpec
from acquisition.synthetic import ACCURACY_RANGE
from calibration_free.frames import FRAMES
from calibration_free.task_likelihoods import LIKELIHOODS
from calibration_free.worlds import WORLDS
from cfbci.offline.plane_worlds import live_source_fields
from session.plane import PLANE_FRAMES as LIVE_PLANE_WORLDS


def parse_settings(pairs: Sequence[str]) -> dict[str, Any]:
    """``key=value`` pairs (values parsed as JSON when they can be) into a dictionary."""
    settings: dict[str, Any] = {}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects key=value; got {pair!r}")
        try:
            settings[key] = json.loads(raw)
        except json.JSONDecodeError:
            settings[key] = raw
    return settings


def add_data_options(p: argparse.ArgumentParser) -> None:
    """``--dataset`` and ``--synthetic-accuracy``: where the simulated user's signals come from."""
    p.add_argument(
        "--dataset", type=Path,
        help="dataset file: .mat, .npz, or a session recording .mcap (its epochs, labelled by "
        "its truth; raw epochs if it holds them); default synthetic",
    )
    p.add_argument(
        "--synthetic-accuracy", type=float, default=DEFAULT_SYNTHETIC_ACCURACY,
        help=f"synthetic difficulty as nominal balanced LDA accuracy, in {list(ACCURACY_RANGE)} "
        "(ErrP); for Gaussian signals the Bayes-optimal balanced accuracy",
    )
    p.add_argument(
        "--synthetic", choices=SYNTHETIC_KINDS, default="errp",
        help="synthetic generator: ErrP EEG epochs (feedback), or Gaussian signals with as many "
        "classes as the frame needs (default errp)",
    )
    p.add_argument("--dims", type=int, default=2, help="dimensions of a Gaussian signal")
    p.add_argument(
        "--mixing-decay", type=float, default=0.0,
        help="Gaussian signals seen through a fixed linear mixing whose spectrum decays as "
        "j^-GAMMA (correlated features, as EEG's; the nominal accuracy holds; default 0: none)",
    )


def add_likelihood_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--likelihood", choices=LIKELIHOODS,
        help="how tasks are scored (the learner setting 'likelihood'; default matching)",
    )


def learner_settings_of(args: argparse.Namespace, **defaults: Any) -> dict[str, Any]:
    """``defaults``, then the ``--set`` settings, then ``--likelihood`` if given."""
    given = parse_settings(args.set)
    if "frame" in given:
        raise ValueError("--set frame=...: the frame is set with --frame")
    settings = {**defaults, **given}
    if args.likelihood is not None:
        settings["likelihood"] = args.likelihood
    return settings


def data_spec(args: argparse.Namespace) -> DataSpec:
    """The `DataSpec` of the options of `add_data_options`."""
    return DataSpec(
        args.dataset, args.synthetic_accuracy, args.synthetic, args.dims, args.mixing_decay
    )


def add_endpoints(p: argparse.ArgumentParser, listen_help: str, connect_help: str) -> None:
    p.add_argument("--listen", action="append", default=[], metavar="EP", help=listen_help)
    p.add_argument("--connect", action="append", default=[], metavar="EP", help=connect_help)


def add_zenoh_config(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    p.add_argument(
        "--zenoh-config", type=Path, metavar="FILE",
        help="Zenoh JSON5 configuration merged over the defaults (peer mode, multicast "
        "scouting off); --listen/--connect replace its endpoints (docs/deployment.md)",
    )


def add_source_options(p: argparse.ArgumentParser) -> None:
    add_data_options(p)
    p.add_argument("--seed", type=int, default=0, help="session seed (default 0)")
    p.add_argument("--steps", type=int, default=500, help="actions in the session (default 500)")
    p.add_argument("--grid", type=int, help="grid side, grid world only (default 5)")
    p.add_argument("--world", choices=(*WORLDS, *LIVE_PLANE_WORLDS), default="grid",
                   help="the world (default grid)")
    p.add_argument("--frame", choices=(*FRAMES, *LIVE_PLANE_WORLDS.values()), default="feedback")
    add_live_plane_options(p)
    add_likelihood_option(p)
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="a learner setting sent in the config (see calibration_free.config.LearnerConfig)",
    )
    p.add_argument(
        "--interval", type=float, default=0.0,
        help="seconds between a move and the user's epoch (default 0)",
    )
    p.add_argument(
        "--user-error-rate", type=float, default=0.0,
        help="probability that the simulated user's label is wrong (default 0)",
    )


def grid_of(args: argparse.Namespace) -> int:
    """The grid side: ``--grid``, which only the grid world takes (default 5)."""
    if args.grid is not None and args.world != "grid":
        raise ValueError(f"--grid applies to --world grid only; this world is {args.world!r}")
    return 5 if args.grid is None else args.grid


def source_settings(args: argparse.Namespace, session: str) -> Any:
    from acquisition.simulated_source import SourceSettings

    if args.steps < 1 or args.interval < 0:
        raise ValueError("--steps must be at least 1 and --interval at least 0")
    learner = learner_settings_of(args)
    plane = live_source_fields(args.world, args.frame, learner, args.class_order)  # fail early
    return SourceSettings(
        session=session, data=data_spec(args), seed=args.seed,
        steps=args.steps, grid=grid_of(args), frame=args.frame, learner=learner,
        interval=args.interval, user_error_rate=args.user_error_rate, world=args.world,
        pick_service=getattr(args, "pick_service", False), **plane,
    )


def add_live_plane_options(parser: argparse.ArgumentParser) -> None:
    """The continuous world's options of ``cfbci source`` and ``cfbci session`` (the puddle
    world has none: its learner settings go with ``--set``, e.g. ``--set
    exploration=random``)."""
    parser.add_argument(
        "--class-order", default=None, metavar="K,K,K,K",
        help="continuous world: dataset class of each direction up,down,right,left "
        "(default 0,1,2,3; the learner never knows it)",
    )


def add_prior_option(parser: argparse.ArgumentParser) -> None:
    """``--prior FILE.mcap ...`` of the sources (``source``, ``session``, ``lsl-bridge``)."""
    parser.add_argument(
        "--prior", type=Path, nargs="+", default=[], metavar="FILE.mcap",
        help="earlier recordings of the user: the learner starts from their signals and the "
        "labels adopted at their targets (grid, line and pick-and-place worlds); uploaded "
        "into the service's prior store of the session's user where it lacks them",
    )


def checked_prior(args: argparse.Namespace) -> tuple[Path, ...]:
    """The ``--prior`` files, each one a readable prior (else a ``ValueError`` or
    ``FileNotFoundError`` naming the file and the problem)."""
    if args.prior:
        from replay.prior import read_prior

        read_prior(args.prior)
    return tuple(args.prior)
