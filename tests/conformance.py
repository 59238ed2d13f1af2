"""Conformance checks of a learner (`calibration_free.protocol.Learner`), in the spirit
of scikit-learn's ``check_estimator``: plain functions raising ``AssertionError``.

Each check takes ``make_learner`` (a seed -> a fresh learner built on that seed) and, for
those that run sessions, ``make_teacher`` (a seed -> a fresh `Teacher`: the world
and a simulated user answering from labelled data) and a number of steps:

* `check_label_free_interface`: after its construction the learner never receives a
  label or the target: ``propose(state)``, ``observe(state, action, signal)`` and
  ``beliefs()`` take exactly those parameters, and the only label-like constructor
  parameters are the declared calibration inputs (the calibrated baseline's);
* `check_learns_from_signals_alone`: a closed-loop session with the labelled teacher
  is replayed step for step by a fresh learner given the recorded states and signals
  alone (no teacher, labels or target exist for it);
* `check_deterministic`: two learners of one seed fed the same signals propose the
  same actions and end with equal beliefs, whether their beliefs are read at every step
  or not (reading them draws nothing), and neither touches the global random states;
* `check_beliefs_well_formed`: at every step, the beliefs meet
  `TaskBeliefs`, are finite, the confidence in [0, 1]
  (summing to 1 where the rule is "normalised"), ``best_task`` a task of the largest
  confidence, ``n_signals`` the count observed; beliefs already returned do not change;
* `check_rejects_malformed_signals`: a signal of the wrong size, of two dimensions
  or holding NaN (the first signal too) is a ``ValueError`` whose message names the
  signal and what is wrong, and the learner goes on exactly as one that never saw it.

`check_learner` runs them all. The learner gets every signal as a read-only float32
copy (the wire format), never the dataset row itself.
"""

from __future__ import annotations

import copy
import dataclasses
import inspect
import random
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from acquisition.cardinal_teacher import CardinalTeacher
from acquisition.gaussian import generate_gaussian_features
from acquisition.labelled import LabelledFeatures
from acquisition.mixed_teacher import MixedTeacher
from acquisition.user import SimulatedUser
from calibration_free.protocol import NORMALISED, Learner, ProposalLike, TaskBeliefs
from calibration_free.puddle import MIXED_LABELS, PuddleWorld
from calibration_free.streams import session_streams, world_stream
from calibration_free.world import World, transition_draws

#: The parameters of the protocol's methods, exactly (no label, no target, no ``**kwargs``).
PROTOCOL_PARAMETERS: dict[str, tuple[str, ...]] = {
    "propose": ("state",),
    "observe": ("state", "action", "signal"),
    "beliefs": (),
}
#: Words of a parameter name (split at "_") that make it a label or target input.
LABEL_WORDS = frozenset(
    {"label", "labels", "target", "targets", "truth", "true", "goal", "goals", "task", "y",
     "answer", "answers"}
)
#: Tolerance of sums and comparisons that rounding may move.
TOLERANCE = 1e-9


class Teacher(Protocol):
    """A world and a simulated user with a hidden target, answering from labelled data."""

    def start(self) -> Any:
        """The state of the first proposal."""
        ...

    def answer(self, state: Any, proposal: ProposalLike) -> tuple[np.ndarray, Any]:
        """The signal, shape (d,), answering ``proposal`` made in ``state``, and the next
        state."""
        ...


LearnerFactory = Callable[[int], Learner]
TeacherFactory = Callable[[int], Teacher]


@dataclass
class Session:
    """What a closed-loop session passed the learner, step by step.

    Attributes
    ----------
    states : list
        The state of every proposal.
    proposals : list of ProposalLike
    signals : list of ndarray, shape (d,) float32
        The read-only signals observed.
    """

    states: list[Any] = dataclasses.field(default_factory=list)
    proposals: list[ProposalLike] = dataclasses.field(default_factory=list)
    signals: list[np.ndarray] = dataclasses.field(default_factory=list)


def wire_signal(signal: np.ndarray) -> np.ndarray:
    """A read-only float32 copy of a dataset row (shape (d,)): all a learner is given."""
    copied = np.array(signal, dtype=np.float32)
    copied.flags.writeable = False
    return copied


