"""The simulated source: a simulated user answering the live service's moves over Zenoh.

It plays the part of `cfbci.offline.simulation.run_session`'s user against the pipeline
service (docs/protocol.md): it publishes the session's ``config``, waits for
``session_started``, then answers every ``move`` with the ``epoch`` of that step and the
step's ``truth``, until ``session_ended``. The loop (re-sending, sequence numbers, the
events that start and end the session, the timeout) is every client's,
`wire.client.Client`; this module is the user's side: the signals and the answers.

The random streams are those of the simulation (`calibration_free.streams.session_streams`):
the data stream makes the synthetic epochs, the user stream drives
`acquisition.user.SimulatedUser` with the same draws in the same order (the answer
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
world's `acquisition.cardinal_teacher.CardinalTeacher` answers each probe point; the
puddle world's `acquisition.mixed_teacher.MixedTeacher` (its task drawn first from
the user stream, as `cfbci.offline.puddle.run_puddle_session` draws it) answers each move
``(from_state, action)`` with a signal of `acquisition.mixed_teacher.gaussian_signals`
(the data stream's, as offline) and, since it knows its task, says ``reset`` on the epoch
when the move's ``to_state`` is in the task's goal cell: the service then restarts the
agent.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, NamedTuple, TypeVar

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
from wire.client import DEFAULT_TIMEOUT, RESEND_INTERVAL, Client
from wire.prior_upload import file_sha256, upload_priors
from wire.services import QUERY_TIMEOUT, SERVICES, ask_for_offers, pick_service
from wire.zenoh_config import peer_config

log = logging.getLogger("cfbci.source")


@dataclass(frozen=True)
class SourceSettings:
    """One simulated session.

    Attributes
    ----------
    session : str
        Session id: ``NAME`` or ``USER/NAME`` (each ``[A-Za-z0-9_-]{1,64}``).
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
        Probability that the user's label is wrong (see `SimulatedUser`).
    timeout : float
        Seconds the service may keep the source waiting before it gives up (``cfbci
        source --timeout``; a failure guard).
    resend_interval : float
        Seconds between two sendings of the unanswered config or epoch.
    world : {"grid", "line", "pick-and-place", "continuous", "puddle"}
        The world (`calibration_free.worlds.make_world`; "continuous": the plane of
        goal points, frame "cardinal", ``learner`` the ``ContinuousConfig`` settings;
        "puddle": frame "mixed", ``learner`` the ``PuddleConfig`` settings, whose
        ``mixing`` the teacher takes too, and the signals the puddle world's own: ``data``
        must be the default).
    class_order : tuple of int or None
        Continuous world: the dataset class of each direction (default: class k for
        direction k); sent in the config's ``dataset``.
    pick_service : bool
        Ask the services for their load (`wire.services.ask_for_offers`) and name the
        least loaded in the config's ``service``, so that only it runs the session.
    prior : tuple of Path
        Earlier recordings of the user the learner starts from: uploaded into the
        service's prior store where it lacks them (`wire.prior_upload`) and named by
        their SHA-256 in the config's ``prior``.
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
    prior: tuple[Path, ...] = ()

    def __post_init__(self) -> None:
        check_option("world", self.world, (*WORLDS, *PLANE_FRAMES))
        if not self.timeout > 0:
            raise ValueError(f"--timeout must be positive; got {self.timeout}")
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
    """What happened in a simulated session, from the truth and the moves.

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
        Every step as `cfbci.offline.simulation.run_session` traces it (``confident`` and
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
    defaults, says) and run one session (see `replay_session`)."""
    with zenoh.open(peer_config(listen, connect, zenoh_config)) as session:
        return replay_session(session, settings)


