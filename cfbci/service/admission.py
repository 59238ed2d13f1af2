"""Admission: whether the service can run a config, and the configs waiting to start.

A config is checked against the service's :class:`cfbci.limits.ServiceLimits` (grid side,
steps, channels, the learner settings, the memory the session would commit:
:func:`session.memory.config_memory_bytes`, one estimate for every world) before anything
is built; a config whose source has not subscribed to its events yet waits as a
:class:`Pending` entry; a puddle-world config also waits while its world's policy tables,
which every puddle session of the process shares, are built on a thread of their own
(:class:`PuddleTables`: 3-4 s and about 300 MiB of temporaries, once per process).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from cfbci.limits import ServiceLimits
from session.config import resolved_config
from session.memory import config_memory_bytes
from session.plane import puddle_world, puddle_world_built
from wire import protocol
from wire.protocol import ProtocolError

log = logging.getLogger("cfbci.service")


class Rejection(ProtocolError):
    """A session the service cannot run, or stops running: a ``session_rejected`` event.

    ``config_t_ns`` is the ``t_ns`` of the config it answers (see docs/protocol.md).
    """

    def __init__(self, problem: str, session: str, seq: int | None, config_t_ns: int) -> None:
        super().__init__(problem, session, seq)
        self.config_t_ns = config_t_ns


#: Makes the :class:`Rejection` of a problem with the config being admitted.
Reject = Callable[[str], Rejection]


def resolved_or_none(config: dict[str, Any]) -> dict[str, Any] | None:
    """:func:`session.config.resolved_config`, or None for a config whose learner settings
    are bad."""
    try:
        return resolved_config(config)
    except (ValueError, TypeError):
        return None


def check_config(config: dict[str, Any], limits: ServiceLimits, reject: Reject) -> None:
    """Raise ``reject(problem)`` for a config the service cannot run within ``limits``."""
    if "grid" in config and not 2 <= config["grid"] <= limits.max_grid:
        raise reject(f"field 'grid' must be in 2..{limits.max_grid}; got {config['grid']}")
    if not 1 <= config["steps"] <= limits.max_steps:
        raise reject(f"field 'steps' must be in 1..{limits.max_steps}; got {config['steps']}")
    if len(config.get("ch_names", ())) > limits.max_epoch_values:
        raise reject(f"more than {limits.max_epoch_values} ch_names")
    try:
        resolved_config(config)
    except (ValueError, TypeError) as exc:
        raise reject(f"bad config: {exc}") from None
    check_memory(config, 0, limits, reject)


def check_memory(
    config: dict[str, Any], n_features: int, limits: ServiceLimits, reject: Reject
) -> None:
    """Raise ``reject(problem)`` for a session that would commit more memory than the
    limit (:func:`session.memory.config_memory_bytes`; ``n_features`` 0 at the config)."""
    needed, what = config_memory_bytes(config, n_features)
    if needed > limits.max_session_mb * 2**20:
        raise reject(
            f"the session would commit about {needed / 2**20:.0f} MiB ({what}), more than "
            f"the limit of {limits.max_session_mb:g} MiB"
        )


@dataclass
class Pending:
    """A started config whose source has not subscribed to the session's events yet."""

    message: protocol.Message
    publisher: zenoh.Publisher
    deadline_ns: int


class PuddleTables:
    """Builds the puddle world's policy tables (:func:`session.plane.puddle_world`) on a
    daemon thread, once per process, so that the service's loop never waits for them."""

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def ready(self) -> bool:
        """Whether the tables are built; starts building them if nobody has.

        Raises
        ------
        RuntimeError
            If the build failed (e.g. out of memory).
        """
        if puddle_world_built():
            return True
        if self._error is not None:
            raise RuntimeError(f"the puddle world's tables could not be built: {self._error!r}")
        if self._thread is None:
            self._thread = threading.Thread(target=self._build, name="puddle-tables",
                                            daemon=True)
            self._thread.start()
            log.info("building the puddle world's policy tables (once per process)")
        return False

    def _build(self) -> None:
        try:
            puddle_world()
        except BaseException as error:  # reported by ready(), on the loop
            self._error = error