def run_session(
    learner: Learner,
    teacher: Teacher,
    steps: int,
    on_step: Callable[[int, Learner], None] | None = None,
) -> Session:
    """``steps`` closed-loop steps: propose, the teacher's signal, observe.

    ``on_step(n_observed, learner)`` is called before the first step and after every
    observation.
    """
    session, state = Session(), teacher.start()
    if on_step is not None:
        on_step(0, learner)
    for step in range(1, steps + 1):
        proposal = learner.propose(state)
        signal, next_state = teacher.answer(state, proposal)
        signal = wire_signal(signal)
        learner.observe(state, proposal.action, signal)
        session.states.append(state)
        session.proposals.append(proposal)
        session.signals.append(signal)
        if on_step is not None:
            on_step(step, learner)
        state = next_state
    return session


def run_in_turn(
    first: Learner,
    second: Learner,
    make_teacher: TeacherFactory,
    steps: int,
    seed: int,
    before_first_observes: Callable[[int, Any, Any, np.ndarray], None],
) -> None:
    """Step two learners in turn, each with its teacher of ``seed``, asserting at every
    step that they propose the same; ``before_first_observes(step, state, action,
    signal)`` is called before the first learner observes each step's signal."""
    teachers = make_teacher(seed), make_teacher(seed)
    states = [teacher.start() for teacher in teachers]
    for step in range(1, steps + 1):
        proposals = first.propose(states[0]), second.propose(states[1])
        assert_same_proposal(*proposals, f"step {step}")
        answers = [
            teacher.answer(state, proposal)
            for teacher, state, proposal in zip(teachers, states, proposals, strict=True)
        ]
        signals = [wire_signal(signal) for signal, _ in answers]
        before_first_observes(step, states[0], proposals[0].action, signals[0])
        for learner, state, proposal, signal in zip(
            (first, second), states, proposals, signals, strict=True
        ):
            learner.observe(state, proposal.action, signal)
        states = [next_state for _, next_state in answers]


# --- the checks ----------------------------------------------------------------------------


def check_label_free_interface(
    make_learner: LearnerFactory, calibration_inputs: tuple[str, ...] = ()
) -> None:
    """The learner meets the protocol; its methods take exactly the protocol's parameters;
    its label-like constructor parameters are exactly ``calibration_inputs``."""
    learner = make_learner(0)
    name = type(learner).__name__
    assert isinstance(learner, Learner), (
        f"{name} does not meet the Learner protocol (n_signals, propose, observe, beliefs)"
    )
    for method, expected in PROTOCOL_PARAMETERS.items():
        parameters = tuple(inspect.signature(getattr(learner, method)).parameters)
        assert parameters == expected, (
            f"{name}.{method} takes {parameters}; the protocol's are exactly {expected} "
            "(no label or target may reach a learner after its construction)"
        )
    constructor = inspect.signature(type(learner)).parameters
    label_like = tuple(p for p in constructor if LABEL_WORDS & set(p.lower().split("_")))
    assert set(label_like) == set(calibration_inputs), (
        f"{name}'s constructor takes the label-like parameters {label_like}; declared "
        f"calibration inputs: {calibration_inputs}"
    )


def check_learns_from_signals_alone(
    make_learner: LearnerFactory, make_teacher: TeacherFactory, steps: int, seed: int = 1
) -> None:
    """A session with the labelled teacher, then a fresh learner given only the recorded
    states and signals: it proposes the same actions and ends with the same beliefs."""
    learner = make_learner(seed)
    recorded = run_session(learner, make_teacher(seed), steps)
    replay = make_learner(seed)
    for step, (state, proposal, signal) in enumerate(
        zip(recorded.states, recorded.proposals, recorded.signals, strict=True), start=1
    ):
        proposed = replay.propose(state)
        assert_same_proposal(proposed, proposal, f"step {step} of the replay")
        replay.observe(state, proposed.action, signal)
    assert_same_beliefs(replay.beliefs(), learner.beliefs(), "after the replay")


