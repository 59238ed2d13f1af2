"""Offline sessions of the puddle world (method-extensions §2).

Streams (`calibration_free.streams`): the data stream generates the signals (six
classes of the Gaussian generator, 20-D, nominal accuracy 0.95, as many per class as the
ErrP synthetic pools), the user stream drives the teacher, the learner stream the learner,
and the world stream the start state, the move lengths and the restarts: when the agent
enters its task's goal cell it starts again from a uniform state (the task stays).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from acquisition.labelled import LabelledFeatures
from acquisition.mixed_teacher import (
    SIGNAL_ACCURACY,
    SIGNAL_DIMS,
    MixedTeacher,
    gaussian_signals,
)
from calibration_free.puddle import PuddleWorld
from calibration_free.puddle_learner import PuddleConfig, PuddleLearner
from calibration_free.streams import session_streams
from session.plane import PUDDLE_MOVES, PuddleSession, plane_config

__all__ = [
    "SIGNAL_ACCURACY", "SIGNAL_DIMS", "PuddleResult", "PuddleStep", "gaussian_signals",
    "run_puddle_session",
]


@dataclass(frozen=True)
class PuddleResult:
    """One session: the taught task's normalised likelihood after every update.

    Attributes
    ----------
    seed, task : int
    update_steps : tuple of int
        Steps (1-based) after which the likelihoods were updated.
    taught_likelihood : tuple of float
        The taught task's normalised likelihood after each of those steps.
    goals_reached : int
    """

    seed: int
    task: int
    update_steps: tuple[int, ...]
    taught_likelihood: tuple[float, ...]
    goals_reached: int

    def to_dict(self) -> dict[str, object]:
        return {
            "seed": self.seed,
            "task": self.task,
            "update_steps": list(self.update_steps),
            "taught_likelihood": list(self.taught_likelihood),
            "goals_reached": self.goals_reached,
        }


@dataclass(frozen=True)
class PuddleStep:
    """One step of an offline session, for a trace (``run_puddle_session``'s ``on_step``).

    Attributes
    ----------
    step : int
        1-based.
    state : ndarray, shape (2,)
        The agent's state when the action was chosen.
    action : int
        Index into `calibration_free.puddle.ACTIONS`.
    label : int
        The teacher's label (index into `calibration_free.puddle.MIXED_LABELS`).
    next_state : ndarray, shape (2,)
        The move's outcome (in the goal cell when ``restart`` is not None).
    restart : ndarray of shape (2,) or None
        The uniform state the agent started again from, when the move entered the task's
        goal cell.
    """

    step: int
    state: np.ndarray
    action: int
    label: int
    next_state: np.ndarray
    restart: np.ndarray | None


def run_puddle_session(
    seed: int,
    config: PuddleConfig,
    world: PuddleWorld,
    steps: int = 525,
    data: LabelledFeatures | None = None,
    on_step: Callable[[PuddleStep], None] | None = None,
) -> PuddleResult:
    """One closed-loop session: a teacher answering a `session.plane.PuddleSession`,
    which restarts the agent (``reset``) when a move enters the task's goal cell; ``data``
    defaults to `gaussian_signals`.

    ``on_step``, if given, is called with every step's `PuddleStep` (it changes
    nothing in the session).
    """
    data_rng, user_rng, _ = session_streams(seed)
    data = gaussian_signals(data_rng) if data is None else data
    teacher = MixedTeacher(world, data.labels, user_rng, mixing=config.mixing)
    session = PuddleSession(plane_config(seed, steps, config), world)
    goal = world.tasks[teacher.task].goal
    update_steps: list[int] = []
    taught: list[float] = []

    def after(step: int, learner: PuddleLearner) -> None:
        if step % config.update_every == 0:
            update_steps.append(step)
            taught.append(float(learner.probabilities[teacher.task]))

    move = session.start().move
    while move is not None:
        state, outcome = np.array(move["from_state"]), np.array(move["to_state"])
        action = PUDDLE_MOVES.index(move["action"])
        index, label = teacher.answer(state, action)
        reset = world.task_cell(outcome) == goal
        step = session.observe(data.features[index], reset, after)
        if on_step is not None:
            restart = session.agent if reset else None
            on_step(PuddleStep(move["step"], state, action, label, outcome, restart))
        move = step.move
    return PuddleResult(
        seed, teacher.task, tuple(update_steps), tuple(taught), len(session.restarts)
    )
