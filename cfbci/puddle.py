"""Offline sessions of the puddle world (method-extensions §2).

Streams (:mod:`calibration_free.session`): the data stream generates the signals (six
classes of the Gaussian generator, 20-D, nominal accuracy 0.95, as many per class as the
ErrP synthetic pools), the user stream drives the teacher, the learner stream the learner,
and the world stream the start state, the move lengths and the restarts: when the agent
enters its task's goal cell it starts again from a uniform state (the task stays).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acquisition.gaussian import generate_gaussian_features
from acquisition.labelled import LabelledFeatures
from acquisition.mixed_teacher import MixedTeacher
from acquisition.sources import SYNTHETIC_EPOCHS_PER_CLASS
from calibration_free.puddle import MIXED_LABELS, PuddleWorld
from calibration_free.puddle_learner import PuddleConfig, PuddleLearner
from calibration_free.session import session_streams, world_stream

#: The Gaussian stand-in for the thesis's speech features: six words, 20-D.
SIGNAL_DIMS, SIGNAL_ACCURACY = 20, 0.95


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


def gaussian_signals(rng: np.random.Generator) -> LabelledFeatures:
    """The session's six-class signals."""
    return generate_gaussian_features(
        SYNTHETIC_EPOCHS_PER_CLASS, len(MIXED_LABELS), SIGNAL_DIMS, SIGNAL_ACCURACY, rng
    )


def run_puddle_session(
    seed: int,
    config: PuddleConfig,
    world: PuddleWorld,
    steps: int = 525,
    data: LabelledFeatures | None = None,
) -> PuddleResult:
    """One closed-loop session; ``data`` defaults to :func:`gaussian_signals`."""
    data_rng, user_rng, learner_rng = session_streams(seed)
    moves = world_stream(seed)
    data = gaussian_signals(data_rng) if data is None else data
    teacher = MixedTeacher(world, data.labels, user_rng, mixing=config.mixing)
    learner = PuddleLearner(world, config, learner_rng)
    goal = world.tasks[teacher.task].goal
    state = moves.uniform(size=2)
    update_steps, taught, reached = [], [], 0
    for step in range(1, steps + 1):
        action = learner.propose(state)
        index, _ = teacher.answer(state, action)
        learner.observe(state, action, data.features[index])
        if step % config.update_every == 0:
            update_steps.append(step)
            taught.append(float(learner.probabilities[teacher.task]))
        state = world.move(state, action, moves)
        if world.task_cell(state) == goal:
            reached += 1
            state = moves.uniform(size=2)
    return PuddleResult(seed, teacher.task, tuple(update_steps), tuple(taught), reached)
