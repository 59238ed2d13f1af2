"""What the browser view shows of each session, built from the messages on the wire.

:class:`SessionView` takes in one session's decoded messages (``config``, ``move``,
``state``, ``event``, ``truth``, ``epoch``; docs/protocol.md) and keeps what the page draws:
the layout (a grid, or a ranked list for a world without one), the agent, the latest
confidence of every task, the best task's confidence and the decoder's balanced accuracy
over the steps, the update latency, the declared targets and whether each was the user's.
:meth:`SessionView.snapshot` is all of it as JSON (for a page that starts following), and
:meth:`SessionView.update` returns the part one message changed (a *patch*: ``set``
replaces fields, ``append`` extends the series). :class:`SessionBook` holds the sessions.

Messages come from the network: :meth:`SessionView.update` checks every field it uses
before it changes anything, and refuses a malformed message with a ``ValueError`` that
names the field, its value and what it must be. The types are the protocol's (the decoder
checks them too); the values must be ones the session's world allows once its config is
seen (:class:`WorldRules`: a state or target of that world, one of its actions, a step of
the session), and the confidences and the balanced accuracy lie in [0, 1]. Everything kept
per session is bounded, the newest kept: :data:`PATH_LENGTH`, :data:`EVENT_LOG`,
:data:`SERIES_LENGTH`, :data:`TARGETS_KEPT`, :data:`PENDING_STEPS`, :data:`TEXT_LENGTH`,
:data:`MAX_TASKS`; and so is the number of sessions (:data:`MAX_SESSIONS`).

Pure bookkeeping: no transport, no clock (receipt times are given).
"""

from __future__ import annotations

import functools
import math
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration_free.config import LearnerConfig
from calibration_free.puddle import puddle_tasks
from calibration_free.world import ACTIONS
from session.config import config_world, learner_settings
from session.plane import PROBE, PUDDLE_MOVES
from wire import protocol

#: Cells of the agent's recent path kept (current cell included).
PATH_LENGTH = 12
#: Events kept per session (the newest).
EVENT_LOG = 20
#: Sessions kept; beyond it the oldest that is not running is forgotten.
MAX_SESSIONS = 32
#: Largest grid side drawn as a grid (a larger one, which the service would refuse
#: anyway, is shown as a list rather than as millions of cells).
MAX_GRID_SIDE = 64
#: Points kept per session of the belief series and of the latency series (the newest).
SERIES_LENGTH = 10_000
#: Declared targets listed per session (the newest; the counts of correct and wrong ones
#: cover them all).
TARGETS_KEPT = 1_000
#: Steps remembered per session while they wait for their pair, per kind (epochs waiting
#: for the move after them, moves for their epoch, truths for their target): the oldest
#: beyond it are forgotten.
PENDING_STEPS = 256
#: Characters kept of an event's message.
TEXT_LENGTH = 500
#: Most tasks a state may hold (its confidences); a state with more is refused.
MAX_TASKS = 65_536

_INT64 = 2**63


