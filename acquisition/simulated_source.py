"""The replay source: a simulated user answering the live service's moves over Zenoh.

It plays the part of :func:`cfbci.simulation.run_session`'s user against the pipeline
service (docs/protocol.md): it publishes the session's ``config``, waits for
``session_started``, then answers every ``move`` with the ``epoch`` of that step and the
step's ``truth``, until ``session_ended``.

The random streams are those of the simulation (:func:`calibration_free.streams.session_streams`):
the data stream makes the synthetic epochs, the user stream drives
:class:`acquisition.user.SimulatedUser` with the same draws in the same order (the answer
to a move, then a new target if the move declared one), and the service derives the
learner's stream and the start state from the same seed, in the same world (the
config's ``world``). A live session therefore makes the decisions of ``cfbci simulate
--world W --first-seed S --seeds 1 --trace`` step for step.

Synthetic ErrP data go out as raw float32 epochs (``signal`` "epochs"), which the service turns
into ErrP features exactly as the simulation does; so do the epochs of a session recording
(``.mcap``) that holds raw epochs, with its ``sfreq``, ``tmin`` and ``ch_names``; other
dataset files (and recordings of feature vectors) and synthetic Gaussian signals go out as
their float32 feature vectors (``signal`` "features").

In the worlds of the plane the source is the environment and its teacher: the continuous
world's :class:`acquisition.cardinal_teacher.CardinalTeacher` answers each probe point; the
puddle world's :class:`acquisition.mixed_teacher.MixedTeacher` (its task drawn first from
the user stream, as :func:`cfbci.puddle.run_puddle_session` draws it) answers each move
``(from_state, action)`` with a signal of :func:`acquisition.mixed_teacher.gaussian_signals`
(the data stream's, as offline) and, since it knows its task, says ``reset`` on the epoch
when the move's ``to_state`` is in the task's goal cell: the service then restarts the
agent.
"""

from __future__ import annotations

import logging
import queue
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from acquisition.cardinal_teacher import CardinalTeacher
from acquisition.labelled import LabelledEpochs, LabelledFeatures
from acquisition.mixed_teacher import MixedTeacher, gaussian_signals
from acquisition.sources import DataSpec, synthetic_epochs
from acquisition.user import SimulatedUser
from calibration_free.streams import StepRecord, session_streams
from calibration_free.world import World
from calibration_free.worlds import WORLDS, make_world
from decoding.validation import check_option
from session.plane import PLANE_FRAMES, PUDDLE_MOVES, plane_settings, puddle_world
from wire import protocol
from wire.protocol import SequenceTracker
from wire.services import QUERY_TIMEOUT, SERVICES, ask_for_offers, pick_service
from wire.transport import (
    Outbox,
    Pump,
    Received,
    Resender,
    decode_from_service,
    wait_for_subscribers,
)
from wire.zenoh_config import peer_config

log = logging.getLogger("cfbci.source")

#: Seconds without any message from the service after which the source gives up.
DEFAULT_TIMEOUT = 30.0
#: Seconds between two sendings of an unanswered config or epoch.
RESEND_INTERVAL = 1.0