def check_deterministic(
    make_learner: LearnerFactory, make_teacher: TeacherFactory, steps: int, seed: int = 2
) -> None:
    """Two learners of one seed, stepped in turn with teachers of one seed: the same
    proposals and final beliefs (the first one's beliefs read at every step), and the
    global random states (``numpy.random``, ``random``) untouched."""
    numpy_state = np.random.get_state()  # noqa: NPY002 - the global state it must not touch
    python_state = random.getstate()
    first, second = make_learner(seed), make_learner(seed)
    run_in_turn(first, second, make_teacher, steps, seed, lambda *_: first.beliefs())
    assert_same_beliefs(first.beliefs(), second.beliefs(), f"after {steps} steps")
    assert _same_numpy_state(np.random.get_state(), numpy_state), (  # noqa: NPY002
        f"{type(first).__name__} draws from numpy's global random state"
    )
    assert random.getstate() == python_state, (
        f"{type(first).__name__} draws from the random module's global state"
    )


def check_beliefs_well_formed(
    make_learner: LearnerFactory, make_teacher: TeacherFactory, steps: int, seed: int = 3
) -> None:
    """The beliefs before the first signal and after every one are well formed (see
    `assert_well_formed`), the number of tasks does not change, and beliefs returned
    earlier are not changed by later observations."""
    n_tasks: list[int] = []
    kept: list[tuple[TaskBeliefs, TaskBeliefs]] = []

    def inspect_beliefs(n_observed: int, learner: Learner) -> None:
        beliefs = learner.beliefs()
        where = f"after {n_observed} signal(s)"
        n_tasks.append(assert_well_formed(beliefs, n_observed, where))
        assert learner.n_signals == n_observed, (
            f"{where}: the learner's n_signals is {learner.n_signals}"
        )
        assert len(set(n_tasks)) == 1, f"{where}: the number of tasks changed: {n_tasks}"
        kept.append((beliefs, copy.deepcopy(beliefs)))

    run_session(make_learner(seed), make_teacher(seed), steps, inspect_beliefs)
    for n_observed, (returned, snapshot) in enumerate(kept):
        assert_same_beliefs(
            returned, snapshot,
            f"the beliefs returned after {n_observed} signal(s), once the session is over",
        )