def _show(value: Any) -> str:
    """A value as an error message shows it (at most 60 characters)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _is_point(value: Any, unit: bool) -> bool:
    """A point ``[x, y]`` of two finite numbers (``unit``: of the unit square)."""
    return (
        isinstance(value, list) and len(value) == 2
        and all(_is_number(v) and (not unit or 0 <= v <= 1) for v in value)
    )


def _field(fields: dict[str, Any], name: str) -> Any:
    if name not in fields:
        raise ValueError(f"field {name!r} is missing")
    return fields[name]


def _integer(fields: dict[str, Any], name: str, low: int, high: int = _INT64 - 1) -> int:
    """Field ``name``, an integer from ``low`` to ``high``."""
    value = _field(fields, name)
    if not _is_int(value) or not low <= value <= high:
        span = f">= {low} in the int64 range" if high == _INT64 - 1 else f"from {low} to {high}"
        raise ValueError(f"field {name!r} must be an integer {span}; got {_show(value)}")
    return value


def _flag(fields: dict[str, Any], name: str) -> bool:
    value = _field(fields, name)
    if not isinstance(value, bool):
        raise ValueError(f"field {name!r} must be true or false; got {_show(value)}")
    return value


def _text(fields: dict[str, Any], name: str, choices: tuple[str, ...] = ()) -> str:
    value = _field(fields, name)
    if not isinstance(value, str) or (choices and value not in choices):
        expected = f"one of {', '.join(choices)}" if choices else "a string"
        raise ValueError(f"field {name!r} must be {expected}; got {_show(value)}")
    return value


def _fraction(value: Any) -> bool:
    return _is_number(value) and 0 <= value <= 1


def _remember(mapping: dict[int, Any], key: int, value: Any) -> None:
    """``mapping[key] = value``, forgetting the oldest entries beyond :data:`PENDING_STEPS`."""
    mapping.pop(key, None)
    mapping[key] = value
    while len(mapping) > PENDING_STEPS:
        del mapping[next(iter(mapping))]


@dataclass(frozen=True)
class WorldRules:
    """What the messages of a session may hold in its world (from the session's config).

    Attributes
    ----------
    name : str
        The config's ``world``.
    actions : tuple of str
        The world's action names (a move's ``action``).
    n_states : int or None
        States are ``0 .. n_states - 1``; None: points ``[x, y]`` of the unit square.
    n_tasks : int or None
        A truth's target is a task ``0 .. n_tasks - 1``; None: a point of the unit square.
    task_states : tuple of int or None
        The state each task wants the agent in; None in a world that declares no targets
        (the worlds in the plane).
    """

    name: str
    actions: tuple[str, ...]
    n_states: int | None
    n_tasks: int | None
    task_states: tuple[int, ...] | None = None

    def state(self, fields: dict[str, Any], name: str) -> int | list[float]:
        """Field ``name``, a state of this world."""
        value = _field(fields, name)
        if self.n_states is None:
            ok, expected = _is_point(value, True), "a point [x, y] of the unit square"
        else:
            ok = _is_int(value) and 0 <= value < self.n_states
            expected = f"a state from 0 to {self.n_states - 1}"
        if not ok:
            raise ValueError(f"field {name!r} must be {expected} (the {self.name} world); "
                             f"got {_show(value)}")
        return value

    def task(self, value: Any) -> bool:
        """Whether ``value`` is one of this world's tasks (a truth's target)."""
        if self.n_tasks is None:
            return _is_point(value, True)
        return _is_int(value) and 0 <= value < self.n_tasks

    def target(self, fields: dict[str, Any]) -> int | list[float]:
        """A truth's ``target``, a task of this world."""
        value = _field(fields, "target")
        if not self.task(value):
            expected = ("a point [x, y] of the unit square" if self.n_tasks is None
                        else f"a task from 0 to {self.n_tasks - 1}")
            raise ValueError(f"field 'target' must be {expected} (the {self.name} world); "
                             f"got {_show(value)}")
        return value


def world_rules(config: dict[str, Any]) -> WorldRules | None:
    """The rules of a config's world (its fields ``world`` and, for a grid, ``grid``); None
    for one the service refuses (a grid side outside 2..64): its messages are checked as
    those of a world not known."""
    try:
        return _world_rules(config["world"], config.get("grid"))
    except ValueError:
        return None


@functools.cache  # a world that cannot be built raises, and is not cached
def _world_rules(world: str, grid: int | None) -> WorldRules:
    if world == "continuous":
        return WorldRules(world, (PROBE,), None, None)
    if world == "puddle":
        return WorldRules(world, PUDDLE_MOVES, None, len(puddle_tasks()))
    built = config_world({"world": world, "grid": grid})
    tasks = tuple(int(s) for s in built.task_states)
    return WorldRules(world, tuple(built.action_names), built.n_states, len(tasks), tasks)


def _any_state(fields: dict[str, Any], name: str) -> int | list[float]:
    """Field ``name``, a state (or a target) of a world not known: an index or a point."""
    value = _field(fields, name)
    if not ((_is_int(value) and 0 <= value < _INT64) or _is_point(value, False)):
        raise ValueError(f"field {name!r} must be an index from 0 to {_INT64 - 1} or a point "
                         f"[x, y] of two finite numbers; got {_show(value)}")
    return value


