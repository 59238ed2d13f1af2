"""One client loop for every source of the service (docs/protocol.md, "A session, message
by message", "Re-sending", "Errors and rejections").

The simulated user (`acquisition.simulated_source`, ``cfbci source``), the LSL bridge
(`acquisition.lsl_bridge`, ``cfbci lsl-bridge``) and the re-publication of a recording
(`cfbci.recordings.publish`, ``cfbci replay --publish``) play the same part: they send a
config, then answer every move with the epoch of its step. `Client` is that part, once:
it subscribes to the session's ``move``, ``state`` and ``event`` keys before anything is
sent, waits for a service to subscribe to the config, sends the config and re-sends it
until its ``session_started`` arrives (answering the service's ``session_pending``
challenge with a ``ready`` message, re-sent with the config: the proof that this client
listens to the session's events), hands every move to the client's own `Answerer` once
and in step order, sends the epochs the answerer gives it (with the step's truth) and
re-sends the latest until the next move arrives, checks the sequence numbers of what it
receives (gaps are logged), takes a repeated move or state as the one it has, and ends
when ``session_ended`` has come with every move and state. While the operator has paused
the session (``session_paused``, until ``session_resumed``) it hands no move to the
answerer and never times out; a ``session_ended`` of the operator (with its ``step``)
ends it after the moves and states of the epochs taken. It ends early only on the
documented reasons: a ``session_rejected`` answering its own config (`RuntimeError`), or
a service that keeps it waiting for ``timeout`` seconds (`TimeoutError`); an ``error``
event, or a rejection of someone else's config on the same id, is only logged. What
stays with each client is its own: where its epochs come from and what it does with a
move.

Layer: the loop speaks only the protocol (keys, messages, sequence numbers, re-sending,
the events that start and end a session) through `wire.transport`; it knows no user,
amplifier or recording. It serves clients of two layers, ``acquisition`` (the simulated
source, the bridge) and ``cfbci`` (``replay --publish``), so it lives in ``wire``, below
both, next to the transport it drives.
"""

from __future__ import annotations

import logging
import math
import queue
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import zenoh

from wire import protocol
from wire.transport import (
    Outbox,
    Pump,
    Received,
    Resender,
    decode_from_service,
    wait_for_subscribers,
)

#: Seconds the service may keep a client waiting before the client gives up.
DEFAULT_TIMEOUT = 30.0
#: Seconds between two sendings of an unanswered config or epoch.
RESEND_INTERVAL = 1.0
#: The kinds a client receives.
KINDS = ("move", "state", "event")


class Answerer(Protocol):
    """A client's own part of the loop: where its epochs come from, what it does with a
    move."""

    def on_move(self, move: protocol.Message) -> None:
        """Take the move of the next step: each step's once, in step order, after the
        session started. Answer it now or later (`poll`) with
        `Client.send_epoch`."""

    def poll(self) -> float:
        """Do what is due now (after every message, every re-send, every wait); return
        the seconds the loop may wait for the service before calling again (``math.inf``:
        until a message comes, or `Client.wake`)."""