@dataclass(frozen=True)
class SourceSettings:
    """One replayed session.

    Attributes
    ----------
    session : str
        Session id (``[A-Za-z0-9_-]{1,64}``).
    data : DataSpec
        A dataset file, or synthetic data (ErrP epochs, sent raw; Gaussian signals, sent
        as feature vectors).
    seed : int
        Session seed.
    steps : int
        Device actions in the session.
    grid : int
        Side of the grid (grid world only).
    frame : {"feedback", "guidance"}
    learner : dict
        Learner settings sent in the config (``LearnerConfig`` field: value).
    interval : float
        Seconds between receiving a move and answering it (the user's reaction).
    user_error_rate : float
        Probability that the user's label is wrong (see :class:`SimulatedUser`).
    timeout : float
        Seconds without a message from the service before giving up (a failure guard).
    resend_interval : float
        Seconds between two sendings of the unanswered config or epoch.
    world : {"grid", "line", "pick-and-place", "continuous", "puddle"}
        The world (:func:`calibration_free.worlds.make_world`; "continuous": the plane of
        goal points, frame "cardinal", ``learner`` the ``ContinuousConfig`` settings;
        "puddle": frame "mixed", ``learner`` the ``PuddleConfig`` settings, whose
        ``mixing`` the teacher takes too, and the signals the puddle world's own: ``data``
        must be the default).
    class_order : tuple of int or None
        Continuous world: the dataset class of each direction (default: class k for
        direction k); sent in the config's ``dataset``.
    pick_service : bool
        Ask the services for their load (:func:`wire.services.ask_for_offers`) and name the
        least loaded in the config's ``service``, so that only it runs the session.
    """

    session: str
    data: DataSpec = field(default_factory=DataSpec)
    seed: int = 0
    steps: int = 500
    grid: int = 5
    frame: str = "feedback"
    learner: dict[str, Any] = field(default_factory=dict)
    interval: float = 0.0
    user_error_rate: float = 0.0
    timeout: float = DEFAULT_TIMEOUT
    resend_interval: float = RESEND_INTERVAL
    world: str = "grid"
    class_order: tuple[int, ...] | None = None
    pick_service: bool = False

    def __post_init__(self) -> None:
        check_option("world", self.world, (*WORLDS, *PLANE_FRAMES))
        if self.world == "puddle" and self.data != DataSpec():
            raise ValueError(
                "the puddle world's signals are its own six-class 20-D Gaussian data; leave "
                "--dataset, --synthetic, --synthetic-accuracy and --dims out"
            )

    def make_world(self) -> World:
        """The session's world."""
        return make_world(self.world, grid=self.grid)

    def world_fields(self) -> dict[str, Any]:
        """The config's ``world`` and, in a grid world, ``grid``."""
        return {"world": self.world, **({"grid": self.grid} if self.world == "grid" else {})}


@dataclass(frozen=True)
class SourceSummary:
    """What happened in a replayed session, from the truth and the moves.

    Attributes
    ----------
    session : str
    steps : int
        Epochs sent.
    first_target_step : int or None
        Step of the first declared target (1-based), None if none.
    correct_targets, wrong_targets : int
        Declared targets that were (not) the user's target.
    records : list of StepRecord
        Every step as :func:`cfbci.simulation.run_session` traces it (``confident`` and
        ``best_task`` from the ``state`` that accompanied the move).
    latency_ns : list of int
        Round trip of each epoch but the last, in step order: from the epoch of step k
        published to the move of step k + 1 taken off the source's subscriber, ns of the
        source's monotonic clock (``steps - 1`` values).
    """

    session: str
    steps: int
    first_target_step: int | None
    correct_targets: int
    wrong_targets: int
    records: list[StepRecord]
    latency_ns: list[int]


class _Signals:
    """The signals the user answers with, and the config fields describing them."""

    def __init__(self, settings: SourceSettings, rng: np.random.Generator) -> None:
        self.dataset: dict[str, Any] = {"description": settings.data.describe()}
        data: LabelledEpochs | LabelledFeatures
        if settings.world == "puddle":  # as cfbci simulate --world puddle has them
            data = gaussian_signals(rng)
            self.dataset["description"] = data.source
        elif settings.world == "continuous":  # as cfbci simulate --world continuous has them
            resolved = settings.data.resolve("guidance")
            data = resolved(np.random.default_rng(settings.seed)) if callable(resolved) else (
                resolved)
            self.dataset["class_order"] = (
                None if settings.class_order is None else list(settings.class_order))
        elif settings.data.path is None:
            generate = settings.data.resolve(settings.frame)  # rejects ErrP guidance data
            assert callable(generate)  # synthetic data are generated per session
            # ErrP epochs go out raw, Gaussian signals as feature vectors.
            gaussian = settings.data.synthetic == "gaussian"
            data = generate(rng) if gaussian else synthetic_epochs(
                settings.data.synthetic_accuracy, rng
            )
            self.dataset["synthetic_accuracy"] = settings.data.synthetic_accuracy
        else:  # a recording of raw epochs gives them raw, any other file features
            data = settings.data.load_signals(settings.frame)
            self.dataset["path"] = str(settings.data.path)
        self.labels = data.labels
        if isinstance(data, LabelledEpochs):
            self.values = np.asarray(data.epochs, dtype=np.float32)  # (n, n_ch, n_times) uV
            self.ch_names: list[str] | None = list(data.ch_names)
            self.config: dict[str, Any] = {
                "signal": "epochs", "sfreq": float(data.sfreq), "tmin": float(data.tmin),
                "ch_names": self.ch_names,
            }
        else:
            self.values = np.asarray(data.features, dtype=np.float32)  # (n, d) uV
            self.ch_names = None
            self.config = {"signal": "features"}

    def epoch_fields(self, step: int, reset: bool = False) -> dict[str, Any]:
        fields: dict[str, Any] = {"step": step, "signal": self.config["signal"]}
        if self.ch_names is not None:
            fields["ch_names"] = self.ch_names
        if reset:
            fields["reset"] = True
        return fields