def replay_session(
    session: zenoh.Session,
    settings: SourceSettings,
    on_step: Callable[[StepRecord], None] | None = None,
) -> SourceSummary:
    """Run one session against the service reachable through ``session`` (the loop:
    `wire.client.Client`; the user's answers: this module).

    Parameters
    ----------
    session : zenoh.Session
    settings : SourceSettings
    on_step : callable, optional
        Called with each step's record once its move and state have arrived.

    Raises
    ------
    TimeoutError
        If no service subscribes to the config, or the service keeps the source waiting
        for ``settings.timeout`` seconds.
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

    def config() -> dict[str, Any]:
        chosen = {"service": _chosen_service(session, sid)} if settings.pick_service else {}
        named = {"prior": prior} if prior else {}
        return {**chosen, **_config_fields(settings, signals), **named}

    # Uploaded before the config, which names them by the digests of the bytes uploaded.
    prior = upload_priors(
        session, sid, settings.prior, settings.timeout, settings.resend_interval
    ) if settings.prior else []
    with Client(session, sid, log, settings.timeout, settings.resend_interval) as client:
        user = _user(settings, signals, user_rng, client, on_step)
        client.run(config, user)
        return user.summary()


def session_config(settings: SourceSettings) -> dict[str, Any]:
    """The config message's fields the source of ``settings`` sends (but the chosen
    ``service``): its data loaded or generated as the source does, so that a bad dataset
    or setting is found before any network is started.

    Raises
    ------
    ValueError, OSError
        On a dataset that cannot be read or settings that do not fit it.
    """
    return _config_fields(settings, _Signals(settings, session_streams(settings.seed)[0]))


def _config_fields(settings: SourceSettings, signals: _Signals) -> dict[str, Any]:
    return {
        "seed": settings.seed, **settings.world_fields(), "frame": settings.frame,
        "steps": settings.steps, "learner": settings.learner, "dataset": signals.dataset,
        **signals.config, **({"prior": [file_sha256(path) for path in settings.prior]}
                             if settings.prior else {}),
    }


def _chosen_service(session: zenoh.Session, sid: str) -> str:
    """The least loaded service's id (`wire.services`)."""
    offers = ask_for_offers(session)
    if not offers:
        raise TimeoutError(f"session {sid!r}: no service answered the offers query on "
                           f"{SERVICES}/* within {QUERY_TIMEOUT} s")
    chosen = pick_service(offers)
    log.info("session %r: service %s chosen among %s", sid, chosen.service,
             ", ".join(f"{o.service} ({o.sessions}/{o.max_sessions})" for o in offers))
    return chosen.service


def _user(
    settings: SourceSettings,
    signals: _Signals,
    user_rng: np.random.Generator,
    client: Client,
    on_step: Callable[[StepRecord], None] | None,
) -> _User[Any]:
    """The source's side of the session's world: its user (or teacher)."""
    if settings.world == "continuous":
        teacher = CardinalTeacher(signals.labels, user_rng, class_order=settings.class_order)
        return _ContinuousUser(settings, signals, teacher, client, on_step)
    if settings.world == "puddle":
        mixing = plane_settings(
            {"world": "puddle", "frame": settings.frame, "learner": settings.learner}
        ).mixing
        mixed = MixedTeacher(puddle_world(), signals.labels, user_rng, mixing=mixing)
        return _PuddleUser(settings, signals, mixed, client, on_step)
    user = SimulatedUser(
        settings.make_world(), settings.frame, signals.labels, user_rng,
        settings.user_error_rate,
    )
    return _WorldUser(settings, signals, user, client, on_step)


class _Answer(NamedTuple):
    """A user's answer to a move: the dataset signal it sends, the step's truth (its
    target and label), the epoch's ``reset`` and the step's event in the records."""

    index: int
    target: Any
    label: int
    reset: bool = False
    event: str | None = None


UserT = TypeVar("UserT", SimulatedUser, CardinalTeacher, MixedTeacher)


