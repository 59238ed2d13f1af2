"""Resume after a restart: a recorded, unfinished session rebuilt and continued.

Started on a record directory, the service resumes every session recorded there that
neither ended nor was rejected (`unfinished`): `rerun_recording` re-runs the
session's core over the recorded epochs (`replay.rerun.Rerun`, as ``cfbci replay``
does) and checks that it reproduces the recorded moves; `resumed_session` continues
it from there, its recording rewritten in place and continued (one file, every step once).
The source re-sends its unanswered epoch until the next move arrives; a re-sent epoch
already answered (same step, ``seq`` and ``t_ns``) is answered again, unrecorded.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cfbci.service.recordings import is_recording_name
from cfbci.service.running import EventSink, RunningSession
from replay.recorded_prior import recorded_prior
from replay.recording import Recording, SessionRecorder, decode_array, read_recording
from replay.rerun import (
    STATE_MESSAGE_FIELDS,
    Rerun,
    move_divergence,
    recorded_resets,
    recorded_signals,
)
from session.config import resolved_config
from session.core import State
from wire.transport import Outbox

if TYPE_CHECKING:
    from cfbci.service.loop import PipelineService

log = logging.getLogger("cfbci.service")


@dataclass(frozen=True)
class EndedAtResume:
    """What is kept of a session that ended when the service resumed it, to answer a
    re-send of its last epoch: its id, last step, that epoch's ``(step, seq, t_ns)`` and the
    last state (the learner is not kept)."""

    id: str
    step: int
    last_epoch: tuple[int, int, int] | None
    state: State


def end_again(ended: EndedAtResume, outbox: Outbox, event: EventSink) -> None:
    """The re-sent last epoch of a session that ended at its resumption: publish its last
    state and ``session_ended`` again (unrecorded: its recording is closed)."""
    outbox.send("state", ended.id, ended.state.fields, ended.state.confidence)
    event(ended.id, "session_ended", f"session {ended.id!r} ended after {ended.step} steps "
          "(sent again: it ended when the service resumed it)")
    outbox.forget(ended.id)


def unfinished(recording: Recording) -> bool:
    """Whether a recorded session started and neither ended nor was rejected (for its own
    config): a session to resume."""
    if not recording.config or not recording.messages.get("/move"):
        return False
    t_ns = recording.config.get("t_ns")
    for _, event in recording.messages.get("/event", []):
        if event["event"] == "session_ended" or (
            event["event"] == "session_rejected" and event.get("config_t_ns") == t_ns
        ):
            return False
    return True


def rerun_recording(recording: Recording) -> tuple[dict[str, Any], Rerun]:
    """The resolved config of a recording and its session re-run over the recorded epochs
(with the prior the recording holds).

    A recording of an older version may hold only the settings its source sent: it
    resumes (as it replays) with today's defaults for the others.

    Raises
    ------
    ValueError
        When the re-run does not reproduce the recorded moves.
    """
    config = resolved_config(
        {k: v for k, v in recording.config.items() if k not in ("seq", "t_ns")}
    )
    rerun = Rerun(config, prior=recorded_prior(recording))
    inputs = zip(recorded_signals(recording), recorded_resets(recording), strict=True)
    for signal, reset in list(inputs)[: rerun.steps]:
        rerun.observe(signal, reset=reset)
    recorded_moves = [m for _, m in recording.messages.get("/move", [])]
    divergence = move_divergence(recorded_moves, rerun.moves[: len(recorded_moves)])
    if divergence is not None or len(recorded_moves) < len(rerun.moves) - 1:
        raise ValueError(f"the re-run does not reproduce the recording: {divergence}")
    return config, rerun


def resumed_session(
    recording: Recording,
    config: dict[str, Any],
    rerun: Rerun,
    recorder: SessionRecorder | None,
    outbox: Outbox,
    event: EventSink,
) -> RunningSession:
    """The running session of a re-run recording, its epochs' numbering continued."""
    session = RunningSession(
        recording.session, config, recording.config["t_ns"], rerun.session, recorder, outbox,
        event, time.monotonic_ns(),
    )
    epochs = recording.accepted_epochs()
    if epochs:
        last = epochs[-1]
        session.last_epoch = (last["step"], last["seq"], last["t_ns"])
        session.epochs.expected = last["seq"] + 1  # later epochs continue its numbering
        first = decode_array(epochs[0])
        session.shape = first.shape
        session.signals(first)  # fits the feature extractor on the first epoch
    return session


def recorded_state(rerun: Rerun, index: int) -> State:
    """The re-run's state message of a move's index (or the last one's, -1)."""
    state = rerun.states[index]
    fields = {k: state[k] for k in STATE_MESSAGE_FIELDS}
    return State(fields, np.asarray(state["confidence"], dtype=np.float32))


def answer_again(session: RunningSession, recording: Recording, rerun: Rerun) -> None:
    """Publish the current move and state of a resumed session again, recording those the
    recording lacks (killed between an epoch and its answer)."""
    recorded_moves = len(recording.messages.get("/move", []))
    recorded_states = len(recording.messages.get("/state", []))
    fields = rerun.moves[-1]
    state = recorded_state(rerun, len(rerun.moves) - 1)
    session.answer = (fields, state.fields, state.confidence)
    record_move = recorded_moves < len(rerun.moves)
    sent = session.send("move", fields, record=record_move)
    if record_move:
        session.record_position(fields, sent.t_ns)
    session.send_state(record=recorded_states < len(rerun.moves), state=state)
    session.answer_unheard = True


def resume_recorded(service: PipelineService, record_dir: Path) -> None:
    """Resume every unfinished session recorded in ``record_dir`` into ``service``; a
    recording that cannot be resumed is named in the log and left as is."""
    for path in sorted(record_dir.rglob("*.mcap")):
        if len(service._sessions) >= service.limits.max_sessions:
            log.warning("not resuming %s: the service runs its maximum of sessions", path)
            continue
        try:
            recording = read_recording(path)
            if (
                is_recording_name(path.relative_to(record_dir).as_posix(), recording.session)
                and not path.is_symlink()
                and unfinished(recording)
                and recording.session not in service._sessions
            ):
                _resume(service, recording)
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("cannot resume %s: %s", path, exc)


def _resume(service: PipelineService, recording: Recording) -> None:
    """Rebuild a session by re-running it over its recording, and go on."""
    config, rerun = rerun_recording(recording)
    sid = recording.session
    if config.get("service") is not None and (
        holder := service.registration.claim(sid, ask=True)  # just started: ask the network
    ):
        raise ValueError(f"session {sid!r} is already served by service {holder!r}")
    recorder = service.recordings.resume(recording)
    session = resumed_session(
        recording, config, rerun, recorder, service._outbox, service.events.publish
    )
    service._sessions[sid] = session
    service.intake.open(sid)
    service.events.publish(sid, "info", f"session {sid!r} resumed at step {session.step} "
                           "after a restart, from its recording")
    if rerun.finished:
        state = recorded_state(rerun, -1)
        recorded_states = len(recording.messages.get("/state", []))
        session.send_state(record=recorded_states < len(rerun.states), state=state)
        service._finish(session)
        service._ended_at_resume[sid] = EndedAtResume(sid, session.step, session.last_epoch, state)
        return
    answer_again(session, recording, rerun)
    service.controls.restore(session, recording)  # paused when it stopped: paused again