def layout_of(
    config: dict[str, Any] | None, n_tasks: int = 0, grid_actions: bool = True
) -> dict[str, Any]:
    """How to draw a session's world: ``{"kind": "grid", "side": n, "inferred": bool}`` or
    ``{"kind": "list"}``.

    A config with a ``grid`` side and no ``world`` description other than a grid is a grid
    world (cells ``row * side + col``); a config of another world is drawn as the agent's
    state and a ranked list of the hypotheses. Without a config (the view missed it: started
    later, or the source reached it after sending it), a session whose number of tasks is a
    square and whose moves are all grid actions is taken for a grid (``inferred``: protocol
    version 1 has grid worlds only); otherwise it is a list.

    Parameters
    ----------
    config : dict or None
        The config message's fields.
    n_tasks : int
        Length of the latest state's confidences (0: none yet).
    grid_actions : bool
        Whether every move seen so far was one of the grid's actions.
    """
    if config is None:
        side = math.isqrt(n_tasks)
        if n_tasks and side * side == n_tasks and grid_actions and side <= MAX_GRID_SIDE:
            return {"kind": "grid", "side": side, "inferred": True}
        return {"kind": "list"}
    world = config.get("world")
    kind = world.get("kind") if isinstance(world, dict) else world
    side = config.get("grid")
    if kind not in (None, "grid") or not isinstance(side, int) or not 1 <= side <= MAX_GRID_SIDE:
        return {"kind": "list"}
    return {"kind": "grid", "side": side, "inferred": False}


def threshold_of(config: dict[str, Any] | None) -> tuple[float, bool]:
    """The confidence threshold beta of a session and whether it is known from its config
    (else the default of :class:`LearnerConfig`)."""
    if config is not None:
        try:
            return learner_settings(config.get("learner", {}), config["frame"]).frame_beta, True
        except (KeyError, ValueError):  # the service rejects such a config
            pass
    return LearnerConfig().frame_beta, False


def _config(fields: dict[str, Any]) -> dict[str, Any]:
    """What the view keeps of a config message's fields (``world``, ``grid`` of a grid,
    ``frame``, ``steps``), checked."""
    world = _text(fields, "world", protocol.CONFIG_WORLDS)
    kept = {"world": world, "frame": _text(fields, "frame"), "steps": _integer(fields, "steps", 0)}
    if not isinstance(_field(fields, "learner"), dict):
        raise ValueError(f"field 'learner' must be a JSON object; got {_show(fields['learner'])}")
    if world == "grid":
        kept["grid"] = _integer(fields, "grid", 0)
    return kept


def _confidences(payload: Any) -> list[float]:
    """A state's payload, checked: 1 to :data:`MAX_TASKS` confidences in [0, 1]."""
    array = isinstance(payload, np.ndarray)
    if not array or payload.ndim != 1 or not 1 <= len(payload) <= MAX_TASKS:
        shape = payload.shape if array else type(payload).__name__
        raise ValueError(f"the payload must hold 1 to {MAX_TASKS} confidences; got {shape}")
    values = payload.astype(np.float64)
    bad = ~((values >= 0) & (values <= 1))  # NaN is neither
    if bad.any():
        first = int(np.argmax(bad))
        raise ValueError(f"the payload's confidences must lie in [0, 1]; got {values[first]} "
                         f"at task {first}")
    return [round(float(c), 6) for c in values]


