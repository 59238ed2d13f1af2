"""Shared by the tests of the live service and of recordings: a spawned service process,
and rewriting a recording after editing its messages.

Spawned, not forked: a forked child's Zenoh session silently drops messages.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import zenoh

from cfbci.service import serve
from cfbci.service.process import SPAWN as SPAWN  # the tests spawn their processes so too
from cfbci.service.process import spawned
from replay.recording import Recording, SessionRecorder
from wire import protocol
from wire.transport import Outbox

TIMEOUT = 60.0  # failure guard, seconds


@contextmanager
def service_process(
    endpoint: str, record_dir: Path, connect: tuple[str, ...] = ()
) -> Iterator[None]:
    """The service in a spawned process, recording to ``record_dir``; stopped with SIGTERM,
    which must exit cleanly (recordings closed, so complete once this exits)."""
    with spawned(serve, [endpoint], list(connect), record_dir):
        yield


def rewrite(recording: Recording, path: Path) -> None:
    """A recording's messages (as they are now in memory) into a new file."""
    with SessionRecorder(path, recording.session, recording.config) as recorder:
        for topic, messages in recording.messages.items():
            if topic not in ("/config", "/belief", "/log"):
                for log_time_ns, message in messages:
                    recorder.record(topic, message, log_time_ns)


@contextmanager
def answering_challenges(session: zenoh.Session) -> Iterator[None]:
    """Answer every ``session_pending`` challenge heard on ``session`` with a ``ready``
    message, as a source listening to its session's events does: for tests that send
    configs by hand (the client loop, `wire.client`, answers for the real sources)."""
    outbox = Outbox(session)

    def on_event(sample: zenoh.Sample) -> None:
        message = protocol.decode(sample.payload.to_bytes(), key_expr=str(sample.key_expr))
        if message.fields["event"] == "session_pending":
            ready = {"config_t_ns": message.fields["config_t_ns"],
                     "challenge": message.fields["challenge"]}
            outbox.send("ready", message.session, ready)

    subscriber = session.declare_subscriber(f"{protocol.PREFIX}/**/event", on_event)
    try:
        yield
    finally:
        subscriber.undeclare()
        outbox.close()
