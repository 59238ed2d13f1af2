"""What the browser view shows of each session, built from the messages on the wire.

:class:`SessionView` takes in one session's decoded messages (``config``, ``move``,
``state``, ``event``, ``truth``, ``epoch``; docs/protocol.md) and keeps what the page draws:
the layout (a grid, or a ranked list for a world without one), the agent, the latest
confidence of every task, the best task's confidence and the decoder's balanced accuracy
over the steps, the update latency, the declared targets and whether each was the user's.
:meth:`SessionView.snapshot` is all of it as JSON (for a page that starts following), and
:meth:`SessionView.update` returns the part one message changed (a *patch*: ``set``
replaces fields, ``append`` extends the series). :class:`SessionBook` holds the sessions.

Pure bookkeeping: no transport, no clock (receipt times are given).
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

from calibration_free.config import LearnerConfig
from calibration_free.world import ACTIONS
from session.config import config_world, learner_settings
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


@dataclass
class SessionView:
    """One session as the view shows it.

    Attributes
    ----------
    id : str
    config : dict or None
        The config message's fields, once seen.
    config_t_ns : int or None
        Its ``t_ns``: a config with another one starts the session anew (id reused).
    status : {"waiting", "running", "ended", "rejected"}
    step : int
        Step of the latest move (0 before the first).
    agent, from_state : int or None
        The agent's cell after and before the latest move.
    action : str or None
    grid_actions : bool
        Whether every move so far was a grid action (:func:`layout_of`).
    path : deque of int
        The agent's latest cells, oldest first (at most :data:`PATH_LENGTH`).
    confidence : list of float
        Latest confidence of every task, in [0, 1] (``n_tasks``).
    best_task : int or None
    confident : bool
    n_signals : int
    balanced_accuracy : float or None
    n_classes : int or None
        Classes of the frame (from the state's ``class_counts``).
    series : list of [int, float, float or None]
        Per state: ``[n_signals, confidence of its best task, balanced accuracy]``, the
        beliefs after the epoch of step ``n_signals``.
    latency : list of [int, float]
        Per step k: ``[k, ms]`` from the epoch of step k to the move of step k + 1, both
        as received by the view (its own monotonic clock).
    targets : list of dict
        Declared targets ``{"step", "cell", "status"}``, status ``"correct"``, ``"wrong"``
        (by the truth of that step) or ``"pending"`` (no truth yet).
    user_target : int or None
        The user's target in the latest truth.
    events : deque of dict
        The latest events ``{"event", "message"}``.
    """

    id: str
    config: dict[str, Any] | None = None
    config_t_ns: int | None = None
    status: str = "waiting"
    step: int = 0
    agent: int | None = None
    from_state: int | None = None
    action: str | None = None
    grid_actions: bool = True
    path: deque[int] = field(default_factory=lambda: deque(maxlen=PATH_LENGTH))
    confidence: list[float] = field(default_factory=list)
    best_task: int | None = None
    confident: bool = False
    n_signals: int = 0
    balanced_accuracy: float | None = None
    n_classes: int | None = None
    series: list[list[Any]] = field(default_factory=list)
    latency: list[list[Any]] = field(default_factory=list)
    targets: list[dict[str, Any]] = field(default_factory=list)
    user_target: int | None = None
    events: deque[dict[str, str]] = field(default_factory=lambda: deque(maxlen=EVENT_LOG))
    _truth: dict[int, int] = field(default_factory=dict)  # step -> the user's target
    _epoch_ns: dict[int, int] = field(default_factory=dict)  # step -> epoch received, ns
    _move_ns: dict[int, int] = field(default_factory=dict)  # step -> move received, ns

    def snapshot(self) -> dict[str, Any]:
        """Everything the page draws, as JSON-able values."""
        threshold, known = threshold_of(self.config)
        config = self.config or {}
        return {
            "session": self.id,
            "status": self.status,
            "layout": self.layout(),
            "threshold": threshold,
            "threshold_known": known,
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
            "series": self.series,
            "latency": self.latency,
            "targets": self.targets,
            "user_target": self.user_target,
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
            A decoded message of this session.
        received_ns : int
            When the view received it (monotonic clock), ns.

        Raises
        ------
        ValueError
            If the message contradicts itself (a state's ``best_task`` beyond its tasks);
            nothing is changed.
        """
        handler = getattr(self, f"_on_{message.kind}")
        return handler(message.fields, message, received_ns)

    def _on_config(
        self, fields: dict[str, Any], message: protocol.Message, _: int
    ) -> dict[str, Any] | None:
        if message.t_ns == self.config_t_ns:
            return None  # the same config re-sent
        self.config, self.config_t_ns = dict(fields), message.t_ns
        return {"reset": self.snapshot()}

    def _on_move(
        self, fields: dict[str, Any], _: protocol.Message, received_ns: int
    ) -> dict[str, Any]:
        self.step, self.agent = fields["step"], fields["to_state"]
        self.from_state, self.action = fields["from_state"], fields["action"]
        self.path.append(self.agent)
        self.grid_actions &= self.action in ACTIONS
        if self.status == "waiting":  # session_started went by before the view started
            self.status = "running"
        changed: dict[str, Any] = {
            "step": self.step, "agent": self.agent, "from_state": self.from_state,
            "action": self.action, "path": list(self.path), "layout": self.layout(),
            "status": self.status,
        }
        if fields["target_reached"]:
            self.targets.append({"step": self.step, "cell": self.from_state, "status": "pending"})
            self._resolve_targets()
            changed["targets"] = self.targets
        self._move_ns[self.step] = received_ns
        return {"set": changed, "append": {"latency": self._latency(self.step - 1)}}

    def _on_state(
        self, fields: dict[str, Any], message: protocol.Message, _: int
    ) -> dict[str, Any]:
        assert message.payload is not None  # decode guarantees a state's payload
        if fields["best_task"] >= len(message.payload):
            raise ValueError(
                f"best_task {fields['best_task']} is not one of the {len(message.payload)} tasks"
            )
        self.confidence = [round(float(c), 6) for c in message.payload]
        self.best_task, self.confident = fields["best_task"], fields["confident"]
        self.n_signals, self.balanced_accuracy = fields["n_signals"], fields["balanced_accuracy"]
        self.n_classes = len(fields["class_counts"]) or None
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
        event = fields["event"]
        status = {
            "session_started": "running", "session_ended": "ended",
            "session_rejected": "rejected",
        }.get(event)
        if status is not None:
            self.status = status
        self.events.append({"event": event, "message": fields["message"]})
        return {"set": {"status": self.status, "events": list(self.events)}}

    def _on_truth(
        self, fields: dict[str, Any], _: protocol.Message, __: int
    ) -> dict[str, Any]:
        self._truth[fields["step"]] = fields["target"]
        self.user_target = fields["target"]
        changed: dict[str, Any] = {"user_target": self.user_target}
        if self._resolve_targets():
            changed["targets"] = self.targets
        return {"set": changed}

    def _on_epoch(
        self, fields: dict[str, Any], _: protocol.Message, received_ns: int
    ) -> dict[str, Any] | None:
        self._epoch_ns[fields["step"]] = received_ns
        latency = self._latency(fields["step"])
        return {"append": {"latency": latency}} if latency else None

    def _latency(self, step: int) -> list[list[Any]]:
        """``[[step, ms]]`` once the epoch of ``step`` and the move after it are both in."""
        if step in self._epoch_ns and step + 1 in self._move_ns:
            ns = self._move_ns.pop(step + 1) - self._epoch_ns.pop(step)
            point = [step, ns / 1e6]
            self.latency.append(point)
            return [point]
        return []

    def _target_state(self, task: int) -> int:
        """The state of a truth's target task (a grid's, or without a config: the task)."""
        if self.config is None or self.config.get("world", "grid") == "grid":
            return task
        return int(config_world(self.config).task_states[task])

    def _resolve_targets(self) -> bool:
        """Judge the pending targets whose step's truth is in; True if any was."""
        resolved = False
        for target in self.targets:
            if target["status"] == "pending" and target["step"] in self._truth:
                correct = self._target_state(self._truth[target["step"]]) == target["cell"]
                target["status"] = "correct" if correct else "wrong"
                resolved = True
        return resolved


class SessionBook:
    """The sessions the view has seen, oldest first (at most :data:`MAX_SESSIONS`)."""

    def __init__(self) -> None:
        self.sessions: OrderedDict[str, SessionView] = OrderedDict()

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
            view = SessionView(message.session)
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