@dataclass
class SessionView:
    """One session as the view shows it.

    Attributes
    ----------
    id : str
    truth_hidden : bool
        Truth messages are not taken in (:class:`SessionBook`): no page learns the user's
        targets, and declared targets stay unjudged.
    config : dict or None
        What the view keeps of the config message's fields (``world``, ``grid``,
        ``frame``, ``steps``), once seen.
    config_t_ns : int or None
        Its ``t_ns``: a config with another one starts the session anew (id reused).
    rules : WorldRules or None
        What the session's messages may hold (None: its world is not known).
    threshold, threshold_known : float, bool
        The confidence threshold beta, and whether it is the config's (else the default).
    status : {"waiting", "running", "ended", "rejected"}
    step : int
        Step of the latest move (0 before the first).
    agent, from_state : int, [x, y] or None
        The agent's state after and before the latest move.
    action : str or None
    grid_actions : bool
        Whether every move so far was a grid action (:func:`layout_of`).
    path : deque
        The agent's latest states, oldest first (at most :data:`PATH_LENGTH`).
    confidence : list of float
        Latest confidence of every task, in [0, 1] (``n_tasks``).
    best_task : int or None
    confident : bool
    n_signals : int
    balanced_accuracy : float or None
    n_classes : int or None
        Classes of the frame (from the state's ``class_counts``).
    series : deque of [int, float, float or None]
        Per state: ``[n_signals, confidence of its best task, balanced accuracy]``, the
        beliefs after the epoch of step ``n_signals`` (the newest :data:`SERIES_LENGTH`).
    latency : deque of [int, float]
        Per step k: ``[k, ms]`` from the epoch of step k to the move of step k + 1, both
        as received by the view (its own monotonic clock; the newest :data:`SERIES_LENGTH`).
    targets : deque of dict
        Declared targets ``{"step", "cell", "status"}``, status ``"correct"``, ``"wrong"``
        (by the truth of that step) or ``"pending"`` (no truth yet); the newest
        :data:`TARGETS_KEPT`.
    correct, wrong : int
        Targets judged correct and wrong, all of them.
    user_target : int, [x, y] or None
        The user's target in the latest truth.
    events : deque of dict
        The latest events ``{"event", "message"}`` (messages cut at :data:`TEXT_LENGTH`).
    truths, epoch_ns, move_ns : dict of int
        Step -> the user's target, the epoch's and the move's receipt time (ns): truths
        waiting for their target, epochs and moves waiting for each other to make a latency
        (each at most :data:`PENDING_STEPS`, the newest).
    """

    id: str
    truth_hidden: bool = False
    config: dict[str, Any] | None = None
    config_t_ns: int | None = None
    rules: WorldRules | None = None
    threshold: float = LearnerConfig().frame_beta
    threshold_known: bool = False
    status: str = "waiting"
    step: int = 0
    agent: Any = None
    from_state: Any = None
    action: str | None = None
    grid_actions: bool = True
    path: deque[Any] = field(default_factory=lambda: deque(maxlen=PATH_LENGTH))
    confidence: list[float] = field(default_factory=list)
    best_task: int | None = None
    confident: bool = False
    n_signals: int = 0
    balanced_accuracy: float | None = None
    n_classes: int | None = None
    series: deque[list[Any]] = field(default_factory=lambda: deque(maxlen=SERIES_LENGTH))
    latency: deque[list[Any]] = field(default_factory=lambda: deque(maxlen=SERIES_LENGTH))
    targets: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=TARGETS_KEPT))
    correct: int = 0
    wrong: int = 0
    user_target: Any = None
    events: deque[dict[str, str]] = field(default_factory=lambda: deque(maxlen=EVENT_LOG))
    truths: dict[int, Any] = field(default_factory=dict)
    epoch_ns: dict[int, int] = field(default_factory=dict)
    move_ns: dict[int, int] = field(default_factory=dict)

    def snapshot(self) -> dict[str, Any]:
        """Everything the page draws, as JSON-able values (``series_length``: the points a
        page keeps of ``series`` and ``latency``)."""
        config = self.config or {}
        return {
            "session": self.id,
            "status": self.status,
            "layout": self.layout(),
            "threshold": self.threshold,
            "threshold_known": self.threshold_known,
            "steps": config.get("steps"),
            "frame": config.get("frame"),
            "step": self.step,
            "agent": self.agent,
            "from_state": self.from_state,
            "action": self.action,
            "path": list(self.path),
            "confidence": self.confidence,
            "best_task": self.best_task,
            "confident": self.confident,
            "n_signals": self.n_signals,
            "balanced_accuracy": self.balanced_accuracy,
            "n_classes": self.n_classes,
            "series": list(self.series),
            "latency": list(self.latency),
            "series_length": SERIES_LENGTH,
            "targets": list(self.targets),
            "correct": self.correct,
            "wrong": self.wrong,
            "user_target": self.user_target,
            "truth_hidden": self.truth_hidden,
            "events": list(self.events),
        }

    def layout(self) -> dict[str, Any]:
        """See :func:`layout_of`."""
        return layout_of(self.config, len(self.confidence), self.grid_actions)

    def starts_anew(self, config: protocol.Message) -> bool:
        """Whether a config message starts another session under this id: it is not the
        config already seen (re-sent) and this session had a config or has ended."""
        return config.t_ns != self.config_t_ns and (
            self.config is not None or self.status == "ended"
        )

    def update(self, message: protocol.Message, received_ns: int) -> dict[str, Any] | None:
        """Take in one message of this session; return the patch of the snapshot it makes,
        ``{"set": {...}, "append": {...}}`` (``{"reset": snapshot}`` for a new config),
        or None when nothing shown changed.

        Parameters
        ----------
        message : protocol.Message
            A message of this session (as :func:`wire.protocol.decode` returns it).
        received_ns : int
            When the view received it (monotonic clock), ns.

        Raises
        ------
        ValueError
            If a field the view uses is missing, of the wrong type or out of range (see the
            module), naming it; nothing is changed.
        """
        if message.kind not in protocol.KINDS or not isinstance(message.fields, dict):
            raise ValueError(f"unknown kind {_show(message.kind)} or fields not an object")
        handler = getattr(self, f"_on_{message.kind}")
        return handler(message.fields, message, received_ns)

    def _step(self, fields: dict[str, Any]) -> int:
        """The ``step`` field: 1 to the config's ``steps`` (once seen)."""
        return _integer(fields, "step", 1, (self.config or {}).get("steps", _INT64 - 1))

    def _state(self, fields: dict[str, Any], name: str) -> int | list[float]:
        return _any_state(fields, name) if self.rules is None else self.rules.state(fields, name)

    def _on_config(
        self, fields: dict[str, Any], message: protocol.Message, _: int
    ) -> dict[str, Any] | None:
        config = _config(fields)
        if message.t_ns == self.config_t_ns:
            return None  # the same config re-sent
        self.config, self.config_t_ns = config, message.t_ns
        self.rules = world_rules(config)
        self.threshold, self.threshold_known = threshold_of(fields)
        if self.rules is not None:  # truths seen before of tasks the world lacks
            rules = self.rules
            self.truths = {s: t for s, t in self.truths.items() if rules.task(t)}
        return {"reset": self.snapshot()}

    def _on_move(
        self, fields: dict[str, Any], _: protocol.Message, received_ns: int
    ) -> dict[str, Any]:
        step = self._step(fields)
        from_state, to_state = self._state(fields, "from_state"), self._state(fields, "to_state")
        actions = protocol.ACTION_NAMES if self.rules is None else self.rules.actions
        action = _text(fields, "action", actions)
        reached = _flag(fields, "target_reached")
        if reached and self.rules is not None and self.rules.task_states is None:
            raise ValueError(f"field 'target_reached' is true, but the {self.rules.name} "
                             "world declares no targets")
        self.step, self.agent, self.from_state, self.action = step, to_state, from_state, action
        self.path.append(self.agent)
        self.grid_actions &= self.action in ACTIONS
        if self.status == "waiting":  # session_started went by before the view started
            self.status = "running"
        changed: dict[str, Any] = {
            "step": self.step, "agent": self.agent, "from_state": self.from_state,
            "action": self.action, "path": list(self.path), "layout": self.layout(),
            "status": self.status,
        }
        if reached:
            self.targets.append({"step": self.step, "cell": self.from_state, "status": "pending"})
            self._resolve_targets()
            changed |= self._target_fields()
        _remember(self.move_ns, self.step, received_ns)
        return {"set": changed, "append": {"latency": self._latency(self.step - 1)}}

    def _on_state(
        self, fields: dict[str, Any], message: protocol.Message, _: int
    ) -> dict[str, Any]:
        confidence = _confidences(message.payload)
        best_task = _integer(fields, "best_task", 0, len(confidence) - 1)
        confident = _flag(fields, "confident")
        n_signals = _integer(fields, "n_signals", 0)
        accuracy = _field(fields, "balanced_accuracy")
        if accuracy is not None and not _fraction(accuracy):
            raise ValueError("field 'balanced_accuracy' must be a number in [0, 1] or null; "
                             f"got {_show(accuracy)}")
        counts = _field(fields, "class_counts")
        if not isinstance(counts, list) or not all(_is_number(c) and c >= 0 for c in counts):
            raise ValueError("field 'class_counts' must be a list of finite numbers >= 0; "
                             f"got {_show(counts)}")
        self.confidence, self.best_task, self.confident = confidence, best_task, confident
        self.n_signals, self.balanced_accuracy = n_signals, accuracy
        self.n_classes = len(counts) or None
        point = [self.n_signals, self.confidence[self.best_task], self.balanced_accuracy]
        if self.series and self.series[-1][0] == self.n_signals:  # the same beliefs re-sent
            self.series[-1] = point
            appended = []
        else:
            self.series.append(point)
            appended = [point]
        return {
            "set": {
                "confidence": self.confidence, "best_task": self.best_task,
                "confident": self.confident, "n_signals": self.n_signals,
                "balanced_accuracy": self.balanced_accuracy, "n_classes": self.n_classes,
                "layout": self.layout(),
            },
            "append": {"series": appended},
        }

    def _on_event(self, fields: dict[str, Any], _: protocol.Message, __: int) -> dict[str, Any]:
        event = _text(fields, "event", protocol.EVENTS)
        text = _text(fields, "message")[:TEXT_LENGTH]
        status = {
            "session_started": "running", "session_ended": "ended",
            "session_rejected": "rejected",
        }.get(event)
        if status is not None:
            self.status = status
        self.events.append({"event": event, "message": text})
        return {"set": {"status": self.status, "events": list(self.events)}}

    def _on_truth(
        self, fields: dict[str, Any], _: protocol.Message, __: int
    ) -> dict[str, Any] | None:
        if self.truth_hidden:
            return None
        step = self._step(fields)
        target = _any_state(fields, "target") if self.rules is None else self.rules.target(fields)
        _remember(self.truths, step, target)
        self.user_target = target
        changed: dict[str, Any] = {"user_target": self.user_target}
        if self._resolve_targets():
            changed |= self._target_fields()
        return {"set": changed}

    def _on_epoch(
        self, fields: dict[str, Any], _: protocol.Message, received_ns: int
    ) -> dict[str, Any] | None:
        step = self._step(fields)
        _remember(self.epoch_ns, step, received_ns)
        latency = self._latency(step)
        return {"append": {"latency": latency}} if latency else None

    def _latency(self, step: int) -> list[list[Any]]:
        """``[[step, ms]]`` once the epoch of ``step`` and the move after it are both in."""
        if step in self.epoch_ns and step + 1 in self.move_ns:
            ns = self.move_ns.pop(step + 1) - self.epoch_ns.pop(step)
            point = [step, ns / 1e6]
            self.latency.append(point)
            return [point]
        return []

    def _target_fields(self) -> dict[str, Any]:
        return {"targets": list(self.targets), "correct": self.correct, "wrong": self.wrong}

    def _target_state(self, task: Any) -> Any:
        """The state of a truth's target task (a grid's, or without a config: the task)."""
        if self.rules is None or self.rules.task_states is None:
            return task
        return self.rules.task_states[task]

    def _resolve_targets(self) -> bool:
        """Judge the pending targets whose step's truth is in; True if any was."""
        resolved = False
        for target in self.targets:
            if target["status"] == "pending" and target["step"] in self.truths:
                correct = self._target_state(self.truths[target["step"]]) == target["cell"]
                target["status"] = "correct" if correct else "wrong"
                self.correct += correct
                self.wrong += not correct
                resolved = True
        return resolved


