"""The service's limits: what one client may make it hold or do, with their defaults.

``cfbci serve`` takes every limit as a flag (`add_options`, `from_args`); the
table in docs/protocol.md ("Limits") documents them. `world_memory_bytes` is the
upper estimate of the memory a session commits, checked against ``max_session_mb`` when
its config arrives (without the feature term) and again at its first epoch (with it).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from calibration_free.config import LearnerConfig
from calibration_free.world import World
from session.memory import estimate

#: Bytes a message may hold besides its payload (the JSON header), for ``max_message_bytes``.
HEADER_ALLOWANCE = 64 * 2**10


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
        Seconds a new session waits for its source to answer its ``session_pending``
        challenge (proving it listens to the session's events) before it is rejected.
    start_timeout : float
        Seconds a started session may wait for its first epoch before it is ended (apart
        from ``idle_timeout``, which counts between epochs). The default leaves a person at
        an LSL amplifier time to start: the bridge sends its config once its streams are
        found, and the first epoch comes one onset and one epoch after the first move is
        shown; two minutes cover a slow start and still free the slot of a session that
        never sends an epoch.
    user_sessions : int
        Sessions one user (the ``<user>`` of session ids ``<user>/<name>``, the key space
        access control gives a source user) may run at once.
    user_pending : int
        Sessions of one user that may wait for their source at once.
    max_grid : int
        Largest grid side.
    max_steps : int
        Most steps in a session.
    max_features : int
        Longest feature vector (after feature extraction for raw epochs).
    max_epoch_values : int
        Most float32 values in an epoch's payload (n_channels x n_times).
    max_session_mb : float
        Most memory a session may commit by `world_memory_bytes`, MiB.
    rate : int
        Messages accepted per session id per second (config, epoch and truth together).
    user_prior_mb : float
        Most MiB of priors one user's prior store may hold, uploads in progress counted
        by their declared size (`cfbci.service.priors`).
    """

    max_sessions: int = 8
    idle_timeout: float = 300.0
    subscriber_timeout: float = 5.0
    start_timeout: float = 120.0
    user_sessions: int = 4
    user_pending: int = 4
    max_grid: int = 10
    max_steps: int = 20_000
    max_features: int = 512
    max_epoch_values: int = 262_144
    max_session_mb: float = 512.0
    rate: int = 1000
    user_prior_mb: float = 256.0

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


#: One line of help for each limit (the command line's flags).
LIMIT_HELP = {
    "max_sessions": "sessions run at once",
    "idle_timeout": "seconds without an epoch before a session is ended",
    "subscriber_timeout": "seconds a new session waits for its source to answer its challenge",
    "start_timeout": "seconds a started session waits for its first epoch",
    "user_sessions": "sessions one user (<user>/<name> ids) may run at once",
    "user_pending": "sessions of one user that may wait for their source at once",
    "max_grid": "largest grid side",
    "max_steps": "most steps in a session",
    "max_features": "longest feature vector",
    "max_epoch_values": "most float32 values in an epoch (channels x samples)",
    "max_session_mb": "most memory a session may commit (estimate), MiB",
    "rate": "messages accepted per session per second",
    "user_prior_mb": "most MiB of priors one user's prior store may hold",
}


def world_memory_bytes(
    world: World, learner: LearnerConfig, steps: int, n_features: int = 0
) -> int:
    """Upper estimate of the memory a session's learner commits, bytes.

    `session.memory.estimate`'s total (documented term by term there): the
    world's tables and their building, the history and every task's per-fold statistics,
    one step's fit, cross-validation and planning, as functions of the world's sizes, the
    learner settings (frame, decoder, likelihood, planner, folds), ``steps`` and
    ``n_features`` (0 when not known yet: at the config).
    """
    return estimate(world, learner, steps, n_features).total