class Client:
    """One session of a client; see the module docstring. A context manager: the
    subscriptions are made at once and undeclared on exit.

    Parameters
    ----------
    session : zenoh.Session
    sid : str
        The session id.
    log : logging.Logger
        Where the client's warnings (sequence problems, ``error`` events) go.
    timeout : float
        Seconds the service may keep the client waiting (for ``session_started``, a move,
        the session's end) before `run` gives up; also the wait for a service to
        subscribe to the config.
    resend_interval : float
        Seconds between two sendings of the unanswered config or epoch.

    Attributes
    ----------
    moves : dict of int to Message
        The first move received of each step.
    move_ns : dict of int to int
        When each of them was taken off the subscriber (``time.monotonic_ns()``).
    states : dict of int to Message
        The first state received for each ``n_signals``.
    epoch_ns : dict of int to int
        Each step's epoch's ``t_ns`` (its first sending).
    target_events : list of str
        The messages of the ``target_reached`` events, in order.
    paused : bool
        The operator has paused the session (docs/protocol.md, "Operator controls").
    """

    def __init__(
        self,
        session: zenoh.Session,
        sid: str,
        log: logging.Logger,
        timeout: float = DEFAULT_TIMEOUT,
        resend_interval: float = RESEND_INTERVAL,
    ) -> None:
        self.config_key = protocol.key(sid, "config")  # ProtocolError (ValueError) on a bad id
        self.sid, self.log, self.timeout = sid, log, timeout
        self._inbox: queue.SimpleQueue[Received | None] = queue.SimpleQueue()  # None: a wake
        self._pumps = [Pump(session, protocol.key(sid, kind), kind, self._inbox)
                       for kind in KINDS]
        self._outbox = Outbox(session)
        self._resender = Resender(self._outbox, resend_interval)
        self._trackers = {kind: protocol.SequenceTracker() for kind in KINDS}
        self._config: protocol.Message | None = None
        self._challenge: str | None = None  # the last session_pending's, answered
        self._last_truth: protocol.Message | None = None  # re-sent with the next epoch
        self._answerer: Answerer | None = None
        self._heard_ns = time.monotonic_ns()  # last message heard, or last epoch sent
        self.steps = 0
        self.started = self.ended = self.paused = False
        self.next_step = 1  # the next move to hand to the answerer
        self.answered_step = 0  # the last step whose epoch was sent
        self.moves: dict[int, protocol.Message] = {}
        self.move_ns: dict[int, int] = {}
        self.states: dict[int, protocol.Message] = {}
        self.epoch_ns: dict[int, int] = {}
        self.target_events: list[str] = []

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *_: object) -> None:
        for pump in self._pumps:
            pump.close()
        self._outbox.close()

    @property
    def complete(self) -> bool:
        """``session_ended`` has come, and every move (all handed to the answerer) and
        every state (``n_signals`` 0 to ``steps``)."""
        return (
            self.ended
            and self.next_step > self.steps
            and all(n in self.states for n in range(self.steps + 1))
        )

    @property
    def awaiting(self) -> bool:
        """The client waits for the service (not the service for the client): the
        session has not started, or every move handed to the answerer has its epoch; never
        while the operator has paused the session."""
        return not self.paused and (not self.started or self.answered_step == self.next_step - 1)

    def latency_ns(self) -> list[int]:
        """Per epoch but the last: from its first sending to the next move taken off the
        subscriber, ns (``steps - 1`` values once `complete`)."""
        return [self.move_ns[step + 1] - self.epoch_ns[step] for step in range(1, self.steps)]

    def run(
        self,
        config: dict[str, Any] | Callable[[], dict[str, Any]],
        answerer: Answerer,
        keep_running: Callable[[], bool] = lambda: True,
    ) -> None:
        """Run the session: send ``config`` (its fields, or a function giving them once a
        service has subscribed), then take the service's messages and hand the moves to
        ``answerer`` until `complete` (or until ``keep_running()`` is false).

        Raises
        ------
        TimeoutError
            If no service subscribes to the config within ``timeout``, or the service
            keeps the client waiting for ``timeout`` seconds.
        RuntimeError
            If the service rejects the session (``session_rejected`` answering this
            client's config).
        """
        if not wait_for_subscribers(self._outbox.publisher(self.config_key), self.timeout):
            raise TimeoutError(
                f"no service subscribed to {self.config_key} within {self.timeout:g} s"
            )
        fields = config() if callable(config) else config
        self.steps, self._answerer = fields["steps"], answerer
        self._config = self._resender.send("config", self.sid, fields)
        self._heard_ns = time.monotonic_ns()
        wait = math.inf
        while not self.complete and keep_running():
            self._receive(min(self._resender.wait(self.timeout), wait))
            self._resender.poll()
            wait = answerer.poll()

    def send_epoch(
        self, fields: dict[str, Any], payload: np.ndarray, truth: dict[str, Any] | None = None
    ) -> protocol.Message:
        """Publish the epoch of ``fields["step"]`` and, if given, the step's ``truth``; both
        are re-sent, with the previous step's truth, until the next move arrives."""
        epoch = self._resender.send("epoch", self.sid, fields, payload)
        step = fields["step"]
        self.epoch_ns.setdefault(step, epoch.t_ns)
        self.answered_step = step
        self._heard_ns = time.monotonic_ns()
        if self._last_truth is not None:  # lost if the service restarted before it came
            self._resender.also(self._last_truth)
        if truth is not None:
            self._last_truth = self._resender.send("truth", self.sid, truth, companion=True)
        return epoch

    def wake(self) -> None:
        """End `run`'s wait for the service now, so that the answerer's `poll` runs at
        once (from any thread: one that reads the answerer's own input, say)."""
        self._inbox.put(None)

    def _receive(self, wait: float) -> None:
        """Take the messages that came, or wait up to ``wait`` s for one (or a `wake`)."""
        try:
            received = self._inbox.get(timeout=wait) if wait > 0 else self._inbox.get_nowait()
            while True:
                if received is not None:
                    self._heard_ns = time.monotonic_ns()
                    self._take(received)
                received = self._inbox.get_nowait()
        except queue.Empty:
            pass
        if self.awaiting and time.monotonic_ns() - self._heard_ns >= self.timeout * 1e9:
            raise TimeoutError(
                f"session {self.sid!r}: no message from the service for "
                f"{self.timeout:g} s (awaiting {self._awaited()})"
            )

    def _awaited(self) -> str:
        if not self.started:
            return "session_started"
        if self.next_step <= self.steps:
            return f"the move of step {self.next_step}"
        return "the session's end"

    def _take(self, received: Received) -> None:
        message = decode_from_service(received, self._trackers, self.log)
        if message is None:
            return
        fields = message.fields
        if message.kind == "move":
            step = fields["step"]
            if step not in self.moves:  # a move sent again is the same move
                self.moves[step], self.move_ns[step] = message, received.t_ns
            pending = self._resender.pending
            if pending is not None and pending.kind == "epoch" and step > pending.fields["step"]:
                self._resender.answered()
        elif message.kind == "state":
            self.states.setdefault(fields["n_signals"], message)
        else:
            self._on_event(
                fields["event"], fields["message"], fields["config_t_ns"],
                fields.get("challenge"), fields.get("step"),
            )
        assert self._answerer is not None
        while (self.started and not self.paused and self.next_step <= self.steps
               and self.next_step in self.moves):
            self._answerer.on_move(self.moves[self.next_step])
            self.next_step += 1

    def _on_event(
        self, event: str, text: str, config_t_ns: int | None, challenge: str | None,
        step: int | None,
    ) -> None:
        assert self._config is not None
        own = config_t_ns == self._config.t_ns
        if event == "session_pending" and own and challenge is not None and not self.started:
            if challenge != self._challenge:  # proves this client listens: re-sent with the
                self._challenge = challenge  # config until the session starts
                ready = {"config_t_ns": self._config.t_ns, "challenge": challenge}
                self._resender.send("ready", self.sid, ready, companion=True)
        elif event == "session_started" and own:
            self.started = True
            pending = self._resender.pending
            if pending is not None and pending.kind == "config":
                self._resender.answered()
        elif event == "session_rejected" and own:
            raise RuntimeError(f"the service rejected session {self.sid!r}: {text}")
        elif event == "session_ended":
            self.ended = True
            if step is not None:  # the operator ended it after the move of ``step``
                self.steps = min(self.steps, step - 1)
                self.log.info("%s: %s", event, text)
        elif event in ("session_paused", "session_resumed"):
            self.paused = event == "session_paused"  # moves held until the resumption
            self.log.info("%s: %s", event, text)
        elif event == "target_reached":
            self.target_events.append(text)
        else:  # errors about single messages, information, others' sessions on this id
            (self.log.warning if event == "error" else self.log.info)("%s: %s", event, text)
