"""The service's limits: what one client may make it hold or do, with their defaults.

``cfbci serve`` takes every limit as a flag (:func:`add_options`, :func:`from_args`); the
table in docs/protocol.md ("Limits") documents them. :func:`world_memory_bytes` is the
upper estimate of the memory a session commits, checked against ``max_session_mb`` when
its config arrives (without the feature term) and again at its first epoch (with it).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, fields

from calibration_free.task_decoders import DEFAULT_FOLDS
from calibration_free.world import GridWorld, World

#: Bytes a message may hold besides its payload (the JSON header), for ``max_message_bytes``.
HEADER_ALLOWANCE = 64 * 2**10
_FLOAT = 8  # bytes of a float64


@dataclass(frozen=True)
class ServiceLimits:
    """Limits of one service; the defaults are those of ``cfbci serve``.

    Attributes
    ----------
    max_sessions : int
        Sessions run at once (started or waiting for their source to subscribe).
    idle_timeout : float
        Seconds without an accepted epoch after which a session is ended (its recording
        closed); counted from its start, its last epoch, or its resumption.
    subscriber_timeout : float
        Seconds a new session waits for a subscriber to its events before it is rejected.
    max_grid : int
        Largest grid side.
    max_steps : int
        Most steps in a session.
    max_features : int
        Longest feature vector (after feature extraction for raw epochs).
    max_epoch_values : int
        Most float32 values in an epoch's payload (n_channels x n_times).
    max_session_mb : float
        Most memory a session may commit by :func:`world_memory_bytes`, MiB.
    rate : int
        Messages accepted per session id per second (config, epoch and truth together).
    """

    max_sessions: int = 8
    idle_timeout: float = 300.0
    subscriber_timeout: float = 5.0
    max_grid: int = 10
    max_steps: int = 20_000
    max_features: int = 512
    max_epoch_values: int = 262_144
    max_session_mb: float = 512.0
    rate: int = 1000

    @property
    def max_message_bytes(self) -> int:
        """Longest message taken in: a maximum epoch's payload plus the header allowance."""
        return 4 * self.max_epoch_values + HEADER_ALLOWANCE

    def __post_init__(self) -> None:
        for spec in fields(self):
            value = getattr(self, spec.name)
            if not value > 0:
                raise ValueError(f"limit {spec.name} must be positive; got {value!r}")
        if self.max_grid < 2:
            raise ValueError(f"limit max_grid must be at least 2; got {self.max_grid}")


_HELP = {
    "max_sessions": "sessions run at once",
    "idle_timeout": "seconds without an epoch before a session is ended",
    "subscriber_timeout": "seconds a new session waits for its source to subscribe",
    "max_grid": "largest grid side",
    "max_steps": "most steps in a session",
    "max_features": "longest feature vector",
    "max_epoch_values": "most float32 values in an epoch (channels x samples)",
    "max_session_mb": "most memory a session may commit (estimate), MiB",
    "rate": "messages accepted per session per second",
}


def add_options(parser: argparse.ArgumentParser) -> None:
    """Add one ``--max-sessions``-style flag per limit, defaulting to :class:`ServiceLimits`."""
    defaults = ServiceLimits()
    for spec in fields(ServiceLimits):
        default = getattr(defaults, spec.name)
        parser.add_argument(
            f"--{spec.name.replace('_', '-')}", type=type(default), default=default,
            help=f"{_HELP[spec.name]} (default {default:g})",
        )


def from_args(args: argparse.Namespace) -> ServiceLimits:
    """The limits given by :func:`add_options`' flags."""
    return ServiceLimits(**{spec.name: getattr(args, spec.name) for spec in fields(ServiceLimits)})


def session_memory_bytes(grid: int, n_classes: int, steps: int, n_features: int = 0) -> int:
    """:func:`world_memory_bytes` of a ``grid x grid`` grid world."""
    return world_memory_bytes(GridWorld(grid), n_classes, steps, n_features)


def world_memory_bytes(world: World, n_classes: int, steps: int, n_features: int = 0) -> int:
    """Upper estimate of the memory a session's learner commits, bytes.

    With T tasks, S states and A actions of the world (a grid: T = S = side², A = 5), K
    classes, F = 10 folds and d features: ``8 * ((4 + K) T S A K + 2 T (F + 1) K d^2 +
    steps (T K + d))`` — the frame's and the planner's tables, the per-fold scatter
    matrices and the decoders fitted from them, and the history: an upper bound. Measured
    (peak resident growth, 30 epochs, d = 57) with the learner of its writing: grid 5,
    29 MiB (estimate 28); grid 16, 313 MiB (estimate 309); the compact statistics since:
    grid 16, 33 MiB; pick-and-place (T = S = 624, A = 4), 200 steps: feedback 45 MiB
    (estimate 825), guidance 78 MiB (estimate 1745), default LDA decoder.

    Parameters
    ----------
    world : World
        The session's world (only its sizes are read).
    n_classes : int
        Classes of the frame: 2 (feedback) or the world's guidance actions (guidance).
    steps : int
        Steps of the session.
    n_features : int
        Length of the learner's feature vectors; 0 when not known yet.
    """
    tasks, states = world.n_tasks, world.n_states
    tables = (4 + n_classes) * tasks * states * world.n_actions * n_classes
    scatter = 2 * tasks * (DEFAULT_FOLDS + 1) * n_classes * n_features**2
    history = steps * (tasks * n_classes + n_features)
    return _FLOAT * (tables + scatter + history)
