"""Every learner passes the conformance checks of ``tests/conformance.py``, and each check
catches a learner that breaks its rule."""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cache, partial

import numpy as np
import pytest
from conformance import (
    ContinuousTeacher,
    LearnerFactory,
    PuddleTeacher,
    TaskTeacher,
    TeacherFactory,
    check_beliefs_well_formed,
    check_deterministic,
    check_label_free_interface,
    check_learns_from_signals_alone,
    check_rejects_malformed_signals,
    wire_signal,
)

from calibration_free.baseline import CalibratedBaseline
from calibration_free.config import LearnerConfig
from calibration_free.continuous_goals import ContinuousConfig, ContinuousGoalLearner
from calibration_free.frame_hypotheses import FrameHypothesesLearner
from calibration_free.learner import CalibrationFreeLearner, Proposal
from calibration_free.protocol import (
    NORMALISED,
    AdaptedBeliefs,
    ContinuousLearnerAdapter,
    FrameHypothesesAdapter,
    Learner,
    PuddleLearnerAdapter,
)
from calibration_free.puddle_learner import PuddleConfig, PuddleLearner
from calibration_free.streams import session_streams
from calibration_free.world import GridWorld, World
from calibration_free.worlds import make_world
from decoding.validation import check_array
from session.plane import puddle_world

STEPS = 16
#: Small settings: the planners run from the 5th signal, on few sampled signals.
SMALL = {"warmup_steps": 4, "n_planning_signals": 5, "n_folds": 5}
CALIBRATION_TRIALS = 8
FRAME_CONFIG = LearnerConfig(planner="random", power_prior=False, **SMALL)
#: The continuous learner scores its particles from the 6th signal, the puddle learner
#: updates every 5.
CONTINUOUS_CONFIG = ContinuousConfig(
    n_hypotheses=8, n_initial=6, n_draws=4, n_candidates=40, n_map_signals=5, n_folds=3
)
PUDDLE_CONFIG = PuddleConfig(update_every=5, n_map_states=10, n_map_signals=5)


@dataclass(frozen=True)
class Case:
    """A learner, the teacher it learns from and its declared calibration inputs."""

    make_learner: LearnerFactory
    make_teacher: TeacherFactory
    calibration_inputs: tuple[str, ...] = ()


@cache
def _world(kind: str) -> World:
    """One world of each kind for the module: its optimal-action table is built once."""
    return make_world(kind, grid=3)


def _calibration_free(kind: str, frame: str, seed: int) -> Learner:
    return CalibrationFreeLearner(_world(kind), LearnerConfig(frame=frame, **SMALL), _rng(seed))


def _baseline(seed: int) -> Learner:
    """Calibrated on the user's first target: its one calibration input, as in a session."""
    world = _world("grid")
    target = TaskTeacher(world, "feedback", seed).user.target
    return CalibratedBaseline(
        world, calibration_target=target, n_calibration=CALIBRATION_TRIALS,
        config=LearnerConfig(**SMALL), rng=_rng(seed),
    )


def _frame_hypotheses(seed: int) -> Learner:
    return FrameHypothesesAdapter(_world("line"), config=FRAME_CONFIG, rng=_rng(seed))


def _continuous(seed: int) -> Learner:
    return ContinuousLearnerAdapter(CONTINUOUS_CONFIG, _rng(seed))


def _puddle(seed: int) -> Learner:
    return PuddleLearnerAdapter(puddle_world(), PUDDLE_CONFIG, _rng(seed))


def _rng(seed: int) -> np.random.Generator:
    """The learner stream of a session seed."""
    return session_streams(seed)[2]


def _task_teacher(kind: str, frame: str, seed: int) -> TaskTeacher:
    return TaskTeacher(_world(kind), frame, seed)


CASES = {
    **{
        f"calibration-free {kind} {frame}": Case(
            partial(_calibration_free, kind, frame), partial(_task_teacher, kind, frame)
        )
        for kind in ("grid", "line", "pick-and-place")
        for frame in ("feedback", "guidance")
    },
    "calibrated baseline": Case(
        _baseline, partial(_task_teacher, "grid", "feedback"), ("calibration_target",)
    ),
    "frame hypotheses": Case(_frame_hypotheses, partial(_task_teacher, "line", "guidance")),
    "continuous": Case(_continuous, ContinuousTeacher),
    "puddle": Case(_puddle, lambda seed: PuddleTeacher(puddle_world(), seed)),
}
#: The learners behind the adapters, driven directly: (build, propose -> action,
#: observe(learner, state, action, signal), confidence), by adapted case.
WRAPPED = {
    "frame hypotheses": (
        lambda seed: FrameHypothesesLearner(_world("line"), config=FRAME_CONFIG, rng=_rng(seed)),
        lambda learner, state: learner.propose(state).action,
        lambda learner, state, action, signal: learner.observe(state, action, signal),
        lambda learner: learner.beliefs().confidence,
    ),
    "continuous": (
        lambda seed: ContinuousGoalLearner(CONTINUOUS_CONFIG, _rng(seed)),
        lambda learner, state: learner.propose(),
        lambda learner, state, action, signal: learner.observe(action, signal),
        lambda learner: learner.confidence,
    ),
    "puddle": (
        lambda seed: PuddleLearner(puddle_world(), PUDDLE_CONFIG, _rng(seed)),
        lambda learner, state: learner.propose(state),
        lambda learner, state, action, signal: learner.observe(state, action, signal),
        lambda learner: learner.probabilities,
    ),
}
SESSION_CHECKS = {
    "signals alone": check_learns_from_signals_alone,
    "deterministic": check_deterministic,
    "well-formed beliefs": check_beliefs_well_formed,
    "malformed signals": check_rejects_malformed_signals,
}


