"""The service's events: published on ``cfbci/<session>/event``, recorded and logged, with
a budget on errors so that a flood of bad messages cannot flood the network."""

from __future__ import annotations

import logging
import time
from collections import Counter

from cfbci.service.recordings import Recordings
from wire.protocol import Message
from wire.transport import Outbox

log = logging.getLogger("cfbci.service")

#: Error events published per session id per second; further ones are only counted.
ERRORS_PER_SECOND = 20
#: Error and rejection events published per second in all.
EVENTS_PER_SECOND = 200
#: foxglove.Log levels of the event kinds.
_LOG_LEVELS = {"error": 4, "session_rejected": 4, "prior_rejected": 4, "info": 2}


class ErrorBudget:
    """At most `ERRORS_PER_SECOND` error and rejection events per session id per
    second, and `EVENTS_PER_SECOND` in all; the others are only counted (and the
    count logged)."""

    def __init__(self) -> None:
        self._window = 0
        self._counts: Counter[str] = Counter()
        self._total = self._suppressed = 0

    def allows(self, session: str) -> bool:
        window = int(time.monotonic())
        if window != self._window:
            if self._suppressed:
                log.warning("%d error events suppressed in the last second", self._suppressed)
            self._window, self._total, self._suppressed = window, 0, 0
            self._counts.clear()
        self._counts[session] += 1
        self._total += 1
        allowed = self._counts[session] <= ERRORS_PER_SECOND and self._total <= EVENTS_PER_SECOND
        self._suppressed += not allowed
        return allowed


class Events:
    """Publishes, records (where the session is recorded) and logs the service's events."""

    def __init__(self, outbox: Outbox, recordings: Recordings) -> None:
        self._outbox = outbox
        self._recordings = recordings

    def publish(
        self,
        session: str,
        event: str,
        text: str,
        config_t_ns: int | None = None,
        challenge: str | None = None,
        extra: dict[str, object] | None = None,
    ) -> None:
        """Publish an event on ``cfbci/<session>/event`` (with the ``challenge`` of a
        ``session_pending``, the ``extra`` fields of an upload's answer); record and log
        it."""
        fields: dict[str, object] = {"event": event, "message": text, "config_t_ns": config_t_ns}
        if challenge is not None:
            fields["challenge"] = challenge
        fields |= extra or {}
        recorder = self._recordings.get(session)

        def record(message: Message) -> None:  # before publishing: what was heard is kept
            if recorder is not None:
                recorder.record("/event", {"seq": message.seq, "t_ns": message.t_ns, **fields},
                                message.t_ns)
                recorder.record_log(_LOG_LEVELS.get(event, 2), f"{event}: {text}",
                                    message.t_ns)

        self._outbox.send("event", session, fields, before=record)
        (log.warning if _LOG_LEVELS.get(event) == 4 else log.info)(
            "%s: %s", event, text
        )
