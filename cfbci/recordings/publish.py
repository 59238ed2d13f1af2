"""``cfbci replay FILE.mcap --publish``: re-publish a recorded session to a running service.

For regression and latency tests of a running ``cfbci serve``. The recorded session is
sent again over Zenoh, open-loop, as a source would (docs/protocol.md), under a new
session id: its ``config`` (the recorded fields; ``steps`` cut to the epochs the recording
holds, ``dataset`` noting the recording it comes from), then every accepted recorded epoch
in order (a puddle epoch with its ``reset`` flag), each followed by the recorded
``truth`` of its step (so that a recording service records it), all with fresh sequence
numbers and timestamps (`wire.transport.Outbox`, reliable publication with
congestion control BLOCK). The service's answers are read by our
own threads (`wire.transport.Pump`), never in Zenoh callbacks. The loop (re-sending,
sequence numbers, the events that start and end the session, the timeout) is every
client's, `wire.client.Client`.

Pacing
    The service checks that an epoch carries the step of its last move and answers each
    epoch with the next move, so epoch ``k`` (step ``k``) is sent once the service's move
    of step ``k`` has arrived *and* the paced delay has elapsed: epoch ``k`` goes out no
    earlier than ``gap_k / speed`` after epoch ``k - 1`` went out, ``gap_k`` being the
    difference of the recorded epochs' ``t_ns`` (the recording source's publication
    clock). Epoch 1 goes out as soon as move 1 arrives. ``speed`` 1 replays the recorded
    pace (when the service is at least as fast as it was), 2 twice as fast; ``speed`` 0 or
    ``inf`` sends every epoch as soon as its move arrives: as fast as the service answers.

Regression check
    Open-loop, the epochs are the recorded ones whatever the service answers. With the same
    configuration and seed a deterministic service makes the recorded decisions again: its
    moves (step, cells, action, target reached) equal the recorded moves, and its states
    (beliefs, confidences bit for bit) the recorded states; `PublishResult` tells
    whether they do and where they first differ.
"""

from __future__ import annotations

import logging
import math
import os
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

import numpy as np
import zenoh
from rich.console import Console

from replay.recorded_prior import prior_files
from replay.recording import Recording, decode_array, read_recording
from replay.rerun import (
    STATE_FIELDS,
    STATE_MESSAGE_FIELDS,
    Divergence,
    move_divergence,
    state_divergence,
)
from session.plane import is_plane
from wire import protocol
from wire.client import DEFAULT_TIMEOUT, RESEND_INTERVAL, Client
from wire.prior_upload import upload_contents
from wire.zenoh_config import peer_config

log = logging.getLogger("cfbci.recordings.publish")


def default_session_id(recording: Recording) -> str:
    """``<recorded session>-replay`` (a valid id; not the recorded one, so that a recording
    service does not overwrite the original recording); a session ``<user>/<name>`` stays
    in its user's space, ``<user>/<name>-replay``, which access control lets that user
    publish."""
    session = recording.session
    user = protocol.user_of(session) if protocol.TYPES["session"][1](session) else None
    if user is not None:
        return f"{user}/{session.partition('/')[2][:57]}-replay"
    base = re.sub(r"[^A-Za-z0-9_-]", "-", session)[:57] or "session"
    return f"{base}-replay"


def check_speed(speed: float) -> float:
    """``speed`` if valid: > 0 paces, 0 or ``inf`` is as fast as possible (see the module
    docstring)."""
    if math.isnan(speed) or speed < 0:
        raise ValueError(f"--speed must be >= 0 (0 or inf: as fast as possible); got {speed}")
    return speed


@dataclass(frozen=True)
class PublishResult:
    """What was published and what the service answered.

    Attributes
    ----------
    session : str
        The session id it was published under.
    epochs, truths : int
        Epochs and truth messages published.
    moves, states : list of dict
        The service's move and state fields (states with ``confidence``), in order.
    target_events : list of str
        Messages of the service's ``target_reached`` events.
    recorded_moves, recorded_states : int
        Recorded moves and states compared with them.
    moves_divergence, states_divergence : Divergence or None
        First difference between the recorded and the service's moves (states, target
        events included after them); None when they are equal.
    latency_ns : list of int
        Per epoch but the last: from the epoch published to the service's next move taken
        off our subscriber, ns.
    elapsed_s, recorded_s : float
        From the first epoch published to the session's end; recorded: from the first to
        the last recorded epoch.
    speed : float
    """

    session: str
    epochs: int
    truths: int
    moves: list[dict[str, Any]]
    states: list[dict[str, Any]]
    target_events: list[str]
    recorded_moves: int
    recorded_states: int
    moves_divergence: Divergence | None
    states_divergence: Divergence | None
    latency_ns: list[int]
    elapsed_s: float
    recorded_s: float
    speed: float

    @property
    def paced(self) -> bool:
        """Published at a pace (speed > 0 and finite), not as fast as possible."""
        return self.speed > 0 and math.isfinite(self.speed)

    @property
    def moves_equal(self) -> bool:
        """The regression check: the service's moves equal the recorded moves."""
        return self.moves_divergence is None

    def to_json(self) -> dict[str, Any]:
        latency = np.asarray(self.latency_ns, dtype=np.float64) / 1e6
        return {
            "session": self.session,
            "speed": self.speed if self.paced else None,  # null: as fast as possible
            "epochs": self.epochs,
            "truths": self.truths,
            "moves_received": len(self.moves),
            "states_received": len(self.states),
            "target_events": self.target_events,
            "moves_equal": self.moves_equal,
            "moves_divergence": _divergence_json(self.moves_divergence),
            "states_equal": self.states_divergence is None,
            "states_divergence": _divergence_json(self.states_divergence),
            "latency_ms": {
                "median": float(np.median(latency)),
                "p99": float(np.percentile(latency, 99)),
                "max": float(latency.max()),
            } if latency.size else None,
            "elapsed_s": self.elapsed_s,
            "recorded_s": self.recorded_s,
        }


