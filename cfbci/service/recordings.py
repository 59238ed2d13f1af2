"""The service's recordings: one MCAP file per session, and the only reader of ``truth``.

`Recordings` holds the session recorders and no learner: it owns the service's only
``cfbci/**/truth`` subscription's messages and writes them to the recordings, so that a
label never reaches a learner. `record_beliefs` records a state's beliefs in the
form each world's recording holds them.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any

from replay.recording import Recording, SessionRecorder
from session.core import Session, State
from session.plane import TASK_CELLS, goal_probabilities
from wire import protocol
from wire.protocol import ProtocolError
from wire.transport import Received

log = logging.getLogger("cfbci.service")

#: Seconds an ended session's recording waits for the truth of its last step.
TRUTH_WAIT = 10.0


def recording_path(directory: Path, session: str) -> Path:
    """Where a new recording of ``session`` goes in ``directory``: ``<session>.mcap``, or
    ``<session>.<n>.mcap`` with the smallest ``n >= 2`` that names no file, directory or
    link (a dangling link included), so that no recording is ever written over another or
    through a link. A session ``<user>/<name>`` is recorded in the user's folder."""
    path, n = directory / f"{session}.mcap", 2
    while os.path.lexists(path):
        path, n = directory / f"{session}.{n}.mcap", n + 1
    return path


def is_recording_name(name: str, session: str) -> bool:
    """Whether a file name (relative to the record directory, ``/``-separated) is one
    `recording_path` gives ``session``'s recordings."""
    stem = name.removesuffix(".mcap")
    if stem == session:
        return name.endswith(".mcap")
    number = stem.removeprefix(f"{session}.")
    return name.endswith(".mcap") and number != stem and number.isdigit() and int(number) >= 2


def record_beliefs(
    recorder: SessionRecorder, config: dict[str, Any], core: Session, state: State, t_ns: int
) -> None:
    """Record a state's beliefs for viewers: the goal cells' probabilities on ``/belief``
    in the puddle world, the particles on ``/particles`` in the continuous world, the
    belief over the world's states on ``/belief`` in the discrete worlds."""
    world = config.get("world")
    if world == "puddle":
        recorder.record_grid(
            goal_probabilities(state.confidence), TASK_CELLS, 1.0 / TASK_CELLS, "plane", t_ns
        )
    elif world == "continuous":
        recorder.record_particles(state.fields["points"], state.confidence, t_ns)
    else:
        recorder.record_belief(state.confidence, core.world, t_ns)  # type: ignore[attr-defined]


class Recordings:
    """The session recorders, and the only reader of ``truth``.

    One MCAP file per session, ``<directory>/<session>.mcap``; never over an existing
    file: a session whose id already names a file there (an earlier session's recording,
    or anything else, a link included) is recorded to ``<session>.<n>.mcap``, the first
    ``n`` from 2 that names no file (`recording_path`). A recording is closed when
    its session has ended and the truth of its last step has been recorded (at once if no
    truth arrived at all; after `TRUTH_WAIT` seconds at the latest), or by
    `close`.

    Parameters
    ----------
    directory : Path or None
        Where recordings go; None records nothing.
    """

    def __init__(self, directory: Path | None) -> None:
        self.directory = directory
        self._recorders: dict[str, SessionRecorder] = {}
        self._truths: dict[str, set[int]] = {}  # session -> steps whose truth is recorded
        self._awaiting: dict[str, int] = {}  # ended session -> step whose truth closes it
        self._deadlines: dict[str, int] = {}  # ended session -> monotonic ns to close anyway

    def open(self, session: str, config: dict[str, Any]) -> SessionRecorder | None:
        """Start the recording of a session (None when not recording)."""
        if self.directory is None:
            return None
        self.directory.mkdir(parents=True, exist_ok=True)
        if session in self._recorders:  # an ended session's id reused before its last truth
            self._close(session)
        path = recording_path(self.directory, session)
        path.parent.mkdir(exist_ok=True)  # a user's folder, for ``<user>/<name>`` ids
        recorder = SessionRecorder(path, session, config)
        self._recorders[session] = recorder
        return recorder

    def resume(self, recording: Recording) -> SessionRecorder | None:
        """Continue an unfinished recording in place (None when not recording).

        Its messages are written again, in log-time order, to a new file that then replaces
        it (so a crash meanwhile leaves the original intact); new messages follow them.
        """
        if self.directory is None:
            return None
        path = Path(recording.path)  # its own file, whichever name it was given
        partial = path.with_suffix(".mcap.resuming")
        recorder = SessionRecorder(partial, recording.session, recording.config)
        # An epoch recorded without its features was not accepted (killed in between):
        # left out, since its re-sent copy (same seq) will be.
        accepted = {m["seq"] for _, m in recording.messages.get("/features", [])}
        messages = sorted(
            (log_time, order, index, topic, message)
            for order, (topic, entries) in enumerate(recording.messages.items())
            if topic != "/config"
            for index, (log_time, message) in enumerate(entries)
            if topic != "/epoch" or message["seq"] in accepted
        )
        for log_time, _, _, topic, message in messages:
            recorder.record(topic, message, log_time)
        os.replace(partial, path)
        recorder.path = path
        self._truths[recording.session] = {
            m["step"] for _, m in recording.messages.get("/truth", [])
        }
        self._recorders[recording.session] = recorder
        return recorder

    def get(self, session: str) -> SessionRecorder | None:
        """The open recorder of a session, if any."""
        return self._recorders.get(session)

    def truth(self, received: Received, latest_step: int) -> None:
        """Record a ``truth`` message on its session's ``/truth`` (else log why not).

        Only the truth of a step not recorded yet and at most ``latest_step`` (the
        session's last move; 0 when not running) is recorded: once per step.
        """
        try:
            message = protocol.decode(received.data, key_expr=received.key_expr)
        except ProtocolError as error:
            log.debug("truth not recorded: %s", error)
            return
        recorder = self._recorders.get(message.session)
        if recorder is None:
            log.debug("truth of session %r not recorded: no open recording", message.session)
            return
        step = message.fields["step"]
        recorded = self._truths.setdefault(message.session, set())
        if step in recorded or step > max(latest_step, self._awaiting.get(message.session, 0)):
            log.debug("truth of step %d of session %r not recorded", step, message.session)
            return  # re-sent with its epoch, or of no step yet
        record = {"seq": message.seq, "t_ns": message.t_ns, **message.fields}
        recorder.record("/truth", record, received.t_ns)
        recorded.add(step)
        if self._awaiting.get(message.session) == message.fields["step"]:
            self._close(message.session)

    def end(self, session: str, last_step: int) -> None:
        """The session ended at ``last_step``: close now, or once that step's truth is in."""
        if session not in self._recorders:
            return
        recorded = self._truths.get(session)
        if not recorded or last_step in recorded:
            self._close(session)
        else:
            self._awaiting[session] = last_step
            self._deadlines[session] = time.monotonic_ns() + int(TRUTH_WAIT * 1e9)

    def close_overdue(self) -> None:
        """Close the recordings of ended sessions whose last truth is overdue."""
        now = time.monotonic_ns()
        for session in [s for s, deadline in self._deadlines.items() if now >= deadline]:
            log.warning("session %r: the truth of its last step never came", session)
            self._close(session)

    def _close(self, session: str) -> None:
        self._recorders.pop(session).close()
        self._truths.pop(session, None)
        self._awaiting.pop(session, None)
        self._deadlines.pop(session, None)

    def close(self) -> None:
        """Close every recording."""
        for session in list(self._recorders):
            self._close(session)