def run_source(
    settings: SourceSettings,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    zenoh_config: Path | None = None,
) -> SourceSummary:
    """Open a Zenoh peer (or what ``zenoh_config``, a Zenoh JSON5 file merged over the
    defaults, says) and replay one session (see :func:`replay_session`)."""
    with zenoh.open(peer_config(listen, connect, zenoh_config)) as session:
        return replay_session(session, settings)


def replay_session(
    session: zenoh.Session,
    settings: SourceSettings,
    on_step: Callable[[StepRecord], None] | None = None,
) -> SourceSummary:
    """Run one session against the service reachable through ``session``.

    Parameters
    ----------
    session : zenoh.Session
    settings : SourceSettings
    on_step : callable, optional
        Called with each step's record once its move and state have arrived.

    Raises
    ------
    TimeoutError
        If no service subscribes to the config, or the service falls silent for
        ``settings.timeout`` seconds.
    RuntimeError
        If the service rejects the session (a ``session_rejected`` event answering its
        config), or moves by an action not of the session's world; ``error`` events
        about single messages are only logged.
    """
    data_rng, user_rng, _ = session_streams(settings.seed)
    signals = _Signals(settings, data_rng)
    sid = settings.session
    if settings.world == "puddle":
        puddle_world()  # the teacher's policy tables (3-4 s), before the config goes out
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    pumps = [Pump(session, protocol.key(sid, kind), kind, inbox) for kind in ("move", "state",
                                                                                "event")]
    outbox = Outbox(session)
    try:
        if not wait_for_subscribers(outbox.publisher(protocol.key(sid, "config")),
                                    settings.timeout):
            raise TimeoutError(f"no service subscribed to {protocol.key(sid, 'config')} "
                               f"within {settings.timeout} s")
        resender = Resender(outbox, settings.resend_interval)
        chosen = {"service": _chosen_service(session, sid)} if settings.pick_service else {}
        config = resender.send("config", sid, {**chosen,
            "seed": settings.seed, **settings.world_fields(), "frame": settings.frame,
            "steps": settings.steps, "learner": settings.learner,
            "dataset": signals.dataset, **signals.config,
        })
        replay = _replay(settings, signals, user_rng, resender, config.t_ns, on_step)
        heard = time.monotonic()
        while not replay.done:
            try:
                replay.handle(inbox.get(timeout=resender.wait(settings.timeout)))
                heard = time.monotonic()
            except queue.Empty:
                if time.monotonic() - heard >= settings.timeout:
                    raise TimeoutError(
                        f"session {sid!r}: no message from the service for {settings.timeout} "
                        f"s (at step {replay.next_step})"
                    ) from None
            resender.poll()
        return replay.summary()
    finally:
        for pump in pumps:
            pump.close()
        outbox.close()


def _chosen_service(session: zenoh.Session, sid: str) -> str:
    """The least loaded service's id (:mod:`wire.services`)."""
    offers = ask_for_offers(session)
    if not offers:
        raise TimeoutError(f"session {sid!r}: no service answered the offers query on "
                           f"{SERVICES}/* within {QUERY_TIMEOUT} s")
    chosen = pick_service(offers)
    log.info("session %r: service %s chosen among %s", sid, chosen.service,
             ", ".join(f"{o.service} ({o.sessions}/{o.max_sessions})" for o in offers))
    return chosen.service


def _replay(
    settings: SourceSettings,
    signals: _Signals,
    user_rng: np.random.Generator,
    resender: Resender,
    config_t_ns: int,
    on_step: Callable[[StepRecord], None] | None,
) -> _Replay:
    """The source's side of the session's world: its user (or teacher) and its replay."""
    if settings.world == "continuous":
        teacher = CardinalTeacher(signals.labels, user_rng, class_order=settings.class_order)
        return _ContinuousReplay(settings, signals, teacher, resender, config_t_ns, on_step)
    if settings.world == "puddle":
        mixing = plane_settings(
            {"world": "puddle", "frame": settings.frame, "learner": settings.learner}
        ).mixing
        mixed = MixedTeacher(puddle_world(), signals.labels, user_rng, mixing=mixing)
        return _PuddleReplay(settings, signals, mixed, resender, config_t_ns, on_step)
    world = settings.make_world()
    user = SimulatedUser(
        world, settings.frame, signals.labels, user_rng, settings.user_error_rate
    )
    return _Replay(settings, signals, world, user, resender, config_t_ns, on_step)