def _divergence_json(divergence: Divergence | None) -> dict[str, Any] | None:
    return None if divergence is None else vars(divergence)


@dataclass
class _Published:
    """The recorded session as it will be published."""

    config: dict[str, Any]
    epochs: list[tuple[dict[str, Any], np.ndarray]]  # (epoch fields, payload)
    truths: dict[int, dict[str, Any]]  # step -> truth fields
    gaps_ns: list[int]  # recorded t_ns difference before each epoch (0 for the first)
    moves: list[dict[str, Any]]
    states: list[dict[str, Any]]
    target_events: list[str]


def _prepare(recording: Recording, where: str) -> _Published:
    """The config, epochs, truths and pacing to publish; the moves and states to expect."""
    config = recording.config
    if not config:
        raise ValueError(f"{where}: the recording holds no session configuration")
    epochs = recording.accepted_epochs()
    if not epochs:
        raise ValueError(f"{where}: the recording holds no epoch to publish")
    for k, epoch in enumerate(epochs, 1):
        if epoch.get("step") != k:
            raise ValueError(
                f"{where}: epoch #{k} is of step {epoch.get('step')}: the recorded epochs' "
                "steps are not 1, 2, ... in order"
            )
    # A version 2 recording (grid worlds only) names no world.
    config = {"world": "grid", **config}
    names = list(protocol.SPECS["config"].fields_for(config))
    missing = [name for name in names if name not in config]
    if missing:
        raise ValueError(f"{where}: the recorded configuration lacks {missing}")
    fields = {name: config[name] for name in names}
    fields["steps"] = min(config["steps"], len(epochs))
    fields["dataset"] = {
        **config["dataset"], "replayed_from": where, "recorded_session": recording.session,
    }
    epochs = epochs[: fields["steps"]]
    epoch_fields: dict[str, Any] = {"signal": config["signal"]}
    if config["signal"] == "epochs":
        epoch_fields["ch_names"] = config["ch_names"]
    times = [epoch["t_ns"] for epoch in epochs]
    truth_fields = ("step", "target", "label")
    return _Published(
        config=fields,
        epochs=[
            ({"step": e["step"], **epoch_fields, **({"reset": True} if e.get("reset") else {})},
             decode_array(e))
            for e in epochs
        ],
        truths={
            m["step"]: {name: m[name] for name in truth_fields}
            for _, m in recording.messages.get("/truth", [])
        },
        gaps_ns=[0, *(max(0, b - a) for a, b in pairwise(times))],
        moves=[m for _, m in recording.messages.get("/move", [])][: len(epochs)],
        states=[m for _, m in recording.messages.get("/state", [])][: len(epochs) + 1],
        target_events=[
            m["message"] for _, m in recording.messages.get("/event", [])
            if m.get("event") == "target_reached"
        ],
    )


class _Publisher:
    """The re-publication's side of the session (a `wire.client.Answerer`): epoch
    ``k`` answers move ``k`` once its paced time has come (see the module docstring)."""

    def __init__(self, client: Client, published: _Published, speed: float) -> None:
        self.client, self.published, self.speed = client, published, speed
        self.pace = speed > 0 and math.isfinite(speed)
        self.moves = 0  # moves handed to us
        self.sent = 0  # epochs sent
        self.truths = 0  # truths sent

    def on_move(self, move: protocol.Message) -> None:
        """Move ``k`` came: epoch ``k`` is due at its paced time (`poll`)."""
        self.moves += 1

    def poll(self) -> float:
        """Send the epoch that answers the latest move once its paced time has come;
        return the seconds until then."""
        if self.sent == self.moves:
            return math.inf
        fields, payload = self.published.epochs[self.sent]
        step = fields["step"]
        if self.pace and step > 1:
            gap_ns = self.published.gaps_ns[self.sent]
            due_ns = self.client.epoch_ns[step - 1] + int(gap_ns / self.speed)
            if (wait_ns := due_ns - time.monotonic_ns()) > 0:
                return wait_ns / 1e9
        truth = self.published.truths.get(step)
        self.client.send_epoch(fields, payload, truth)
        self.sent += 1
        self.truths += truth is not None
        return math.inf


