"""One interface for every learner of tasks from unlabelled interaction, and its adapters.

A learner (`Learner`) proposes an action in a state, observes the signal the user
produced after it, and reports its beliefs over the tasks; after its construction it never
receives a label or the user's target. `TaskLearner`
(the calibration-free learner and the calibrated baseline) meets the protocol as it is; the
other learners meet it through an adapter built with the same arguments as the learner it
wraps (`learner`):

* `FrameHypothesesAdapter`: the (task, frame) pairs of
  `FrameHypothesesLearner` are its tasks;
* `PuddleLearnerAdapter`: the puddle world's 660 tasks, the normalised likelihood
  of `PuddleLearner` their confidence;
* `ContinuousLearnerAdapter`: the particles of
  `ContinuousGoalLearner` are its tasks, the
  probe point its action; it has no state (``None``).

An adapter calls the wrapped learner's methods exactly as a direct caller does, in the same
order and with the same arguments, so no random draw moves; its `beliefs` only reads
the learner (it draws nothing). It validates the signals the wrapped learner would take
unchecked (one size for a session, finite), so that a bad signal is a ``ValueError``
naming it and leaves the learner as it was.

``tests/conformance.py`` holds the checks every learner must pass (run over every learner
by ``tests/test_learner_conformance.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from calibration_free.config import LearnerConfig
from calibration_free.continuous_goals import ContinuousConfig, ContinuousGoalLearner
from calibration_free.frame_hypotheses import FrameHypothesesLearner
from calibration_free.learner import Proposal
from calibration_free.puddle import PuddleWorld
from calibration_free.puddle_learner import PuddleConfig, PuddleLearner
from calibration_free.world import World
from decoding.validation import check_array

#: The confidence rule whose confidences sum to 1 over the tasks (a key of
#: `calibration_free.likelihood.CONFIDENCES`).
NORMALISED = "normalised"
#: The continuous learner's confidence rule: each particle's pairwise-min normal-difference
#: probability over sampled classifiers (`calibration_free.sampled_confidence`).
SAMPLED = "sampled"


@runtime_checkable
class TaskBeliefs(Protocol):
    """What every learner's beliefs tell (`calibration_free.learner.Beliefs` has
    more).

    Attributes
    ----------
    confidence : ndarray, shape (n_tasks,)
        Every task's confidence, in [0, 1]; summing to 1 when ``rule`` is
        `NORMALISED`.
    best_task : int
        The task the learner would pick, in ``[0, n_tasks)``.
    confident : bool
        Whether the learner is confident about ``best_task`` (would declare it).
    n_signals : int
        Signals observed so far.
    rule : str
        The confidence rule (`NORMALISED`, "pairwise", `SAMPLED`).
    """

    @property
    def confidence(self) -> np.ndarray: ...

    @property
    def best_task(self) -> int: ...

    @property
    def confident(self) -> bool: ...

    @property
    def n_signals(self) -> int: ...

    @property
    def rule(self) -> str: ...


@runtime_checkable
class ProposalLike(Protocol):
    """A proposed action (`Proposal`,
    `PointProposal`).

    Attributes
    ----------
    action : int or ndarray
        An action index of the world, or a point of the plane, shape (2,).
    declares_target : bool
        Whether performing the action declares a target reached.
    """

    @property
    def action(self) -> Any: ...

    @property
    def declares_target(self) -> bool: ...


@runtime_checkable
class Learner(Protocol):
    """A learner of the user's task from unlabelled signals.

    The state is what the learner chooses from: a state index (discrete worlds), a point
    of the plane, shape (2,) (the puddle world), or None (the continuous world's learner,
    which probes points of its choice). After its construction a learner never receives a
    label or the target: its inputs are ``(state, action, signal)`` only.

    Attributes
    ----------
    n_signals : int
        Signals observed so far.
    """

    @property
    def n_signals(self) -> int: ...

    def propose(self, state: Any) -> ProposalLike:
        """The next action from ``state`` (may draw from the learner's generator)."""
        ...

    def observe(self, state: Any, action: Any, signal: np.ndarray) -> None:
        """Take in the signal, shape (d,), the user produced after ``action`` in ``state``;
        a signal of another size than the session's first, or not finite, is a
        ``ValueError`` that leaves the learner as it was."""
        ...

    def beliefs(self) -> TaskBeliefs:
        """The current beliefs over the tasks (draws nothing)."""
        ...


@dataclass(frozen=True, eq=False)
class PointProposal:
    """A point of the plane to probe (the continuous learner's action).

    Attributes
    ----------
    action : ndarray, shape (2,)
        The probe point, in ``[0, 1]^2``.
    declares_target : bool
        Always False: the continuous learner declares no target.
    """

    action: np.ndarray
    declares_target: bool = False


@dataclass(frozen=True)
class AdaptedBeliefs:
    """An adapter's beliefs: the fields of `TaskBeliefs`.

    Attributes
    ----------
    confidence : ndarray, shape (n_tasks,)
        A copy of the learner's confidences, in [0, 1].
    best_task : int
    confident : bool
    n_signals : int
    rule : str
    """

    confidence: np.ndarray
    best_task: int
    confident: bool
    n_signals: int
    rule: str


class _SignalSize:
    """The checks of signals a wrapped learner takes unchecked: finite numbers, shape
    (d,), ``d`` fixed by the first signal accepted."""

    def __init__(self) -> None:
        self.n_features: int | None = None

    def check(self, signal: np.ndarray) -> None:
        """Raise ``ValueError`` naming what is wrong with ``signal``; fix ``d`` from the
        first good one. The signal itself is not converted (the learner gets it as is)."""
        x = check_array("signal", signal, shape=(self.n_features,), dtype=np.float64)
        if x.shape[0] == 0:
            raise ValueError("signal is empty")
        self.n_features = x.shape[0]


def _check_point(name: str, point: Any) -> None:
    """Raise ``ValueError`` unless ``point`` is a finite point of ``[0, 1]^2``."""
    x = check_array(name, point, shape=(2,), dtype=np.float64)
    if not np.all((x >= 0.0) & (x <= 1.0)):
        raise ValueError(f"{name} must lie in [0, 1]^2; got {x.tolist()}")


def _check_no_state(state: Any) -> None:
    """Raise ``ValueError`` unless ``state`` is None (the continuous learner has none)."""
    if state is not None:
        raise ValueError(f"the continuous learner has no state: state must be None; got {state!r}")


class FrameHypothesesAdapter:
    """`FrameHypothesesLearner` as a
    `Learner`: its tasks are the (task, frame) hypotheses ``f * n_tasks + t``.

    Parameters
    ----------
    world, frames, config, rng
        As `FrameHypothesesLearner`'s.

    Attributes
    ----------
    learner : FrameHypothesesLearner
    """

    def __init__(
        self,
        world: World,
        frames: tuple[str, ...] = ("feedback", "guidance"),
        config: LearnerConfig | None = None,
        rng: np.random.Generator | int | None = None,
    ) -> None:
        self.learner = FrameHypothesesLearner(world, frames, config, rng)
        self._n_signals = 0

    @property
    def n_signals(self) -> int:
        return self._n_signals

    def propose(self, state: int) -> Proposal:
        """A uniform action (never a declaration)."""
        return self.learner.propose(state)

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        """Every frame's learner takes in the signal (each validates it first)."""
        self.learner.observe(state, action, signal)
        self._n_signals += 1

    def beliefs(self) -> AdaptedBeliefs:
        """The pairs' pairwise confidence; confident only beyond chance."""
        pairs = self.learner.beliefs()
        return AdaptedBeliefs(
            pairs.confidence, pairs.best, pairs.confident, self._n_signals, "pairwise"
        )


class PuddleLearnerAdapter:
    """`PuddleLearner` as a `Learner`.

    The state is the agent's point, shape (2,); the beliefs are the 660 tasks' normalised
    likelihoods of the last update (`PuddleLearner.probabilities`); it declares
    nothing.

    Parameters
    ----------
    world, config, rng
        As `PuddleLearner`'s.

    Attributes
    ----------
    learner : PuddleLearner
    """

    def __init__(self, world: PuddleWorld, config: PuddleConfig, rng: np.random.Generator) -> None:
        self.learner = PuddleLearner(world, config, rng)
        self._signals = _SignalSize()
        self._n_signals = 0

    @property
    def n_signals(self) -> int:
        return self._n_signals

    def propose(self, state: np.ndarray) -> Proposal:
        """The learner's action at ``state``, shape (2,)."""
        _check_point("state", state)
        return Proposal(self.learner.propose(state), False)

    def observe(self, state: np.ndarray, action: int, signal: np.ndarray) -> None:
        """Check the inputs, then pass them on (the learner updates on its schedule)."""
        _check_point("state", state)
        n_actions = self.learner.world.n_actions
        if not 0 <= int(action) < n_actions or int(action) != action:
            raise ValueError(f"action must be in [0, {n_actions}); got {action!r}")
        self._signals.check(signal)
        self.learner.observe(state, action, signal)
        self._n_signals += 1

    def beliefs(self) -> AdaptedBeliefs:
        """The tasks' normalised likelihoods after the last update (uniform before)."""
        probabilities = self.learner.probabilities.copy()
        return AdaptedBeliefs(
            probabilities, int(np.argmax(probabilities)), False, self._n_signals, NORMALISED
        )


class ContinuousLearnerAdapter:
    """`ContinuousGoalLearner` as a
    `Learner`.

    It has no state (``None``); its action is the probe point, shape (2,); its tasks are
    the current particles (`ContinuousGoalLearner.particles`, resampled by every
    proposal after the initial probes), their confidence ``W`` of the last observation. It
    declares nothing.

    Parameters
    ----------
    config, rng
        As `ContinuousGoalLearner`'s.

    Attributes
    ----------
    learner : ContinuousGoalLearner
    """

    def __init__(self, config: ContinuousConfig, rng: np.random.Generator) -> None:
        self.learner = ContinuousGoalLearner(config, rng)
        self._signals = _SignalSize()

    @property
    def n_signals(self) -> int:
        return self.learner.n_signals

    def propose(self, state: None = None) -> PointProposal:
        """Resample the particles (after the initial probes); the next probe point."""
        _check_no_state(state)
        return PointProposal(self.learner.propose())

    def observe(self, state: None, action: np.ndarray, signal: np.ndarray) -> None:
        """Check the inputs, then give the learner the signal answering the probe point
        ``action``, shape (2,)."""
        _check_no_state(state)
        _check_point("action (the probe point)", action)
        self._signals.check(signal)
        self.learner.observe(action, signal)

    def beliefs(self) -> AdaptedBeliefs:
        """The particles' confidence; the best is the learner's estimate."""
        confidence = self.learner.confidence.copy()
        return AdaptedBeliefs(
            confidence, int(np.argmax(confidence)), False, self.learner.n_signals, SAMPLED
        )