class SessionBook:
    """The sessions the view has seen, oldest first (at most :data:`MAX_SESSIONS`).

    Parameters
    ----------
    hide_truth : bool
        Take in no truth message: no page learns the user's targets (see
        :attr:`SessionView.truth_hidden`).
    """

    def __init__(self, hide_truth: bool = False) -> None:
        self.hide_truth = hide_truth
        self.sessions: OrderedDict[str, SessionView] = OrderedDict()

    def view(self, session: str) -> SessionView:
        """The session ``session``, or an empty one (not kept) if it has not been seen."""
        return self.sessions.get(session) or SessionView(session, self.hide_truth)

    def update(
        self, message: protocol.Message, received_ns: int
    ) -> tuple[dict[str, Any] | None, bool]:
        """Route a message to its session (created if new); return its patch (see
        :meth:`SessionView.update`) and whether the list of sessions (ids, statuses)
        changed.

        Raises
        ------
        ValueError
            As :meth:`SessionView.update` (nothing is stored).
        """
        view = self.sessions.get(message.session)
        before = None if view is None else (view.status, view.config_t_ns)
        if view is None or (message.kind == "config" and view.starts_anew(message)):
            view = SessionView(message.session, self.hide_truth)
        patch = view.update(message, received_ns)  # may raise: then nothing is stored
        if self.sessions.get(message.session) is not view:
            self.sessions.pop(message.session, None)
            self.sessions[message.session] = view
            self._forget_old()
        return patch, before != (view.status, view.config_t_ns)

    def listing(self) -> list[dict[str, Any]]:
        """``[{"session", "status", "steps"}]``, oldest first."""
        return [
            {"session": v.id, "status": v.status, "steps": (v.config or {}).get("steps")}
            for v in self.sessions.values()
        ]

    def _forget_old(self) -> None:
        while len(self.sessions) > MAX_SESSIONS:
            idle = [sid for sid, v in self.sessions.items() if v.status != "running"]
            del self.sessions[idle[0] if idle else next(iter(self.sessions))]