def publish_recording(
    session: zenoh.Session,
    recording: Recording | str | os.PathLike[str],
    *,
    session_id: str | None = None,
    speed: float = 1.0,
    timeout: float = DEFAULT_TIMEOUT,
    resend_interval: float = RESEND_INTERVAL,
) -> PublishResult:
    """Publish a recorded session to the service reachable through ``session`` (the loop:
    `wire.client.Client`; the recorded epochs and their pace: this module).

    Parameters
    ----------
    session : zenoh.Session
    recording : Recording or path
    session_id : str, optional
        Default `default_session_id`.
    speed : float
        Pace factor (see the module docstring); 0 or ``inf``: as fast as possible.
    timeout : float
        Seconds the service may keep us waiting before giving up (a failure guard).
    resend_interval : float
        Seconds between two sendings of the unanswered config or epoch.

    Raises
    ------
    ValueError
        On an unusable recording or a bad session id or speed.
    TimeoutError
        If no service subscribes to the config, or the service keeps us waiting.
    RuntimeError
        If the service rejects the session (a ``session_rejected`` event answering its
        config) or the files of its prior, which are uploaded first (the recording's
        ``/prior``); ``error`` events about single messages are only logged.
    """
    if not isinstance(recording, Recording):
        recording = read_recording(recording)
    published = _prepare(recording, recording.path)
    sid = session_id or default_session_id(recording)
    check_speed(speed)
    files = prior_files(recording)  # uploaded again, for the service's store of sid's user
    if files:
        names = [f"{recording.path} /prior {sha256[:12]}" for sha256 in files]
        upload_contents(session, sid, list(zip(names, files.values(), strict=True)), timeout,
                        resend_interval)
    with Client(session, sid, log, timeout, resend_interval) as client:  # checks the id
        publisher = _Publisher(client, published, speed)
        client.run(published.config, publisher)
        elapsed = (time.monotonic_ns() - client.epoch_ns[1]) / 1e9
    n = len(published.epochs)
    moves = [client.moves[step].fields for step in range(1, n + 1)]
    states = [
        {**client.states[k].fields, "confidence": [float(x) for x in client.states[k].payload]}
        for k in range(n + 1)
    ]
    recorded_epochs = recording.accepted_epochs()[:n]
    return PublishResult(
        session=sid,
        epochs=n,
        truths=publisher.truths,
        moves=moves,
        states=states,
        target_events=client.target_events,
        recorded_moves=len(published.moves),
        recorded_states=len(published.states),
        moves_divergence=move_divergence(published.moves, moves),
        states_divergence=state_divergence(
            published.states, states, published.target_events, client.target_events, moves,
            STATE_MESSAGE_FIELDS if is_plane(published.config) else STATE_FIELDS,
        ),
        latency_ns=client.latency_ns(),
        elapsed_s=elapsed,
        recorded_s=(recorded_epochs[-1]["t_ns"] - recorded_epochs[0]["t_ns"]) / 1e9,
        speed=speed,
    )


def run_publish(
    path: str | os.PathLike[str],
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    zenoh_config: os.PathLike[str] | None = None,
    **options: Any,
) -> PublishResult:
    """Open a Zenoh peer on the endpoints (``zenoh_config``: a Zenoh JSON5 file merged over
    the defaults) and `publish_recording` ``path``."""
    if not listen and not connect and zenoh_config is None:
        raise ValueError("give at least one --connect (the service's endpoint) or --listen")
    recording = read_recording(path)  # a bad file fails before the network is touched
    with zenoh.open(peer_config(listen, connect, zenoh_config)) as session:
        return publish_recording(session, recording, **options)


def print_publish(result: PublishResult, console: Console) -> None:
    """What was published, what came back, and the regression check."""
    pace = f"speed {result.speed:g}" if result.paced else "as fast as the service answers"
    console.print(
        f"published session {result.session!r} ({pace}): config, {result.epochs} epochs, "
        f"{result.truths} truths in {result.elapsed_s:.2f} s (recorded: "
        f"{result.recorded_s:.2f} s)",
        soft_wrap=True,
    )
    console.print(
        f"service answered {len(result.moves)} moves, {len(result.states)} states, "
        f"{len(result.target_events)} target events",
        soft_wrap=True,
    )
    if result.latency_ns:
        ms = np.asarray(result.latency_ns, dtype=np.float64) / 1e6
        console.print(
            f"epoch to next move: median {np.median(ms):.2f} ms, p99 "
            f"{np.percentile(ms, 99):.2f} ms, max {ms.max():.2f} ms"
        )
    if result.moves_equal:
        console.print(f"moves equal the recorded moves: yes ({result.recorded_moves} moves)")
    else:
        assert result.moves_divergence is not None
        console.print(
            f"moves equal the recorded moves: [bold red]no[/], "
            f"{result.moves_divergence.describe()}",
            soft_wrap=True,
        )
    if result.states_divergence is None:
        console.print(f"states and target events equal the recorded ones: yes "
                      f"({result.recorded_states} states)")
    else:
        console.print(
            f"states and target events equal the recorded ones: no, "
            f"{result.states_divergence.describe()}",
            soft_wrap=True,
        )