@pytest.mark.parametrize("name", CASES)
def test_the_learner_takes_no_label_after_its_construction(name):
    case = CASES[name]
    check_label_free_interface(case.make_learner, case.calibration_inputs)


@pytest.mark.parametrize("check", SESSION_CHECKS)
@pytest.mark.parametrize("name", CASES)
def test_the_learner_passes_the_session_checks(name, check):
    case = CASES[name]
    SESSION_CHECKS[check](case.make_learner, case.make_teacher, STEPS)


@pytest.mark.parametrize("name", WRAPPED)
def test_an_adapter_calls_its_learner_as_a_direct_caller_does(name):
    """The adapted learner and the learner driven directly (as the sessions drive it), on
    one seed and one teacher's signals, take the same actions, end on the same generator
    state and the same confidences, the adapter's beliefs read at every step."""
    build, propose, observe, confidence = WRAPPED[name]
    case = CASES[name]
    adapter, direct = case.make_learner(5), build(5)
    teachers = case.make_teacher(5), case.make_teacher(5)
    states = [teacher.start() for teacher in teachers]
    for step in range(STEPS):
        adapter.beliefs()
        proposal = adapter.propose(states[0])
        action = propose(direct, states[1])
        assert np.array_equal(proposal.action, action), f"step {step + 1}"
        (signal, next_state), (direct_signal, direct_next) = (
            teachers[0].answer(states[0], proposal), teachers[1].answer(states[1], proposal)
        )
        adapter.observe(states[0], proposal.action, wire_signal(signal))
        observe(direct, states[1], action, wire_signal(direct_signal))
        states = [next_state, direct_next]
    wrapped = adapter.learner
    assert wrapped.rng.bit_generator.state == direct.rng.bit_generator.state
    assert np.array_equal(adapter.beliefs().confidence, confidence(direct))
    assert adapter.n_signals == STEPS


def test_the_sessions_reach_the_paths_they_check():
    """The baseline leaves its calibration and the planners run within the steps, so the
    checks see the decoders and the planner at work, not only the warm-up."""
    assert CALIBRATION_TRIALS < STEPS and SMALL["warmup_steps"] < STEPS
    baseline = _baseline(0)
    teacher = _task_teacher("grid", "feedback", 0)
    state = teacher.start()
    for _ in range(STEPS):
        proposal = baseline.propose(state)
        signal, next_state = teacher.answer(state, proposal)
        baseline.observe(state, proposal.action, signal.astype(np.float32))
        state = next_state
    assert not baseline.calibrating and np.any(baseline.beliefs().log_likelihood != 0)


# --- deliberately broken learners: each check catches its rule's breach ----------------


class ToyLearner:
    """A small learner that keeps the rules: the tasks are a grid's cells, a task's score
    the summed first feature of the signals observed in its cell; actions are uniform
    draws from its own generator."""

    def __init__(self, world: World, rng: np.random.Generator) -> None:
        self.world, self.rng = world, rng
        self.n_signals = 0
        self._scores = np.zeros(world.n_tasks)
        self._n_features: int | None = None

    def propose(self, state: int) -> Proposal:
        return Proposal(int(self.rng.integers(self.world.n_actions)), False)

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        x = check_array("signal", signal, shape=(self._n_features,))
        self._n_features = x.shape[0]
        self._scores[state] += x[0]
        self.n_signals += 1

    def beliefs(self) -> AdaptedBeliefs:
        weights = np.exp(self._scores - self._scores.max())
        confidence = weights / weights.sum()
        return AdaptedBeliefs(
            confidence, int(np.argmax(confidence)), False, self.n_signals, NORMALISED
        )


class TakesLabel(ToyLearner):
    def observe(  # type: ignore[override]
        self, state: int, action: int, signal: np.ndarray, label: int | None = None
    ) -> None:
        super().observe(state, action, signal)


class TakesTarget(ToyLearner):
    def __init__(self, world: World, rng: np.random.Generator, target: int = 0) -> None:
        super().__init__(world, rng)


