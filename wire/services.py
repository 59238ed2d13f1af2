"""Several services on one Zenoh network: each session served by exactly one of them.

Every service answers a Zenoh *queryable* on ``cfbci/services/<service id>`` with its load
(`ServiceOffer`, JSON). A source that wants one service asks ``cfbci/services/*``,
picks the least loaded offer (`pick_service`) and names it in its config's
``service`` field; the other services ignore that config. The chosen service *claims* the
session with a Zenoh liveliness token ``cfbci/<session>/served-by/<service id>`` for as long
as it runs it, and refuses a session another service already claims (a second source
reusing a running session's id). A claim vanishes with its service, so a killed service's
session can be resumed elsewhere. No coordinator of our own: the queryables and the
liveliness tokens are Zenoh's.
"""

from __future__ import annotations

import json
import os
import re
import socket
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass

import zenoh

from wire.protocol import PREFIX, TYPES

#: Key expression prefix of the services' queryables (``<prefix>/<service id>``).
SERVICES = f"{PREFIX}/services"
#: Seconds a query for offers or claims waits for its replies.
QUERY_TIMEOUT = 2.0


@dataclass(frozen=True)
class ServiceOffer:
    """A service's answer to the offers query.

    Attributes
    ----------
    service : str
        The service's id (a session-id-like token, ``[A-Za-z0-9_-]{1,64}``).
    sessions, max_sessions : int
        Sessions it runs (or waits to start) now, and its limit.
    """

    service: str
    sessions: int
    max_sessions: int


def default_service_id() -> str:
    """``<host>-<pid>`` with other characters than ``[A-Za-z0-9_-]`` replaced by ``-``."""
    return re.sub(r"[^A-Za-z0-9_-]", "-", f"{socket.gethostname()}-{os.getpid()}")[-64:]


def check_service_id(service: str) -> str:
    """``service`` if it is a valid id, else a ValueError naming the rule."""
    description, valid = TYPES["name"]
    if not valid(service):
        raise ValueError(f"a service id must be {description}; got {service!r}")
    return service


def claim_key(session: str, service: str) -> str:
    """The liveliness token of ``service`` serving ``session``."""
    return f"{PREFIX}/{session}/served-by/{service}"


def pick_service(offers: list[ServiceOffer]) -> ServiceOffer:
    """The least loaded offer: lowest share of its limit in use, then fewest sessions, then
    the smallest id (deterministic)."""
    if not offers:
        raise ValueError("no service offered to run the session")
    return min(offers, key=lambda o: (o.sessions / max(o.max_sessions, 1), o.sessions, o.service))


def ask_for_offers(session: zenoh.Session, timeout: float = QUERY_TIMEOUT) -> list[ServiceOffer]:
    """Every service's offer (replies that do not parse are skipped)."""
    offers = []
    for reply in session.get(f"{SERVICES}/*", timeout=timeout):
        if reply.ok is None:
            continue
        try:
            offers.append(ServiceOffer(**json.loads(reply.ok.payload.to_bytes())))
        except (ValueError, TypeError):
            continue
    return offers


def claims_of(session: zenoh.Session, sid: str, timeout: float = QUERY_TIMEOUT) -> list[str]:
    """The ids of the services whose liveliness token claims session ``sid``."""
    prefix = claim_key(sid, "")
    return sorted(
        str(reply.ok.key_expr)[len(prefix):]
        for reply in session.liveliness().get(claim_key(sid, "*"), timeout=timeout)
        if reply.ok is not None
    )


class ServiceRegistration:
    """A service's side: its queryable of offers and its claims.

    The other services' claims are followed with a liveliness subscriber (with history, so
    the claims made before this service started are known too): `claim` checks them
    locally and never waits on the network.

    Parameters
    ----------
    session : zenoh.Session
    service : str
        The service's id.
    load : callable
        Returns ``(sessions, max_sessions)`` now (called on Zenoh's thread: it must only
        read).
    """

    def __init__(
        self, session: zenoh.Session, service: str, load: Callable[[], tuple[int, int]]
    ) -> None:
        self.session, self.service, self._load = session, check_service_id(service), load
        self._claims: dict[str, zenoh.LivelinessToken] = {}
        self._lock = threading.Lock()
        self._others: dict[str, set[str]] = {}  # session id -> the other services claiming it
        self._conflicts: dict[str, str] = {}  # our sessions also claimed by a smaller id
        self._watcher = session.liveliness().declare_subscriber(
            claim_key("**", "*"), self._on_claim, history=True
        )
        self._queryable = session.declare_queryable(f"{SERVICES}/{service}", self._answer)

    def _answer(self, query: zenoh.Query) -> None:
        sessions, max_sessions = self._load()
        offer = ServiceOffer(self.service, sessions, max_sessions)
        query.reply(f"{SERVICES}/{self.service}", json.dumps(asdict(offer)))

    def _on_claim(self, sample: zenoh.Sample) -> None:
        """A claim appears (PUT) or vanishes (DELETE) on the network (Zenoh's thread)."""
        parts = str(sample.key_expr).split("/")  # <prefix>/<session>/served-by/<service>
        if len(parts) not in (4, 5) or parts[-2] != "served-by" or parts[-1] == self.service:
            return
        sid, service = "/".join(parts[1:-2]), parts[-1]
        with self._lock:
            holders = self._others.setdefault(sid, set())
            if sample.kind == zenoh.SampleKind.PUT:
                holders.add(service)
                self._note_conflict(sid)
            else:
                holders.discard(service)
                if not holders:
                    del self._others[sid]

    def _note_conflict(self, sid: str) -> None:
        """With the lock held: if ``sid`` is ours and a service with a smaller id claims it
        too (both checked before either claim reached the other), ours must yield."""
        smaller = [s for s in self._others.get(sid, ()) if s < self.service]
        if sid in self._claims and smaller:
            self._conflicts[sid] = min(smaller)

    def claim(self, sid: str, ask: bool = False) -> str | None:
        """Claim session ``sid``; None if done (or already ours), else the id of the
        service that holds it (the smallest, if several).

        The claims heard so far decide; with ``ask``, the network is also asked
        (`claims_of`, up to `QUERY_TIMEOUT`): for a service that has just
        started (resuming its recordings), whose subscriber may not have heard the
        existing claims yet. Two services may claim one session at the same moment, each
        before it hears of the other's claim: then the smaller id keeps it, and the other
        finds it in `take_conflicts`."""
        if sid in self._claims:
            return None
        with self._lock:
            heard = set(self._others.get(sid, ()))
        if ask:
            heard.update(s for s in claims_of(self.session, sid) if s != self.service)
        others = sorted(heard)
        if others:
            return others[0]
        token = self.session.liveliness().declare_token(claim_key(sid, self.service))
        with self._lock:  # a claim heard meanwhile is seen here, a later one in _on_claim
            self._claims[sid] = token
            self._note_conflict(sid)
        return None

    def take_conflicts(self) -> dict[str, str]:
        """The sessions this service must give up, each with the smaller id of the service
        that keeps it (see `claim`); each reported once."""
        with self._lock:
            conflicts, self._conflicts = self._conflicts, {}
        return conflicts

    def release(self, sid: str) -> None:
        """Withdraw the claim on ``sid``, if any."""
        with self._lock:
            token = self._claims.pop(sid, None)
            self._conflicts.pop(sid, None)
        if token is not None:
            token.undeclare()

    def close(self) -> None:
        """Withdraw every claim, the claims' subscriber and the queryable."""
        for sid in list(self._claims):
            self.release(sid)
        self._watcher.undeclare()
        self._queryable.undeclare()
