"""Offline closed-loop sessions: the learner, a simulated user and a dataset, no network.

A step is one device action (``goal`` included) answered by one signal. A target is
reached when the device performs the world's declaration action (the grid's ``goal``)
while confident, in the state of the task it is confident about; the user then picks a
new target.

Random streams: `calibration_free.streams` (data, user and learner streams of a
session seed); stochastic moves (the line world's edges) draw from the seed's world stream
(`calibration_free.world.transition_draws`), one number per step.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from acquisition.labelled import LabelledFeatures
from acquisition.user import SimulatedUser
from calibration_free.baseline import DEFAULT_CALIBRATION_TRIALS, CalibratedBaseline
from calibration_free.config import LearnerConfig
from calibration_free.learner import TaskLearner
from calibration_free.prior import Prior
from calibration_free.streams import StepRecord, session_streams
from calibration_free.world import World
from calibration_free.worlds import WORLDS, make_world
from decoding.validation import check_option
from replay.calibration import (
    RuleCounts,
    calibration_counts,
    calibration_curve,
    counts_by_rule,
    pool_counts,
    pool_counts_by_rule,
    rule_summary,
)
from session.core import Step
from session.sessions import task_learner
from session.tasks import TaskSession

BASELINES: tuple[str, ...] = ("calibrated",)


@dataclass(frozen=True)
class SessionConfig:
    """Everything that defines a simulated session but its seed and its data.

    Attributes
    ----------
    steps : int
        Device actions in the session.
    grid : int
        Side of the grid (grid world only).
    learner : LearnerConfig
    baseline : str or None
        None for the calibration-free learner, "calibrated" for the baseline.
    calibration_trials : int
        Calibration actions of the baseline.
    user_error_rate : float
        Probability that the simulated user gives the wrong label.
    world : {"grid", "line", "pick-and-place"}
        The world (`calibration_free.worlds.make_world`).
    prior : Prior or None
        Earlier sessions of the user the learner starts from (`calibration_free.prior`);
        None: none (the report's config then has no ``prior`` key).
    """

    steps: int = 500
    grid: int = 5
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    baseline: str | None = None
    calibration_trials: int = DEFAULT_CALIBRATION_TRIALS
    user_error_rate: float = 0.0
    world: str = "grid"
    prior: Prior | None = None

    def __post_init__(self) -> None:
        check_option("world", self.world, WORLDS)
        if self.prior is not None and self.baseline is not None:
            raise ValueError("the calibrated baseline takes no prior: it calibrates")

    def make_world(self) -> World:
        """The session's world (its large tables are built on first use)."""
        return make_world(self.world, grid=self.grid)

    def to_dict(self) -> dict[str, Any]:
        """Every setting, the learner's as `LearnerConfig.to_dict` writes them, the
        prior's description (`Prior.describe`) if there is one."""
        settings = asdict(dataclasses.replace(self, prior=None))
        del settings["prior"]
        if self.prior is not None:
            settings["prior"] = self.prior.describe()
        return settings | {"learner": self.learner.to_dict()}


#: Steps between two samples of the user's task likelihood (`SessionResult`).
LIKELIHOOD_EVERY = 10


@dataclass(frozen=True)
class SessionResult:
    """Figures of one session (steps are 1-based; None when it never happened).

    Attributes
    ----------
    first_confident_step : int or None
        The first step whose action was chosen while some task was confident.
    first_confident_correct : bool or None
        Whether that task was the user's target then.
    user_task_likelihood : list of float
        Normalised likelihood ``L_t / sum_u L_u`` of the user's current target (the
        matching log-likelihood without the power prior, within the current task segment)
        after steps 10, 20, 30, ... (`LIKELIHOOD_EVERY`).
    calibration_counts : list of [int, int]
        Per confidence bin (`replay.calibration`), the steps whose best task had a
        confidence in it (before the step's action) and those where it was the user's
        target then.
    calibration_counts_by_rule : list of RuleCounts
        The same counts split by the decision rule in force at the step: by default the
        pairwise W against 0.9, and the normalised likelihood against 0.995 in segments
        whose evidence is calibrated.
    shrinkages : list of float or str
        The decoders' shrinkage from each target on (the calibrated baseline's: from the
        end of its calibration); with ``shrinkage="cv"``, the choices the data made.
    temperatures : list of float
        The evidence temperature of each task segment a target ended, in order (1 where
        the evidence was not calibrated: the first segment, a target on fewer than
        ``calibration_signals`` signals, ``calibrated_evidence`` off, the baseline).
    """

    seed: int
    steps: int
    first_target_step: int | None
    first_correct_target_step: int | None
    correct_targets: int
    wrong_targets: int
    first_confident_step: int | None = None
    first_confident_correct: bool | None = None
    user_task_likelihood: list[float] = field(default_factory=list)
    calibration_counts: list[list[int]] = field(default_factory=list)
    calibration_counts_by_rule: list[RuleCounts] = field(default_factory=list)
    shrinkages: list[float | str] = field(default_factory=list)
    temperatures: list[float] = field(default_factory=list)


def run_session(
    seed: int,
    config: SessionConfig,
    data: LabelledFeatures | Callable[[np.random.Generator], LabelledFeatures],
    on_step: Callable[[StepRecord], None] | None = None,
    after_observe: Callable[[TaskLearner], None] | None = None,
    on_move: Callable[[TaskSession, Step], None] | None = None,
) -> SessionResult:
    """Run one closed-loop session: a simulated user answering a
    `session.tasks.TaskSession`.

    Parameters
    ----------
    seed : int
        Session seed (see the module docstring for how streams derive from it).
    config : SessionConfig
    data : LabelledFeatures, or a function of the data stream returning them
        The signals the user answers with (synthetic data are generated per session).
    on_step : callable, optional
        Called with every `StepRecord` (for traces and progress).
    after_observe : callable, optional
        Called with the learner after it observes each step's signal (for measurements of
        its state, e.g. ``tools/labellings.py``); it must not change the learner.
    on_move : callable, optional
        Called with the session and every step it produced (the first move, then each
        observation's), to record the session as the service does
        (`cfbci.bench.returning`); it must not change the learner.
    """
    data_rng, user_rng, learner_rng = session_streams(seed)
    dataset = data(data_rng) if callable(data) else data
    signals = np.asarray(dataset.features, dtype=np.float32)
    world = config.make_world()
    user = SimulatedUser(
        world, config.learner.frame, dataset.labels, user_rng, config.user_error_rate
    )
    calibration = None if config.baseline is None else (
        user.target, config.calibration_trials)
    learner = task_learner(world, config.learner, learner_rng, calibration, config.prior)
    session = TaskSession(world, learner, seed, config.steps, decisions=True)
    observer = None if after_observe is None else (lambda _, learner: after_observe(learner))
    first_target = first_correct = first_confident = confident_correct = None
    correct = wrong = 0
    user_likelihood: list[float] = []
    best_confidence: list[float] = []
    best_is_target: list[bool] = []
    rules: list[tuple[str, float]] = []
    shrinkages: list[float | str] = []
    temperatures: list[float] = []
    move = session.start()
    if on_move is not None:
        on_move(session, move)
    for step in range(1, config.steps + 1):
        beliefs, state, action = move.decision, session.agent, session.action
        assert move.move is not None
        best_confidence.append(float(beliefs.confidence[beliefs.best_task]))
        best_is_target.append(beliefs.best_task == user.target)
        rules.append((beliefs.rule, beliefs.threshold))
        if beliefs.confident and first_confident is None:
            first_confident, confident_correct = step, beliefs.best_task == user.target
        index, _ = user.answer(state, action)
        event = None
        if move.move["target_reached"]:
            reached = state == world.task_states[user.target]
            event = "correct_target" if reached else "wrong_target"
            temperatures.append(learner.evidence_temperature)  # the segment it ends
            first_target = first_target or step
            if event == "correct_target":
                correct += 1
                first_correct = first_correct or step
            else:
                wrong += 1
            user.new_target()
        record = StepRecord(
            seed, step, state, move.move["action"], move.move["to_state"],
            beliefs.confident, beliefs.best_task, event,
        )
        move = session.observe(signals[index], on_observe=observer)
        if on_move is not None:
            on_move(session, move)
        if isinstance(learner, CalibratedBaseline) and step == learner.n_calibration:
            record = dataclasses.replace(record, event="calibration_done")
            user.new_target()
        if record.event in ("correct_target", "wrong_target", "calibration_done"):
            shrinkages.append(learner.shrinkage_in_use)
        if on_step is not None:
            on_step(record)
        if step % LIKELIHOOD_EVERY == 0:
            user_likelihood.append(float(normalised(learner.beliefs().log_likelihood)[user.target]))
    return SessionResult(
        seed, config.steps, first_target, first_correct, correct, wrong, first_confident,
        confident_correct, user_likelihood, calibration_counts(best_confidence, best_is_target),
        counts_by_rule(best_confidence, best_is_target, rules), shrinkages, temperatures,
    )


def normalised(log_likelihood: np.ndarray) -> np.ndarray:
    """``L_t / sum_u L_u`` from log-likelihoods, computed stably: (n_tasks,) -> (n_tasks,)."""
    weights = np.exp(log_likelihood - log_likelihood.max())
    return weights / weights.sum()


def summarise(results: list[SessionResult]) -> dict[str, Any]:
    """Median first target and first confident step (none counts as steps + 1), mean
    targets, pooled wrong rate, the thesis's fraction of wrong *first* targets (among the
    sessions that reached one), the mean user-task likelihood at steps 10, 20, ..., and the
    confidence calibration curve, pooled and per decision rule."""
    firsts = [r.first_target_step or r.steps + 1 for r in results]
    confident = [r.first_confident_step or r.steps + 1 for r in results]
    reached = [r for r in results if r.first_target_step is not None]
    wrong_first = sum(r.first_correct_target_step != r.first_target_step for r in reached)
    correct = sum(r.correct_targets for r in results)
    wrong = sum(r.wrong_targets for r in results)
    samples = min(len(r.user_task_likelihood) for r in results)
    likelihood = np.mean([r.user_task_likelihood[:samples] for r in results], axis=0)
    return {
        "median_first_target_step": float(np.median(firsts)),
        "sessions_with_a_target": len(reached),
        "median_first_confident_step": float(np.median(confident)),
        "mean_correct_targets": correct / len(results),
        "mean_wrong_targets": wrong / len(results),
        "wrong_target_rate": wrong / (correct + wrong) if correct + wrong else 0.0,
        "wrong_first_target_fraction": wrong_first / len(reached) if reached else 0.0,
        "mean_user_task_likelihood": {
            str(LIKELIHOOD_EVERY * (i + 1)): float(v) for i, v in enumerate(likelihood)
        },
        "confidence_calibration": [
            asdict(b) for b in calibration_curve(pool_counts(r.calibration_counts for r in results))
        ],
        "confidence_calibration_by_rule": [
            rule_summary(pooled)
            for pooled in pool_counts_by_rule(r.calibration_counts_by_rule for r in results)
        ],
    }
