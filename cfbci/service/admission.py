"""Admission: whether the service can run a config, and the configs waiting to start.

A config is checked against the service's `cfbci.service.limits.ServiceLimits` (grid side,
steps, channels, the learner settings, the memory the session would commit:
`session.memory.config_memory_bytes`, one estimate for every world) before anything
is built; a config whose source has not subscribed to its events yet waits as a
`Pending` entry; a puddle-world config also waits while its world's policy tables,
which every puddle session of the process shares, are built on a thread of their own
(`PuddleTables`: 3-4 s and about 300 MiB of temporaries, once per process).
"""

from __future__ import annotations

import logging
import secrets
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from cfbci.service.limits import ServiceLimits
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


#: Makes the `Rejection` of a problem with the config being admitted.
Reject = Callable[[str], Rejection]


def resolved_or_none(config: dict[str, Any]) -> dict[str, Any] | None:
    """`session.config.resolved_config`, or None for a config whose learner settings
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
    limit (`session.memory.config_memory_bytes`; ``n_features`` 0 at the config)."""
    needed, what = config_memory_bytes(config, n_features)
    if needed > limits.max_session_mb * 2**20:
        raise reject(
            f"the session would commit about {needed / 2**20:.0f} MiB ({what}), more than "
            f"the limit of {limits.max_session_mb:g} MiB"
        )


@dataclass
class Pending:
    """An admitted config waiting for its source to prove it listens: its ``ready``
    message must repeat the ``challenge`` of the ``session_pending`` event, which only a
    subscriber to the session's events receives (a monitor that listens but never answers
    starts nothing)."""

    message: protocol.Message
    publisher: zenoh.Publisher
    deadline_ns: int
    challenge: str = field(default_factory=lambda: secrets.token_hex(8))
    confirmed: bool = False


def confirm(pending: Pending | None, ready: protocol.Message) -> None:
    """Mark ``pending`` confirmed by the source's ``ready`` message.

    Raises
    ------
    ProtocolError
        When no session of that id waits for its source, or the message does not repeat
        its config's ``t_ns`` and its challenge.
    """
    where = {"session": ready.session, "seq": ready.seq}
    if pending is None:
        raise ProtocolError("ready for no session waiting for its source", **where)
    fields = ready.fields
    if fields["config_t_ns"] != pending.message.t_ns or not secrets.compare_digest(
        fields["challenge"], pending.challenge
    ):
        raise ProtocolError(
            "ready does not answer the session's challenge (its config_t_ns or challenge "
            "differs)", **where,
        )
    pending.confirmed = True


def take_due(
    pending: dict[str, Pending], now_ns: int, world_ready: Callable[[dict[str, Any]], bool]
) -> list[tuple[str, Pending, str | None]]:
    """Take out of ``pending`` the configs due now: ``(id, entry, None)`` for one to start
    (its source answered, its world is ready), ``(id, entry, problem)`` for one to reject:
    ``""`` when its source did not answer by its deadline, the error when its world's
    tables could not be built (``world_ready`` raised RuntimeError). A config whose source
    answered waits for its world's tables with no deadline."""
    due: list[tuple[str, Pending, str | None]] = []
    for sid, entry in list(pending.items()):
        if entry.confirmed:
            try:
                if not world_ready(entry.message.fields):
                    continue
            except RuntimeError as error:
                due.append((sid, pending.pop(sid), str(error)))
                continue
            due.append((sid, pending.pop(sid), None))
        elif now_ns >= entry.deadline_ns:
            due.append((sid, pending.pop(sid), ""))
    return due


def make_room(pending: dict[str, Pending], reject: Reject) -> tuple[str, Pending]:
    """Take the oldest waiting config whose source has not answered its challenge out of
    ``pending`` (full), so that a flood of configs nobody answers cannot keep a real source
    out; raise ``reject(problem)`` if every one has answered.

    Returns
    -------
    (str, Pending)
        The session id and the entry taken out (to be rejected).
    """
    oldest = next((sid for sid, p in pending.items() if not p.confirmed), None)
    if oldest is None:
        raise reject(f"{len(pending)} sessions already wait for their source")
    return oldest, pending.pop(oldest)


def check_quota(
    sid: str,
    running: Iterable[str],
    pending: Iterable[str],
    limits: ServiceLimits,
    reject: Reject,
) -> None:
    """Raise ``reject(problem)`` when the user of ``sid`` (``<user>/<name>``) already runs
    or waits for as many sessions as ``limits`` allow it; one-chunk ids have no user."""
    user = protocol.user_of(sid)
    if user is None:
        return
    mine = [s for s in running if protocol.user_of(s) == user]
    if len(mine) >= limits.user_sessions:
        raise reject(f"user {user!r} runs its maximum of {limits.user_sessions} sessions")
    waiting = [s for s in pending if protocol.user_of(s) == user]
    if len(waiting) >= limits.user_pending:
        raise reject(
            f"user {user!r} has its maximum of {limits.user_pending} sessions waiting for "
            "their source"
        )


class PuddleTables:
    """Builds the puddle world's policy tables (`session.plane.puddle_world`) on a
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
