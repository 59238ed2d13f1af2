"""Offline sessions of the continuous-goal world (method-extensions §3): learner and teacher.

Random streams are those of `calibration_free.streams`: the user stream drives the
`acquisition.cardinal_teacher.CardinalTeacher` (goal, directions, pools), the
learner stream the `calibration_free.continuous_goals.ContinuousGoalLearner`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from acquisition.cardinal_teacher import CardinalTeacher
from acquisition.labelled import LabelledFeatures
from calibration_free.continuous_goals import ContinuousConfig, ContinuousGoalLearner
from calibration_free.streams import session_streams
from session.plane import ONE_BLAS_THREAD, ContinuousSession, plane_config


@dataclass(frozen=True)
class ContinuousResult:
    """One session: the best particle's distance to the goal after every step.

    Attributes
    ----------
    seed : int
    goal : tuple of float
    distances : tuple of float
        Euclidean distance of the estimate to the goal after steps 1, 2, ...
    probes : tuple of tuple of float
        The probed points, in order.
    """

    seed: int
    goal: tuple[float, float]
    distances: tuple[float, ...]
    probes: tuple[tuple[float, float], ...]

    @property
    def final_distance(self) -> float:
        return self.distances[-1]

    def to_dict(self) -> dict[str, object]:
        return {
            "seed": self.seed,
            "goal": list(self.goal),
            "final_distance": self.final_distance,
            "distance_every_10": [self.distances[k] for k in range(9, len(self.distances), 10)],
        }


def run_continuous_session(
    seed: int,
    config: ContinuousConfig,
    data: LabelledFeatures,
    steps: int = 200,
    class_order: Sequence[int] | None = None,
    on_step: Callable[[ContinuousGoalLearner], None] | None = None,
) -> ContinuousResult:
    """One closed-loop session of ``steps`` probes on a 4-class dataset: a teacher
    answering a `session.plane.ContinuousSession`; ``on_step`` is called with the
    learner after each observation (it must not change it).

    The learner gets each signal as float32, the wire format (as
    `cfbci.offline.simulation.run_session` does), and computes with one BLAS thread (see
    `session.plane`), so that a live session equals this one.
    """
    with threadpool_limits(**ONE_BLAS_THREAD):
        return _run(seed, config, data, steps, class_order, on_step)


def _run(
    seed: int,
    config: ContinuousConfig,
    data: LabelledFeatures,
    steps: int,
    class_order: Sequence[int] | None,
    on_step: Callable[[ContinuousGoalLearner], None] | None,
) -> ContinuousResult:
    _, user_rng, _ = session_streams(seed)
    teacher = CardinalTeacher(data.labels, user_rng, class_order=class_order)
    session = ContinuousSession(plane_config(seed, steps, config))
    signals = np.asarray(data.features, dtype=np.float32)
    distances: list[float] = []
    probes: list[tuple[float, float]] = []

    def after(_: int, learner: ContinuousGoalLearner) -> None:
        if on_step is not None:
            on_step(learner)
        distances.append(float(np.linalg.norm(learner.estimate() - teacher.goal)))

    move = session.start().move
    while move is not None:
        x, y = move["from_state"]
        index, _ = teacher.answer(np.array([x, y]))
        probes.append((x, y))
        move = session.observe(signals[index], on_observe=after).move
    return ContinuousResult(
        seed, (float(teacher.goal[0]), float(teacher.goal[1])), tuple(distances), tuple(probes)
    )