class _Replay:
    """The source's side of one session: answers moves, keeps the score."""

    def __init__(
        self,
        settings: SourceSettings,
        signals: _Signals,
        world: World,
        user: SimulatedUser,
        resender: Resender,
        config_t_ns: int,
        on_step: Callable[[StepRecord], None] | None,
    ) -> None:
        self.settings, self.signals, self.world, self.user = settings, signals, world, user
        self.resender, self.config_t_ns, self.on_step = resender, config_t_ns, on_step
        self.trackers = {kind: SequenceTracker() for kind in ("move", "state", "event")}
        self.started = self.ended = False
        self.moves: dict[int, protocol.Message] = {}  # step -> first move received
        self.states: dict[int, protocol.Message] = {}  # n_signals -> first state received
        self.records: list[StepRecord] = []
        self.events: dict[int, str | None] = {}
        self.epoch_sent_ns: dict[int, int] = {}  # step -> its epoch's t_ns
        self.latency_ns: dict[int, int] = {}  # step k -> epoch k published to move k + 1
        self.next_step = 1  # the next move to answer
        self.last_truth: protocol.Message | None = None  # re-sent with the next epoch
        self.agent = None if user is None else user.start_state  # none in the plane
        self.first_target: int | None = None
        self.correct = self.wrong = 0

    @property
    def done(self) -> bool:
        return (
            self.ended
            and self.next_step > self.settings.steps
            and len(self.records) == self.settings.steps
        )

    def handle(self, received: Received) -> None:
        """Take one message of the service; answer the moves that are due."""
        message = decode_from_service(received, self.trackers, log)
        if message is None:
            return
        if message.kind == "event":
            self._on_event(message)
        elif message.kind == "move":
            step = message.fields["step"]
            self.moves.setdefault(step, message)  # a move sent again is the same move
            if step - 1 in self.epoch_sent_ns:
                self.latency_ns[step - 1] = received.t_ns - self.epoch_sent_ns.pop(step - 1)
            pending = self.resender.pending
            if pending is not None and pending.kind == "epoch" and step > pending.fields["step"]:
                self.resender.answered()
        else:
            self.states.setdefault(message.fields["n_signals"], message)
        while self.started and self.next_step in self.moves:
            self._answer(self.moves[self.next_step])
            self.next_step += 1
        self._complete_records()

    def _on_event(self, message: protocol.Message) -> None:
        event, text = message.fields["event"], message.fields["message"]
        own = message.fields["config_t_ns"] == self.config_t_ns
        if event == "session_started" and own:
            self.started = True
            if self.resender.pending is not None and self.resender.pending.kind == "config":
                self.resender.answered()
        elif event == "session_ended":
            self.ended = True
        elif event == "session_rejected" and own:
            raise RuntimeError(f"the service rejected the session: {text}")
        else:  # errors about single messages, information, others' sessions on this id
            (log.warning if event == "error" else log.info)("%s: %s", event, text)

    def _send_answer(
        self, step: int, index: int, target: Any, label: int, reset: bool = False
    ) -> None:
        """Publish the epoch of ``step`` (dataset signal ``index``; ``reset`` on it when
        true) and the step's truth."""
        sid = self.settings.session
        epoch = self.signals.values[index]
        sent = self.resender.send("epoch", sid, self.signals.epoch_fields(step, reset), epoch)
        self.epoch_sent_ns[step] = sent.t_ns
        if self.last_truth is not None:  # lost if the service restarted before it came
            self.resender.also(self.last_truth)
        truth = {"step": step, "target": target, "label": label}
        self.last_truth = self.resender.send("truth", sid, truth, companion=True)

    def _answer(self, move: protocol.Message) -> None:
        fields = move.fields
        step, state = fields["step"], fields["from_state"]
        if state != self.agent:
            log.warning("step %d: move from state %d, the agent was in %d", step, state, self.agent)
        if fields["action"] not in self.world.action_names:
            raise RuntimeError(
                f"the service's move of step {step} is {fields['action']!r}, not an action of "
                f"the {self.world.name} world: {', '.join(self.world.action_names)}"
            )
        action = self.world.action_names.index(fields["action"])
        if self.settings.interval > 0:
            time.sleep(self.settings.interval)  # the user's reaction time
        index, label = self.user.answer(state, action)
        target = self.user.target
        self._send_answer(step, index, target, label)
        event = None
        if fields["target_reached"]:
            reached = state == self.world.task_states[target]
            event = "correct_target" if reached else "wrong_target"
            self.first_target = self.first_target or step
            self.correct += event == "correct_target"
            self.wrong += event == "wrong_target"
            self.user.new_target()
        self.events[step] = event
        self.agent = fields["to_state"]

    def _complete_records(self) -> None:
        """Records of the answered steps whose state has arrived, in step order."""
        while (step := len(self.records) + 1) < self.next_step and step - 1 in self.states:
            move, state = self.moves[step].fields, self.states[step - 1].fields
            record = StepRecord(
                self.settings.seed, step, move["from_state"], move["action"], move["to_state"],
                state["confident"], state["best_task"], self.events.pop(step),
            )
            self.records.append(record)
            if self.on_step is not None:
                self.on_step(record)

    def summary(self) -> SourceSummary:
        return SourceSummary(
            self.settings.session, len(self.records), self.first_target, self.correct,
            self.wrong, self.records, [self.latency_ns[step] for step in sorted(self.latency_ns)],
        )


