"""What the browser view shows of each session, built from the messages on the wire.

`SessionView` takes in one session's decoded messages (``config``, ``move``,
``state``, ``event``, ``truth``, ``epoch``; docs/protocol.md) and keeps what the page draws:
the layout (a grid, or a ranked list for a world without one), the agent, the latest
confidence of every task, the best task's confidence and the decoder's balanced accuracy
over the steps, the update latency, the declared targets and whether each was the user's.
`SessionView.snapshot` is all of it as JSON (for a page that starts following), and
`SessionView.update` returns the part one message changed (a *patch*: ``set``
replaces fields, ``append`` extends the series). `SessionBook` holds the sessions.

Messages come from the network: `SessionView.update` checks every field it uses
before it changes anything, and refuses a malformed message with a ``ValueError`` that
names the field, its value and what it must be. The types are the protocol's (the decoder
checks them too); the values must be ones the session's world allows once its config is
seen (`WorldRules`: a state or target of that world, one of its actions, a step of
the session), and the confidences and the balanced accuracy lie in [0, 1]. Everything kept
per session is bounded, the newest kept: `PATH_LENGTH`, `EVENT_LOG`,
`SERIES_LENGTH`, `TARGETS_KEPT`, `PENDING_STEPS`, `TEXT_LENGTH`,
`MAX_TASKS`; and so is the number of sessions (`MAX_SESSIONS`).

Pure bookkeeping: no transport, no clock (receipt times are given).
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

from calibration_free.config import LearnerConfig
from calibration_free.world import ACTIONS
from cfbci.view.checks import (
    INT64,
    WorldRules,
    any_state,
    confidences_of,
    config_of,
    field_of,
    flag_of,
    integer_of,
    is_fraction,
    is_number,
    layout_of,
    remember,
    show,
    text_of,
    threshold_of,
    world_rules,
)
from wire import protocol

#: Cells of the agent's recent path kept (current cell included).
PATH_LENGTH = 12
#: Events kept per session (the newest).
EVENT_LOG = 20
#: Sessions kept; beyond it the oldest that is not running is forgotten.
MAX_SESSIONS = 32
#: Points kept per session of the belief series and of the latency series (the newest).
SERIES_LENGTH = 10_000
#: Declared targets listed per session (the newest; the counts of correct and wrong ones
#: cover them all).
TARGETS_KEPT = 1_000
#: Characters kept of an event's message.
TEXT_LENGTH = 500



@dataclass
class SessionView:
    """One session as the view shows it.

    Attributes
    ----------
    id : str
    truth_hidden : bool
        Truth messages are not taken in (`SessionBook`): no page learns the user's
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
    status : {"waiting", "running", "paused", "ended", "rejected"}
    step : int
        Step of the latest move (0 before the first).
    agent, from_state : int, [x, y] or None
        The agent's state after and before the latest move.
    action : str or None
    grid_actions : bool
        Whether every move so far was a grid action (`layout_of`).
    path : deque
        The agent's latest states, oldest first (at most `PATH_LENGTH`).
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
        beliefs after the epoch of step ``n_signals`` (the newest `SERIES_LENGTH`).
    latency : deque of [int, float]
        Per step k: ``[k, ms]`` from the epoch of step k to the move of step k + 1, both
        as received by the view (its own monotonic clock; the newest `SERIES_LENGTH`).
    targets : deque of dict
        Declared targets ``{"step", "cell", "status"}``, status ``"correct"``, ``"wrong"``
        (by the truth of that step) or ``"pending"`` (no truth yet); the newest
        `TARGETS_KEPT`.
    correct, wrong : int
        Targets judged correct and wrong, all of them.
    user_target : int, [x, y] or None
        The user's target in the latest truth.
    events : deque of dict
        The latest events ``{"event", "message"}`` (messages cut at `TEXT_LENGTH`).
    truths, epoch_ns, move_ns : dict of int
        Step -> the user's target, the epoch's and the move's receipt time (ns): truths
        waiting for their target, epochs and moves waiting for each other to make a latency
        (each at most `PENDING_STEPS`, the newest).
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
        """See `layout_of`."""
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
            A message of this session (as `wire.protocol.decode` returns it).
        received_ns : int
            When the view received it (monotonic clock), ns.

        Raises
        ------
        ValueError
            If a field the view uses is missing, of the wrong type or out of range (see the
            module), naming it; nothing is changed.
        """
        if message.kind not in protocol.KINDS or not isinstance(message.fields, dict):
            raise ValueError(f"unknown kind {show(message.kind)} or fields not an object")
        handler = getattr(self, f"_on_{message.kind}")
        return handler(message.fields, message, received_ns)

    def _step(self, fields: dict[str, Any]) -> int:
        """The ``step`` field: 1 to the config's ``steps`` (once seen)."""
        return integer_of(fields, "step", 1, (self.config or {}).get("steps", INT64 - 1))

    def _state(self, fields: dict[str, Any], name: str) -> int | list[float]:
        return any_state(fields, name) if self.rules is None else self.rules.state(fields, name)

    def _on_config(
        self, fields: dict[str, Any], message: protocol.Message, _: int
    ) -> dict[str, Any] | None:
        config = config_of(fields)
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
        action = text_of(fields, "action", actions)
        reached = flag_of(fields, "target_reached")
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
        remember(self.move_ns, self.step, received_ns)
        return {"set": changed, "append": {"latency": self._latency(self.step - 1)}}

    def _on_state(
        self, fields: dict[str, Any], message: protocol.Message, _: int
    ) -> dict[str, Any]:
        confidence = confidences_of(message.payload)
        best_task = integer_of(fields, "best_task", 0, len(confidence) - 1)
        confident = flag_of(fields, "confident")
        n_signals = integer_of(fields, "n_signals", 0)
        accuracy = field_of(fields, "balanced_accuracy")
        if accuracy is not None and not is_fraction(accuracy):
            raise ValueError("field 'balanced_accuracy' must be a number in [0, 1] or null; "
                             f"got {show(accuracy)}")
        counts = field_of(fields, "class_counts")
        if not isinstance(counts, list) or not all(is_number(c) and c >= 0 for c in counts):
            raise ValueError("field 'class_counts' must be a list of finite numbers >= 0; "
                             f"got {show(counts)}")
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
        event = text_of(fields, "event", protocol.EVENTS)
        text = text_of(fields, "message")[:TEXT_LENGTH]
        status = {
            "session_started": "running", "session_ended": "ended",
            "session_rejected": "rejected", "session_paused": "paused",
            "session_resumed": "running",
        }.get(event)
        if status is not None:
            self.status = status
        self.events.append({"event": event, "message": text})
        changed: dict[str, Any] = {"status": self.status, "events": list(self.events)}
        if event == "target_marked" and not self.truth_hidden:  # the operator's truth
            self.user_target = changed["user_target"] = any_state(fields, "target")
        return {"set": changed}

    def _on_truth(
        self, fields: dict[str, Any], _: protocol.Message, __: int
    ) -> dict[str, Any] | None:
        if self.truth_hidden:
            return None
        step = self._step(fields)
        target = any_state(fields, "target") if self.rules is None else self.rules.target(fields)
        remember(self.truths, step, target)
        self.user_target = target
        changed: dict[str, Any] = {"user_target": self.user_target}
        if self._resolve_targets():
            changed |= self._target_fields()
        return {"set": changed}

    def _on_epoch(
        self, fields: dict[str, Any], _: protocol.Message, received_ns: int
    ) -> dict[str, Any] | None:
        step = self._step(fields)
        remember(self.epoch_ns, step, received_ns)
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
    """The sessions the view has seen, oldest first (at most `MAX_SESSIONS`).

    Parameters
    ----------
    hide_truth : bool
        Take in no truth message: no page learns the user's targets (see
        `SessionView.truth_hidden`).
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
        `SessionView.update`) and whether the list of sessions (ids, statuses)
        changed.

        Raises
        ------
        ValueError
            As `SessionView.update` (nothing is stored).
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
            live = ("running", "paused")
            idle = [sid for sid, v in self.sessions.items() if v.status not in live]
            del self.sessions[idle[0] if idle else next(iter(self.sessions))]