class _User(Generic[UserT]):
    """The source's side of one session (a `wire.client.Answerer`): its user (or
    teacher) answers each move with an epoch and the step's truth; it keeps the score and
    the records. A world's user says how it answers (`_answer`)."""

    def __init__(
        self,
        settings: SourceSettings,
        signals: _Signals,
        user: UserT,
        client: Client,
        on_step: Callable[[StepRecord], None] | None,
    ) -> None:
        self.settings, self.signals, self.user = settings, signals, user
        self.client, self.on_step = client, on_step
        self.records: list[StepRecord] = []
        self.events: dict[int, str | None] = {}  # step -> its event in the records
        self.agent: Any = None  # where the agent is, as the source knows it (None: not known)
        self.first_target: int | None = None
        self.correct = self.wrong = 0

    def on_move(self, move: protocol.Message) -> None:
        """Answer the move with the user's epoch and the step's truth."""
        if self.settings.interval > 0:
            time.sleep(self.settings.interval)  # the user's reaction time
        step = move.fields["step"]
        answer = self._answer(move.fields)
        self.client.send_epoch(
            self.signals.epoch_fields(step, answer.reset), self.signals.values[answer.index],
            {"step": step, "target": answer.target, "label": answer.label},
        )
        self.events[step] = answer.event

    def poll(self) -> float:
        """Complete the records whose state has arrived; nothing else is ever due."""
        self._complete_records()
        return math.inf

    def _answer(self, fields: dict[str, Any]) -> _Answer:
        raise NotImplementedError

    def _complete_records(self) -> None:
        """Records of the answered steps whose state has arrived, in step order."""
        moves, states = self.client.moves, self.client.states
        while (step := len(self.records) + 1) in self.events and step - 1 in states:
            move, state = moves[step].fields, states[step - 1].fields
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
            self.wrong, self.records, self.client.latency_ns(),
        )


class _WorldUser(_User[SimulatedUser]):
    """The grid's, the line's and pick-and-place's source: a `SimulatedUser` answers
    each move by its label for the move's action in its ``from_state``; a target declared
    is judged against the user's target, which then changes."""

    def _answer(self, fields: dict[str, Any]) -> _Answer:
        step, state, world = fields["step"], fields["from_state"], self.user.world
        agent = self.user.start_state if self.agent is None else self.agent
        if state != agent:
            log.warning("step %d: move from state %d, the agent was in %d", step, state, agent)
        if fields["action"] not in world.action_names:
            raise RuntimeError(
                f"the service's move of step {step} is {fields['action']!r}, not an action of "
                f"the {world.name} world: {', '.join(world.action_names)}"
            )
        index, label = self.user.answer(state, world.action_names.index(fields["action"]))
        target, event = self.user.target, None
        if fields["target_reached"]:
            reached = state == world.task_states[target]
            event = "correct_target" if reached else "wrong_target"
            self.first_target = self.first_target or step
            self.correct += event == "correct_target"
            self.wrong += event == "wrong_target"
            self.user.new_target()
        self.agent = fields["to_state"]
        return _Answer(index, target, label, event=event)


class _ContinuousUser(_User[CardinalTeacher]):
    """The continuous world's source: a `CardinalTeacher` answers each probe point
    (the move's ``to_state``) with a signal of its direction's class; the truth holds its
    goal point and the direction (``label``)."""

    def _answer(self, fields: dict[str, Any]) -> _Answer:
        if fields["action"] != "probe" or not isinstance(fields["to_state"], list):
            raise RuntimeError(
                f"the service's move of step {fields['step']} is {fields['action']!r} to "
                f"{fields['to_state']!r}, not a probe point of the continuous world"
            )
        index, direction = self.user.answer(np.asarray(fields["to_state"], dtype=float))
        return _Answer(index, [float(x) for x in self.user.goal], direction)


class _PuddleUser(_User[MixedTeacher]):
    """The puddle world's source: a `MixedTeacher` answers each move (its
    ``from_state`` and ``action``) with a signal of its label's class, and says ``reset``
    on the epoch when the move's ``to_state`` is in its task's goal cell (see the module
    docstring); the truth holds the task and the label. A reset step's record has the event
    "reset"."""

    def _answer(self, fields: dict[str, Any]) -> _Answer:
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
        action = PUDDLE_MOVES.index(fields["action"])
        index, label = self.user.answer(np.asarray(start, dtype=float), action)
        world = self.user.world
        goal = world.tasks[self.user.task].goal
        reset = bool(world.task_cell(np.asarray(end, dtype=float)) == goal)
        self.agent = None if reset else end  # the service draws the restart state
        return _Answer(index, self.user.task, label, reset, "reset" if reset else None)