def check_rejects_malformed_signals(
    make_learner: LearnerFactory, make_teacher: TeacherFactory, steps: int, seed: int = 4
) -> None:
    """At the first step, signals of two dimensions and holding NaN, and halfway through
    the session these and signals one value short and one too long, are each a
    ``ValueError`` naming the signal and what is wrong (`malformed_signals`); the
    learner then goes on as a learner of the same seed that never saw them."""
    learner, reference = make_learner(seed), make_learner(seed)

    def offer_malformed(step: int, state: Any, action: Any, signal: np.ndarray) -> None:
        if step in (1, steps // 2 + 1):
            for bad, what in malformed_signals(signal, size_known=step > 1):
                _assert_rejected(learner, state, action, bad, what, step)

    run_in_turn(learner, reference, make_teacher, steps, seed, offer_malformed)
    assert_same_beliefs(
        learner.beliefs(), reference.beliefs(), "after the rejected signals and the session"
    )
    assert learner.n_signals == steps, (
        f"n_signals is {learner.n_signals} after {steps} accepted signals (rejected ones "
        "counted?)"
    )


def check_learner(
    make_learner: LearnerFactory,
    make_teacher: TeacherFactory,
    steps: int,
    calibration_inputs: tuple[str, ...] = (),
) -> None:
    """Every check of this module."""
    check_label_free_interface(make_learner, calibration_inputs)
    check_learns_from_signals_alone(make_learner, make_teacher, steps)
    check_deterministic(make_learner, make_teacher, steps)
    check_beliefs_well_formed(make_learner, make_teacher, steps)
    check_rejects_malformed_signals(make_learner, make_teacher, steps)


# --- the assertions the checks share -------------------------------------------------------


def malformed_signals(signal: np.ndarray, size_known: bool) -> list[tuple[np.ndarray, str]]:
    """Bad variants of a good signal, shape (d,), each with a regular expression that the
    rejection's message must match (besides naming the signal): of two dimensions and
    holding NaN, and, once the learner knows the session's size ``size_known``, one value
    short and one too long."""
    d = len(signal)
    nan = signal.copy()
    nan[0] = np.nan
    variants = [(signal[None], r"dimension|shape"), (nan, r"nan")]
    if size_known:
        variants += [
            (signal[:-1].copy(), rf"\b{d - 1}\b.*\b{d}\b|\b{d}\b.*\b{d - 1}\b"),
            (np.append(signal, signal[0]), rf"\b{d + 1}\b.*\b{d}\b|\b{d}\b.*\b{d + 1}\b"),
        ]
    return variants


def _assert_rejected(
    learner: Learner, state: Any, action: Any, signal: np.ndarray, what: str, step: int
) -> None:
    name, shape = type(learner).__name__, signal.shape
    try:
        learner.observe(state, action, signal)
    except ValueError as error:
        message = str(error)
        assert "signal" in message.lower() and re.search(what, message, re.IGNORECASE), (
            f"{name} rejected a bad signal of shape {shape} at step {step} with a message "
            f"that does not say what is wrong ({what!r}): {message!r}"
        )
    except Exception as error:
        raise AssertionError(
            f"{name} raised {type(error).__name__} ({error}) on a bad signal of shape {shape} "
            f"at step {step}; expected a ValueError naming the signal"
        ) from error
    else:
        raise AssertionError(
            f"{name} accepted a bad signal of shape {shape} at step {step} ({what!r})"
        )


def assert_well_formed(beliefs: TaskBeliefs, n_observed: int, where: str) -> int:
    """The beliefs meet `TaskBeliefs`, every array and number in them is finite,
    the confidence lies in [0, 1] (summing to 1 under the "normalised" rule),
    ``best_task`` is a task of the largest confidence, ``confident`` a bool and
    ``n_signals`` equal to ``n_observed``. Returns the number of tasks."""
    assert isinstance(beliefs, TaskBeliefs), (
        f"{where}: {type(beliefs).__name__} lacks a field of TaskBeliefs "
        "(confidence, best_task, confident, n_signals, rule)"
    )
    confidence = beliefs.confidence
    assert isinstance(confidence, np.ndarray) and confidence.ndim == 1 and confidence.size, (
        f"{where}: confidence must be an array of shape (n_tasks,); got {confidence!r}"
    )
    for field, value in _fields(beliefs).items():
        floats = isinstance(value, np.ndarray | float | np.floating)
        if floats and np.asarray(value).dtype.kind == "f":
            assert np.all(np.isfinite(value)), f"{where}: {field} is not finite: {value}"
    assert np.all((confidence >= 0.0) & (confidence <= 1.0)), (
        f"{where}: confidence outside [0, 1]: {confidence}"
    )
    assert isinstance(beliefs.rule, str), f"{where}: rule must be a str; got {beliefs.rule!r}"
    if beliefs.rule == NORMALISED:
        total = float(confidence.sum())
        assert abs(total - 1.0) <= TOLERANCE * confidence.size, (
            f"{where}: the {NORMALISED!r} confidence sums to {total!r}, not 1"
        )
    best = beliefs.best_task
    assert isinstance(best, int | np.integer) and 0 <= best < confidence.size, (
        f"{where}: best_task {best!r} is not one of the {confidence.size} tasks"
    )
    assert confidence[best] >= confidence.max() - TOLERANCE, (
        f"{where}: best_task {best} has confidence {confidence[best]}, below the largest "
        f"{confidence.max()}"
    )
    assert isinstance(beliefs.confident, bool | np.bool_), (
        f"{where}: confident must be a bool; got {beliefs.confident!r}"
    )
    assert beliefs.n_signals == n_observed, (
        f"{where}: beliefs.n_signals is {beliefs.n_signals}, the learner observed {n_observed}"
    )
    return confidence.size


def assert_same_proposal(first: ProposalLike, second: ProposalLike, where: str) -> None:
    """Equal actions (indices or points) and declarations."""
    assert np.array_equal(first.action, second.action) and (
        first.declares_target == second.declares_target
    ), f"{where}: proposals differ: {first} vs {second}"


def assert_same_beliefs(first: TaskBeliefs, second: TaskBeliefs, where: str) -> None:
    """Equal beliefs: every field (of a dataclass: all of them) equal, arrays exactly."""
    assert type(first) is type(second), (
        f"{where}: beliefs of types {type(first).__name__} and {type(second).__name__}"
    )
    fields_first, fields_second = _fields(first), _fields(second)
    for field, value in fields_first.items():
        other = fields_second[field]
        same = np.array_equal(value, other) if isinstance(value, np.ndarray) else value == other
        assert same, f"{where}: beliefs differ in {field}: {value!r} vs {other!r}"


def _fields(beliefs: TaskBeliefs) -> dict[str, Any]:
    """Every field of a dataclass's beliefs, else the protocol's."""
    if dataclasses.is_dataclass(beliefs):
        return {f.name: getattr(beliefs, f.name) for f in dataclasses.fields(beliefs)}
    return {
        name: getattr(beliefs, name)
        for name in ("confidence", "best_task", "confident", "n_signals", "rule")
    }


def _same_numpy_state(first: tuple[Any, ...], second: tuple[Any, ...]) -> bool:
    return all(
        np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b
        for a, b in zip(first, second, strict=True)
    )


# --- teachers of the project's worlds ----------------------------------------------------


def gaussian_data(
    n_classes: int, seed: int, n_features: int = 4, accuracy: float = 0.9
) -> LabelledFeatures:
    """Labelled Gaussian signals of a session seed's data stream: 40 per class, shape
    (40 n_classes, n_features), of nominal balanced accuracy ``accuracy``."""
    return generate_gaussian_features(
        40, n_classes, n_features, accuracy, session_streams(seed)[0]
    )


class TaskTeacher:
    """A discrete world with the simulated user (`acquisition.user.SimulatedUser`)
    of a session seed's user stream; a declared target makes it pick a new one; a move's
    outcome takes its draw from the seed's world stream.

    Parameters
    ----------
    world : World
    frame : {"feedback", "guidance"}
    seed : int
    """

    def __init__(self, world: World, frame: str, seed: int) -> None:
        n_classes = 2 if frame == "feedback" else len(world.guidance_actions)
        self.world, self.data = world, gaussian_data(n_classes, seed)
        self.user = SimulatedUser(world, frame, self.data.labels, session_streams(seed)[1])
        self._draws = transition_draws(seed)
        self._step = 0

    def start(self) -> int:
        return self.user.start_state

    def answer(self, state: int, proposal: ProposalLike) -> tuple[np.ndarray, int]:
        index, _ = self.user.answer(state, proposal.action)
        if proposal.declares_target:
            self.user.new_target()
        self._step += 1
        return self.data.features[index], self.world.step(
            state, proposal.action, self._draws.uniform(self._step)
        )


class ContinuousTeacher:
    """The continuous world's teacher (`acquisition.cardinal_teacher.CardinalTeacher`)
    of a session seed: it answers probe points; there is no state."""

    def __init__(self, seed: int) -> None:
        self.data = gaussian_data(4, seed)
        self.teacher = CardinalTeacher(self.data.labels, session_streams(seed)[1])

    def start(self) -> None:
        return None

    def answer(self, state: None, proposal: ProposalLike) -> tuple[np.ndarray, None]:
        index, _ = self.teacher.answer(proposal.action)
        return self.data.features[index], None


class PuddleTeacher:
    """The puddle world's teacher (`acquisition.mixed_teacher.MixedTeacher`) of a
    session seed; the moves and restarts (on entering the goal cell) draw from the seed's
    world stream.

    Parameters
    ----------
    world : PuddleWorld
        Its tables built (shared: they take seconds).
    seed : int
    """

    def __init__(self, world: PuddleWorld, seed: int) -> None:
        self.world, self.data = world, gaussian_data(len(MIXED_LABELS), seed)
        self.teacher = MixedTeacher(world, self.data.labels, session_streams(seed)[1])
        self._moves = world_stream(seed)

    def start(self) -> np.ndarray:
        return self._moves.uniform(size=2)

    def answer(self, state: np.ndarray, proposal: ProposalLike) -> tuple[np.ndarray, np.ndarray]:
        index, _ = self.teacher.answer(state, proposal.action)
        state = self.world.move(state, proposal.action, self._moves)
        if self.world.task_cell(state) == self.world.tasks[self.teacher.task].goal:
            state = self._moves.uniform(size=2)
        return self.data.features[index], state
