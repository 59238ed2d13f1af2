"""Sessions of the discrete worlds (grid, line, pick-and-place): a task learner stepped.

`TaskSession` steps a learner of tasks (`CalibrationFreeLearner`, the
calibrated baseline, the frame-hypotheses learner) in a discrete world: the agent's state,
the session's world stream (`calibration_free.world.transition_draws`: a stochastic
move takes its outcome from the stream's number of its step) and the start state of the
session's user stream (`session.config.start_state`). ``move_fields``,
``state_fields`` and ``target_text`` build the ``move``, ``state`` and ``target_reached``
messages (docs/protocol.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration_free.learner import Beliefs, CalibrationFreeLearner, Proposal
from calibration_free.world import GridWorld, TransitionDraws, World, transition_draws
from session.config import start_state
from session.core import Observer, Session, State, Step


class TaskSession(Session):
    """A task learner in a discrete world, stepped as the service steps it.

    Parameters
    ----------
    world : World
    learner : object
        A learner of the world's tasks (``propose(state) -> Proposal``,
        ``observe(state, action, signal)``, ``beliefs()``, ``n_signals``), built on the
        session's learner stream.
    seed : int
        The session seed (world stream and start state).
    steps : int
    decisions : bool
        Keep the beliefs each move was chosen with (`Step.decision`): the offline
        simulation's traces and metrics need them; the service does not.
    start : int, optional
        The agent's start state; default the session's (`session.config.start_state`).

    Attributes
    ----------
    agent : int
        The agent's state before the last move (after it, once the session is over).
    action : int
        The last move's action.
    """

    def __init__(
        self,
        world: World,
        learner: Any,
        seed: int,
        steps: int,
        decisions: bool = False,
        start: int | None = None,
    ) -> None:
        self.world = world
        self.learner = learner
        self.steps = steps
        self.draws = transition_draws(seed)
        self.agent = start_state(seed, world) if start is None else start
        self.action = 0
        self.moves: list[dict[str, Any]] = []
        self._decisions = decisions

    @property
    def n_signals(self) -> int:
        return self.learner.n_signals

    def start(self) -> Step:
        return self._propose()

    def observe(
        self, signal: np.ndarray, reset: bool = False, on_observe: Observer | None = None
    ) -> Step:
        if reset:
            raise ValueError("only the puddle world's epochs may say reset")
        self.learner.observe(self.agent, self.action, signal)
        if on_observe is not None:
            on_observe(self.learner.n_signals, self.learner)
        self.agent = self.world.step(self.agent, self.action, self.draws.uniform(self.step))
        if self.finished:
            return Step(None)
        return self._propose()

    def state(self) -> State:
        beliefs = self.learner.beliefs()
        fields, confidence = state_fields(self.learner, beliefs)
        return State(fields, confidence, beliefs.rule, beliefs.threshold)

    def _propose(self) -> Step:
        decision = self.learner.beliefs() if self._decisions else None
        proposal = self.learner.propose(self.agent)
        step = self.step + 1
        self.moves.append(move_fields(self.world, step, self.agent, proposal, self.draws))
        self.action = proposal.action
        events = (target_text(self.world, step, self.agent),) if (
            proposal.declares_target) else ()
        return Step(self.moves[-1], events, decision)


class OpenLoop:
    """A task learner fed a recorded history (open-loop re-analysis): it observes every
    recorded ``(state, action, signal)`` in order, never proposes, and switches task where
    the recorded device declared a target, to the declared state
    (`calibration_free.learner.TaskLearner.follow_declaration`).

    Parameters
    ----------
    learner : TaskLearner
        Built on the session's learner stream (observing draws nothing from it).
    """

    def __init__(self, learner: Any) -> None:
        self.learner = learner

    def observe(self, state: int, action: int, signal: np.ndarray, declared: bool) -> None:
        """Observe one recorded step; ``declared``: its move declared a target in ``state``."""
        if declared:
            self.learner.follow_declaration(state)
        self.learner.observe(state, action, signal)

    def beliefs(self) -> Beliefs:
        """The learner's current beliefs."""
        return self.learner.beliefs()


def move_fields(
    world: World, step: int, state: int, proposal: Proposal, draws: TransitionDraws
) -> dict[str, Any]:
    """The fields of the ``move`` message of ``proposal`` taken in ``state`` at ``step``.

    ``draws`` is the session's world stream (`calibration_free.world.transition_draws`):
    a stochastic move takes its outcome from the stream's number of ``step``.
    """
    return {
        "step": step,
        "from_state": state,
        "action": world.action_names[proposal.action],
        "to_state": world.step(state, proposal.action, draws.uniform(step)),
        "target_reached": proposal.declares_target,
    }


def target_text(world: World, step: int, state: int) -> str:
    """The message of the ``target_reached`` event of a target declared in ``state``."""
    if isinstance(world, GridWorld):  # the text of protocol version 2's recordings
        return f"step {step}: target reached in cell {state}"
    return f"step {step}: target reached in state {state} ({world.state_name(state)})"


def state_fields(
    learner: CalibrationFreeLearner, beliefs: Beliefs | None = None
) -> tuple[dict[str, Any], np.ndarray]:
    """The fields of a ``state`` message, and its payload: the confidence of every task
    (float32, shape (n_tasks,)); ``beliefs``: the learner's current ones, if the caller
    has them already."""
    beliefs = learner.beliefs() if beliefs is None else beliefs
    counts = (
        learner.history.task_label_weights(beliefs.best_task).sum(axis=0)
        if beliefs.n_signals
        else np.zeros(learner.frame.n_classes)
    )
    fields = {
        "best_task": beliefs.best_task,
        "confident": beliefs.confident,
        "n_signals": beliefs.n_signals,
        "class_counts": [float(c) for c in counts],
        "balanced_accuracy": (
            learner.balanced_accuracy(beliefs.best_task) if beliefs.n_signals else None
        ),
        "points": [],  # the continuous world's particles; none here
    }
    return fields, beliefs.confidence.astype(np.float32)