class GlobalRandom(ToyLearner):
    def propose(self, state: int) -> Proposal:
        return Proposal(int(np.random.randint(self.world.n_actions)), False)  # noqa: NPY002


class TouchesGlobalState(ToyLearner):
    """Draws from numpy's and the random module's global states, using nothing of it."""

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        np.random.random()  # noqa: NPY002
        random.random()
        super().observe(state, action, signal)


class DrawingBeliefs(ToyLearner):
    def beliefs(self) -> AdaptedBeliefs:
        self.rng.random()
        return super().beliefs()


class Unnormalised(ToyLearner):
    def beliefs(self) -> AdaptedBeliefs:
        beliefs = super().beliefs()
        return replace(beliefs, confidence=beliefs.confidence * 0.5)


class BestIsNotBest(ToyLearner):
    def beliefs(self) -> AdaptedBeliefs:
        beliefs = super().beliefs()
        return replace(beliefs, best_task=int(np.argmin(beliefs.confidence)))


class Miscounts(ToyLearner):
    def beliefs(self) -> AdaptedBeliefs:
        return replace(super().beliefs(), n_signals=min(self.n_signals, 3))


class LiveBeliefs(ToyLearner):
    """Returns one confidence buffer, overwritten by every call."""

    def __init__(self, world: World, rng: np.random.Generator) -> None:
        super().__init__(world, rng)
        self._confidence = np.zeros(world.n_tasks)

    def beliefs(self) -> AdaptedBeliefs:
        beliefs = super().beliefs()
        self._confidence[:] = beliefs.confidence
        return replace(beliefs, confidence=self._confidence)


class IndexErrorOnWrongSize(ToyLearner):
    """Checks a signal's rank and values but not its size: reads the last feature where
    the first signal had it."""

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        x = check_array("signal", signal, shape=(None,))
        last = len(x) - 1 if self._n_features is None else self._n_features - 1
        self._scores[state] += x[last] - x[0]
        self._n_features = last + 1
        self.n_signals += 1


class KeepsRejected(ToyLearner):
    """Takes in a signal before checking it."""

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        self._scores[state] += 1.0
        super().observe(state, action, signal)


class VagueError(ToyLearner):
    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        if self._n_features is not None and np.shape(signal) != (self._n_features,):
            raise ValueError("bad input")
        super().observe(state, action, signal)


TOY_WORLD = GridWorld(3)


def _toy(kind: type[ToyLearner]) -> LearnerFactory:
    return lambda seed: kind(TOY_WORLD, np.random.default_rng(seed))


def _grid_teacher(seed: int) -> TaskTeacher:
    return TaskTeacher(TOY_WORLD, "feedback", seed)


def test_the_toy_learner_passes_every_check():
    """The broken learners below differ from it by their defect alone."""
    check_label_free_interface(_toy(ToyLearner))
    for check in SESSION_CHECKS.values():
        check(_toy(ToyLearner), _grid_teacher, STEPS)


def _interface(make_learner: LearnerFactory) -> None:
    check_label_free_interface(make_learner)


def _session(check: Callable[..., None]) -> Callable[[LearnerFactory], None]:
    return lambda make_learner: check(make_learner, _grid_teacher, STEPS)


BROKEN = {
    "takes a label": (TakesLabel, _interface, "observe takes"),
    "takes the target when built": (TakesTarget, _interface, "label-like parameters"),
    "uses numpy's global random state": (
        GlobalRandom, _session(check_deterministic), "proposals differ"),
    "draws from the global random states": (
        TouchesGlobalState, _session(check_deterministic), "global random state"),
    "draws when asked for its beliefs": (
        DrawingBeliefs, _session(check_deterministic), "proposals differ"),
    "is not normalised": (Unnormalised, _session(check_beliefs_well_formed), "sums to"),
    "names a best task that is not": (
        BestIsNotBest, _session(check_beliefs_well_formed), "best_task"),
    "miscounts its signals": (Miscounts, _session(check_beliefs_well_formed), "n_signals"),
    "returns beliefs that later change": (
        LiveBeliefs, _session(check_beliefs_well_formed), "once the session is over"),
    "crashes with IndexError on a wrong size": (
        IndexErrorOnWrongSize, _session(check_rejects_malformed_signals), "raised IndexError"),
    "keeps a trace of a rejected signal": (
        KeepsRejected, _session(check_rejects_malformed_signals), "beliefs differ"),
    "says not what is wrong": (
        VagueError, _session(check_rejects_malformed_signals), "does not say what is wrong"),
}


@pytest.mark.parametrize("defect", BROKEN)
def test_each_check_catches_a_learner_that_breaks_its_rule(defect):
    kind, check, message = BROKEN[defect]
    with pytest.raises(AssertionError, match=message):
        check(_toy(kind))
