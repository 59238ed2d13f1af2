"""Offline sessions with frame hypotheses (method-extensions §4): the user's frame unknown.

The teacher's frame alternates with the seed: ``("feedback", "guidance")[seed % 2]``, so
seeds 0..2N-1 give N sessions of each. Its task is drawn as usual; signals come from the
dataset classes the world and frame map labels to (line world: feedback classes 0, 1 =
correct, error; guidance classes 0, 1, 2 = right, left, no-move). With ``shuffle_labels``
every answer is a signal drawn uniformly from the whole dataset (data stream) whatever the
user's label: the signals then say nothing about the labels, the shuffled-label control of
the page. (Permuting the dataset's labels once is not such a control: the user draws from
fixed per-class pools without replacement, and a decoder learns the pools' members.)
Random streams are those of `calibration_free.streams`; the world stream drives the
line world's edge moves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acquisition.labelled import LabelledFeatures
from acquisition.sources import DataSpec
from acquisition.user import SimulatedUser
from calibration_free.config import LearnerConfig
from calibration_free.frame_hypotheses import FrameHypothesesLearner
from calibration_free.streams import session_streams
from calibration_free.world import World
from calibration_free.worlds import make_world
from session.tasks import TaskSession

TEACHER_FRAMES: tuple[str, ...] = ("feedback", "guidance")


@dataclass(frozen=True)
class FrameSessionResult:
    """One frame-hypotheses session.

    Attributes
    ----------
    seed : int
    teacher_frame : str
    task : int
        The user's task.
    first_confident_step : int or None
        First step (1-based) whose beliefs, after that step's signal, are confident.
    first_confident_correct : bool or None
        Whether that pair is the user's (task, frame).
    user_pair_confident_step : int or None
        First step at which the user's pair is the confident one (it may come after a
        wrong first decision).
    winning_frame : str
        Frame of the best pair at the end.
    user_pair_confidence : tuple of float
        Pairwise confidence of the user's pair after every step.
    user_task_likelihood : tuple of float
        Normalised likelihood of the user's pair at steps 10, 20, ...
    """

    seed: int
    teacher_frame: str
    task: int
    first_confident_step: int | None
    first_confident_correct: bool | None
    user_pair_confident_step: int | None
    winning_frame: str
    user_pair_confidence: tuple[float, ...]
    user_task_likelihood: tuple[float, ...]

    def to_dict(self) -> dict[str, object]:
        return {
            "seed": self.seed, "teacher_frame": self.teacher_frame, "task": self.task,
            "first_confident_step": self.first_confident_step,
            "first_confident_correct": self.first_confident_correct,
            "user_pair_confident_step": self.user_pair_confident_step,
            "winning_frame": self.winning_frame,
            "user_pair_confidence": list(self.user_pair_confidence),
            "user_task_likelihood": list(self.user_task_likelihood),
        }


def run_frame_session(
    seed: int,
    world: World,
    config: LearnerConfig,
    data: LabelledFeatures,
    steps: int,
    shuffle_labels: bool = False,
) -> FrameSessionResult:
    """One closed-loop session of ``steps`` actions: a simulated user answering a
    `session.tasks.TaskSession` of the frame-hypotheses learner."""
    data_rng, user_rng, learner_rng = session_streams(seed)
    teacher_frame = TEACHER_FRAMES[seed % 2]
    user = SimulatedUser(world, teacher_frame, data.labels, user_rng)
    learner = FrameHypothesesLearner(world, TEACHER_FRAMES, config, learner_rng)
    session = TaskSession(world, learner, seed, steps)
    pair = _UserPair(TEACHER_FRAMES.index(teacher_frame) * world.n_tasks + user.target)
    session.start()
    while not session.finished:
        index, _ = user.answer(session.agent, session.action)
        if shuffle_labels:  # the control: a signal drawn regardless of the label
            index = int(data_rng.integers(len(data.labels)))
        session.observe(data.features[index], on_observe=pair)
    winning = learner.pair(learner.beliefs().best)[1]
    return FrameSessionResult(
        seed, teacher_frame, user.target, pair.first, pair.correct, pair.user_first, winning,
        tuple(pair.confidence), tuple(pair.likelihood),
    )


class _UserPair:
    """What the beliefs say of the user's pair after every signal (the session's
    ``on_observe``): the fields of `FrameSessionResult` it names.

    Parameters
    ----------
    truth : int
        The user's pair, ``frame * n_tasks + task``.
    """

    def __init__(self, truth: int) -> None:
        self.truth = truth
        self.first: int | None = None
        self.correct: bool | None = None
        self.user_first: int | None = None
        self.confidence: list[float] = []
        self.likelihood: list[float] = []

    def __call__(self, step: int, learner: FrameHypothesesLearner) -> None:
        """Read the beliefs after the signal of ``step`` (1-based)."""
        beliefs = learner.beliefs()
        self.confidence.append(float(beliefs.confidence[self.truth]))
        if step % 10 == 0:
            self.likelihood.append(float(beliefs.normalised()[self.truth]))
        if self.first is None and beliefs.confident:
            self.first, self.correct = step, beliefs.best == self.truth
        if self.user_first is None and beliefs.confident and beliefs.best == self.truth:
            self.user_first = step


@dataclass(frozen=True)
class FrameJob:
    """One frame-hypotheses session (picklable, for the workers)."""

    seed: int
    world: str
    grid: int
    config: LearnerConfig
    data: DataSpec
    steps: int
    shuffle_labels: bool


def run_frame_job(job: FrameJob) -> dict[str, object]:
    """The JSON record of one session."""
    data = job.data.resolve("guidance")
    if callable(data):
        data = data(session_streams(job.seed)[0])
    world = make_world(job.world, grid=job.grid)
    return run_frame_session(
        job.seed, world, job.config, data, job.steps, job.shuffle_labels
    ).to_dict()


#: Steps at which the thesis reports the mean W of the user's pair (method-extensions §4).
THESIS_CHECKPOINTS: tuple[int, ...] = (21, 31, 41, 51, 71, 101, 200)


def frame_hypotheses_report(
    sessions: list[dict[str, object]], steps: int, beta: float = 0.9
) -> dict[str, object]:
    """Summary of frame-hypotheses sessions: how often and how soon the user's pair wins,
    over all sessions and per teacher frame.

    ``user_pair_confident_by_step_100`` counts the learner's own decisions (pairwise
    confidence above ``beta`` *and* beating chance); ``user_pair_w_above_beta_by_step_100``
    is the thesis's measure, the pairwise confidence W above ``beta`` alone.
    ``mean_user_pair_w`` is the mean W of the user's pair at the thesis's checkpoints
    within ``steps``.
    """
    summary = _summary(sessions, steps, beta)
    for frame in TEACHER_FRAMES:
        taught = [s for s in sessions if s["teacher_frame"] == frame]
        if taught:
            summary[f"{frame}_teacher"] = _summary(taught, steps, beta)
    return summary


def _summary(sessions: list[dict[str, object]], steps: int, beta: float) -> dict[str, object]:
    first = [s["first_confident_step"] for s in sessions]
    user_first = [s["user_pair_confident_step"] for s in sessions]
    confidence = np.array([s["user_pair_confidence"] for s in sessions])
    return {
        "sessions": len(sessions),
        "sessions_confident": sum(f is not None for f in first),
        "first_confident_correct": sum(bool(s["first_confident_correct"]) for s in sessions),
        "winning_frame_is_teachers": sum(
            s["winning_frame"] == s["teacher_frame"] for s in sessions
        ),
        "user_pair_confident_by_step_100": float(
            np.mean([f is not None and f <= 100 for f in user_first])
        ),
        "user_pair_w_above_beta_by_step_100": float(
            np.mean(confidence[:, :100].max(axis=1) > beta)
        ),
        "median_first_confident_step": float(
            np.median([f if f is not None else steps + 1 for f in first])
        ),
        "undecided": float(np.mean([f is None for f in first])),
        "mean_user_pair_w": {
            str(step): round(float(confidence[:, step - 1].mean()), 3)
            for step in THESIS_CHECKPOINTS
            if step <= steps
        },
    }