class _ContinuousReplay(_Replay):
    """The continuous world's source: a :class:`CardinalTeacher` answers each probe point
    (the move's ``to_state``) with a signal of its direction's class; the truth holds its
    goal point and the direction (``label``)."""

    def __init__(
        self,
        settings: SourceSettings,
        signals: _Signals,
        teacher: CardinalTeacher,
        resender: Resender,
        config_t_ns: int,
        on_step: Callable[[StepRecord], None] | None,
    ) -> None:
        super().__init__(
            settings, signals, None, None, resender, config_t_ns, on_step  # type: ignore[arg-type]
        )
        self.teacher = teacher

    def _answer(self, move: protocol.Message) -> None:
        fields = move.fields
        if fields["action"] != "probe" or not isinstance(fields["to_state"], list):
            raise RuntimeError(
                f"the service's move of step {fields['step']} is {fields['action']!r} to "
                f"{fields['to_state']!r}, not a probe point of the continuous world"
            )
        if self.settings.interval > 0:
            time.sleep(self.settings.interval)  # the user's reaction time
        index, direction = self.teacher.answer(np.asarray(fields["to_state"], dtype=float))
        goal = [float(x) for x in self.teacher.goal]
        self._send_answer(fields["step"], index, goal, direction)
        self.events[fields["step"]] = None


class _PuddleReplay(_Replay):
    """The puddle world's source: a :class:`MixedTeacher` answers each move (its
    ``from_state`` and ``action``) with a signal of its label's class, and says ``reset``
    on the epoch when the move's ``to_state`` is in its task's goal cell (see the module
    docstring); the truth holds the task and the label. A reset step's record has the event
    "reset"."""

    def __init__(
        self,
        settings: SourceSettings,
        signals: _Signals,
        teacher: MixedTeacher,
        resender: Resender,
        config_t_ns: int,
        on_step: Callable[[StepRecord], None] | None,
    ) -> None:
        super().__init__(
            settings, signals, None, None, resender, config_t_ns, on_step  # type: ignore[arg-type]
        )
        self.teacher = teacher
        self.goal = teacher.world.tasks[teacher.task].goal

    def _answer(self, move: protocol.Message) -> None:
        fields = move.fields
        step, start, end = fields["step"], fields["from_state"], fields["to_state"]
        if fields["action"] not in PUDDLE_MOVES or not (
            isinstance(start, list) and isinstance(end, list)
        ):
            raise RuntimeError(
                f"the service's move of step {step} is {fields['action']!r} from {start!r} to "
                f"{end!r}, not a move of the puddle world ({', '.join(PUDDLE_MOVES)} between "
                "points)"
            )
        if self.agent is not None and start != self.agent:
            log.warning("step %d: move from %s, the agent was at %s", step, start, self.agent)
        if self.settings.interval > 0:
            time.sleep(self.settings.interval)  # the user's reaction time
        action = PUDDLE_MOVES.index(fields["action"])
        index, label = self.teacher.answer(np.asarray(start, dtype=float), action)
        world = self.teacher.world
        reset = bool(world.task_cell(np.asarray(end, dtype=float)) == self.goal)
        self._send_answer(step, index, self.teacher.task, label, reset)
        self.events[step] = "reset" if reset else None
        self.agent = None if reset else end  # the service draws the restart state
