"""A prior from earlier sessions of the same user, and the learner that starts from it.

A returning user's earlier sessions hold what a calibration phase would give: signals and
labels, the labels the learner adopted at its declared targets (never the truth, which a
lab does not have). A `Prior` holds them, session by session (read from recordings
by `replay.prior`), with the `FeatureSpace` they were recorded in; it carries
no task information (no state, action or target of the earlier sessions).

How the prior enters: as weighted pseudo-observations in every hypothesis's shared
statistics (`Prior.pseudo_observations`,
`calibration_free.learner.CalibrationFreeLearner.adopt_prior`). The learner starts as
after a target on a history made of the prior's signals with their labels adopted: the
decoders of every task are fitted from the first signal with the prior's labelled signals
in their training sets (and in the cross-validated confusion), the shrinkage is chosen on
the prior's labels, and the first segment's evidence is calibrated on them (the
normalised-likelihood rule). A pseudo-observation of weight 1 is exactly a signal observed
live; weights are:

* each distinct epoch counted once: copies of one epoch (the same float32 vector; a small
  dataset's epochs recur within and across sessions) share its weight, so the prior's
  effective sample size is counted in distinct epochs;
* several earlier sessions weighted by recency: the most recent 1, the one before
  ``recency`` (default 0.5), then ``recency ** 2``, ...; a distinct epoch takes its most
  recent session's weight;
* times ``weight`` (default 1): a weaker prior (another user's, a population's) below 1.

The prior's weight fades as today's evidence grows by dilution: its pseudo-observations
keep their weight and today's signals join them, so after ``n`` signals today's share of
the training sets is ``n / (n + n_prior)``. The power prior does not use it (its form after
a target, on today's signals: a day's signal power may differ).

A prior that is wrong costs nothing: `ReturningLearner` runs the blank learner (no
prior) beside the informed one, both observing every signal, and compares them as two
models of today's signals (`PriorCheck`): it trusts the prior (and drops the blank
learner) or falls back to learning from scratch (the blank learner, which has seen every
signal of today, acts from then on) when one explains today's signals clearly better.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from itertools import pairwise
from typing import Any

import numpy as np
from scipy.special import logsumexp

from calibration_free.config import LearnerConfig
from calibration_free.frames import Frame
from calibration_free.learner import Beliefs, CalibrationFreeLearner, Proposal
from calibration_free.power_prior import LogPowerEvidence
from calibration_free.task_decoders import TaskHistory
from calibration_free.world import World
from decoding.validation import check_array, check_range

#: Weight of an earlier session's epochs relative to those of the next more recent one.
DEFAULT_RECENCY = 0.5


@dataclass(frozen=True)
class FeatureSpace:
    """What a learner's signals are: a prior is usable only in the space it was made in.

    Attributes
    ----------
    n_features : int
        Size of the learner's feature vector.
    frame : str
        The interaction frame the labels belong to.
    n_classes : int
        Classes of the labels.
    sfreq, tmin, ch_names :
        For features extracted from raw epochs: the epochs' sampling frequency (Hz), first
        sample time (s) and channels; None for feature vectors given as they are.
    extractor : tuple of (str, object) pairs, or None
        The feature extractor's settings (features of raw epochs), else None.
    """

    n_features: int
    frame: str
    n_classes: int
    sfreq: float | None = None
    tmin: float | None = None
    ch_names: tuple[str, ...] | None = None
    extractor: tuple[tuple[str, Any], ...] | None = None

    def differences(self, other: FeatureSpace) -> list[str]:
        """Every field that differs, as ``"name: this vs other"``."""
        return [
            f"{f.name}: {getattr(self, f.name)!r} vs {getattr(other, f.name)!r}"
            for f in fields(self)
            if getattr(self, f.name) != getattr(other, f.name)
        ]


@dataclass(frozen=True)
class PriorSession:
    """One earlier session's labelled signals.

    Attributes
    ----------
    signals : ndarray, shape (n, n_features), float32
        The learner's inputs (feature vectors), in the session's order.
    labels : ndarray, shape (n, n_classes)
        The label weights the learner adopted for each (rows sum to 1).
    source : str
        Where they came from (a recording's path).
    """

    signals: np.ndarray
    labels: np.ndarray
    source: str

    def __post_init__(self) -> None:
        signals = check_array("prior signals", self.signals, shape=(None, None))
        labels = check_array("prior labels", self.labels, shape=(len(signals), None))
        if len(signals) == 0:
            raise ValueError(f"{self.source}: a prior session needs labelled signals; it has none")
        if not np.allclose(labels.sum(axis=1), 1.0) or np.any(labels < 0):
            raise ValueError(f"{self.source}: prior label weights must be >= 0, rows summing to 1")


@dataclass(frozen=True)
class Prior:
    """Earlier sessions of a user as a prior (see the module docstring).

    Attributes
    ----------
    sessions : tuple of PriorSession
        Most recent first.
    space : FeatureSpace
        The feature space of every session.
    recency : float, default 0.5
        Weight of a session relative to the next more recent one, in (0, 1].
    weight : float, default 1
        Weight of a distinct epoch of the most recent session relative to a signal of
        today, > 0.
    """

    sessions: tuple[PriorSession, ...]
    space: FeatureSpace
    recency: float = DEFAULT_RECENCY
    weight: float = 1.0

    def __post_init__(self) -> None:
        if not self.sessions:
            raise ValueError("a prior needs at least one earlier session")
        check_range("prior recency", self.recency, 0.0, 1.0)
        if not self.recency > 0 or not self.weight > 0:
            raise ValueError(
                f"prior recency and weight must be > 0; got {self.recency}, {self.weight}"
            )
        for session in self.sessions:
            shape = (self.space.n_features, self.space.n_classes)
            if (session.signals.shape[1], session.labels.shape[1]) != shape:
                raise ValueError(
                    f"{session.source}: {session.signals.shape[1]} features and "
                    f"{session.labels.shape[1]} classes; the prior's space has {shape}"
                )

    def check_space(self, space: FeatureSpace) -> None:
        """Raise a ``ValueError`` saying what differs if ``space`` (the session's) is not
        the prior's."""
        differences = self.space.differences(space)
        if differences:
            sources = ", ".join(session.source for session in self.sessions)
            raise ValueError(
                f"the prior ({sources}) was recorded in another feature space than the "
                f"session's (prior vs session): {'; '.join(differences)}"
            )

    def pseudo_observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The prior's signals, label weights and weights, most recent session last.

        Returns
        -------
        signals : ndarray, shape (n, n_features), float32
        labels : ndarray, shape (n, n_classes)
        weights : ndarray, shape (n,)
            ``weight * recency ** age``, the copies of one epoch (equal float32 vectors)
            sharing it in proportion to their sessions' weights, its total that of the most
            recent session it appears in.
        """
        ordered = self.sessions[::-1]
        signals = np.concatenate([np.asarray(s.signals, np.float32) for s in ordered])
        labels = np.concatenate([np.asarray(s.labels, float) for s in ordered])
        ages = np.concatenate(
            [np.full(len(s.signals), len(ordered) - 1 - i) for i, s in enumerate(ordered)]
        )
        recency = self.recency ** ages.astype(float)
        _, epoch = np.unique(signals, axis=0, return_inverse=True)
        epoch = epoch.ravel()
        share = recency / np.bincount(epoch, weights=recency)[epoch]
        most_recent = np.zeros(epoch.max() + 1)
        np.maximum.at(most_recent, epoch, recency)
        return signals, labels, self.weight * share * most_recent[epoch]

    @property
    def effective_size(self) -> float:
        """The sum of the pseudo-observations' weights (distinct epochs, by recency)."""
        return float(self.pseudo_observations()[2].sum())

    def complemented(self) -> Prior:
        """The prior with every label reversed (class order reversed: feedback's correct
        and error swapped), a prior adopted wrongly: for measurements."""
        return replace(
            self,
            sessions=tuple(
                replace(s, labels=s.labels[:, ::-1].copy(), source=f"{s.source} (complemented)")
                for s in self.sessions
            ),
        )

    def describe(self) -> dict[str, Any]:
        """A JSON-able description: sources, signals per session, weights."""
        return {
            "sources": [s.source for s in self.sessions],
            "signals": [len(s.signals) for s in self.sessions],
            "effective_size": self.effective_size,
            "recency": self.recency,
            "weight": self.weight,
        }


@dataclass(frozen=True)
class PriorCheck:
    """When `ReturningLearner` trusts its prior or falls back to learning from
    scratch.

    Both learners score every signal under every task: its log match ``log m_t`` against
    the prediction of the decoders fitted before it (untempered, the matching filter's
    increment). Summed over the signals of a task segment (since the last target), each
    learner's ``A_t`` is the log pseudo-likelihood of those signals under task t with its
    decoders, and ``A_t(informed) - A_t(blank)`` says, per hypothesis, whether the decoder
    trained with the prior predicts today's signals better than the one trained on today's
    alone. The check's statistic ``D`` is that difference weighted by the informed learner's
    posterior over the tasks (the softmax of its scores), summed over today's segments (a
    target ends one; both learners adopt the same labels there): nats in favour of the prior.
    In the feedback frame with the power prior, ``D`` also carries today's signals' ErrP
    power evidence (`calibration_free.power_prior.LogPowerEvidence`, per task, its
    labels adopted at targets as the learners' are) under the informed learner's posterior
    where it is negative: a prior leading to tasks whose errors carry less power loses.

    While the check is undecided, the informed learner acts while ``D >= declare``; below,
    the blank learner acts when it is confident (its target, as from scratch) or ``D < 0``,
    else the informed one, whose target is then declared only if today's signals alone
    corroborate it (`ReturningLearner.corroborated`: the blank learner's posterior of that
    task at least ``corroboration`` times its best task's and ``lift`` times the uniform
    ``1 / n_tasks``: today's signals alone raised it above what they give a task before
    any signal), else withheld (the blank learner's proposal is made instead). The prior is

    * abandoned once ``D <= -refute``: the blank learner acts from then on;
    * trusted for good once ``D >= trust``: the blank learner is dropped;
    * with a ``horizon``, after ``horizon`` signals still undecided, trusted if ``D >= 0``,
      else abandoned.

    The defaults (measured on synthetic tuning subjects, docs/decisions/0025): ``declare``,
    ``trust`` infinite and no horizon, so that every target the informed learner declares
    is corroborated, to the session's end (both learners observe every signal). At balanced
    accuracy 0.65, ``D`` stayed within a few nats for the user's own prior and another
    subject's alike: another subject's prior allowed to declare at ``D >= 1`` declared ten
    wrong targets in a session, and priors trusted at ``D >= 5`` or ``10`` (or at a horizon
    of 150 signals with ``D >= 0``) cost wrong targets once the blank learner was gone.
    A corroboration by the blank learner's best task alone (``corroboration`` 1) deadlocked
    Gaussian sessions without the power prior, where the blank learner cannot break the
    tie between a task and its mirror and the informed learner can. At 0.78, the ratio alone
    (``lift`` 0) let another subject's prior declare a target after 12 or 17 signals that
    the blank learner gave less than 1.1 / n_tasks: wrong, and both learners, having adopted
    its labels, then locked into wrong targets (2 sessions of 20); ``lift`` 1.5 withheld
    them and left the prior's speed-up unchanged.

    In the feedback frame with the power prior, the prior's own labels are checked against
    the ErrP power premise first (`power_premise`): a prior whose error-labelled
    signals carry less power than its correct ones is abandoned before the first signal. A
    prior adopted wrongly, its labels complemented, fits today's signals as well as the
    right one under the mirror task where the task set is symmetric (opposite corners): the
    signals' power is what tells them apart, as it is for the learner from scratch.

    Attributes
    ----------
    refute, declare, trust : float
        Nats.
    horizon : int or None
        Signals after which the check decides; None: never before ``refute`` or ``trust``.
    corroboration : float
        In (0, 1].
    lift : float
        At least 0 (0: the ratio to the best task's alone).
    """

    refute: float = 3.0
    declare: float = math.inf
    trust: float = math.inf
    horizon: int | None = None
    corroboration: float = 0.5
    lift: float = 1.5


@dataclass
class PriorDecision:
    """What `ReturningLearner` decided about its prior.

    Attributes
    ----------
    outcome : {"testing", "trusted", "fallen back"}
    step : int or None
        Today's signals observed when it was decided.
    statistic : list of float
        The check's statistic ``D`` after every signal while testing.
    premise : float or None
        The prior's power premise (`power_premise`), where it was checked.
    """

    outcome: str = "testing"
    step: int | None = None
    statistic: list[float] = field(default_factory=list)
    premise: float | None = None


class ReturningLearner:
    """The calibration-free learner started from a prior, checked against the blank
    learner until the prior is trusted or abandoned (see the module docstring).

    It has the learner protocol's methods (``propose``, ``observe``, ``beliefs``,
    ``n_signals``) and what the session core reads of a task learner (``history``,
    ``frame``, ``balanced_accuracy``, ...), those of the learner acting now
    (`acting`).

    Parameters
    ----------
    world : World
    config : LearnerConfig
    rng : Generator
        The session's learner stream: the blank learner's, so that a session whose prior is
        abandoned before its first signal is the session from scratch; the informed learner
        draws from a stream spawned from it (spawning draws nothing).
    prior : Prior
    check : PriorCheck, optional
    """

    def __init__(
        self,
        world: World,
        config: LearnerConfig,
        rng: np.random.Generator,
        prior: Prior,
        check: PriorCheck | None = None,
    ) -> None:
        self.prior = prior
        self.check = check or PriorCheck()
        #: The learner started from the prior, and the blank one (None once dropped).
        self.informed: CalibrationFreeLearner | None = CalibrationFreeLearner(
            world, config, rng.spawn(1)[0]
        )
        observations = prior.pseudo_observations()
        self.informed.adopt_prior(*observations)
        self.blank: CalibrationFreeLearner | None = CalibrationFreeLearner(world, config, rng)
        self.decision = PriorDecision()
        self._segment = np.zeros((2, world.n_tasks))  # A_t of the informed and blank
        self._settled = 0.0  # the decoders' part of D of the segments that targets ended
        self._difference = 0.0  # and of the current segment
        self._declared: int | None = None
        #: Today's signals' power evidence per task (feedback frame with the power prior).
        self._power = (LogPowerEvidence(world.n_tasks, 2) if self.informed.uses_power_prior
                       else None)
        if self.informed.uses_power_prior:
            self.decision.premise = power_premise(*observations)
            if self.decision.premise < 0:
                self._decide("fallen back")

    @property
    def acting(self) -> CalibrationFreeLearner:
        """The learner whose proposals are taken now (see `PriorCheck`)."""
        informed, blank = self.informed, self.blank
        if blank is None or informed is None:
            learner = informed or blank
            assert learner is not None
            return learner
        if self.statistic >= self.check.declare:
            return informed
        return blank if self.statistic < 0 or blank.beliefs().confident else informed

    @property
    def statistic(self) -> float:
        """The check's statistic ``D`` now (`PriorCheck`; 0 before any signal)."""
        statistics = self.decision.statistic
        return statistics[-1] if statistics else 0.0

    def propose(self, state: int) -> Proposal:
        """The acting learner's proposal; while the check is undecided, a declaring
        proposal of the informed learner that ``D`` does not allow nor the blank learner
        corroborates is withdrawn and the blank learner's made instead (`PriorCheck`)."""
        acting = self.acting
        proposal = acting.propose(state)
        if proposal.declares_target and acting is self.informed and self.blank is not None:
            if self.statistic < self.check.declare and not self.corroborated:
                acting.withdraw_declaration()
                acting, proposal = self.blank, self.blank.propose(state)
        self._declared = acting.beliefs().best_task if proposal.declares_target else None
        return proposal

    @property
    def corroborated(self) -> bool:
        """Whether today's signals alone back the informed learner's best task: ``D >= 0``
        and the blank learner's posterior of that task at least ``lift / n_tasks`` and
        ``corroboration`` times its best task's (ties between a task and its mirror, which
        the blank learner may not break without the power prior, corroborate either)."""
        informed, blank = self.informed, self.blank
        if informed is None or blank is None:
            return False
        scores = blank.beliefs().scores
        task = informed.beliefs().best_task
        log_posterior = scores[task] - logsumexp(scores)
        return self.statistic >= 0 and bool(
            scores[task] >= scores.max() + np.log(self.check.corroboration)
            and log_posterior >= np.log(self.check.lift / len(scores)))

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        """Every learner observes the signal (following a target another one declared);
        then the check's statistic is updated while the prior is undecided."""
        declared, self._declared = self._declared, None
        for learner in (self.informed, self.blank):
            if learner is not None:
                if declared is not None:
                    learner.follow_declaration(declared)
                learner.observe(state, action, signal)
        if self.informed is not None and self.blank is not None:
            if self._power is not None:
                x = np.asarray(signal, dtype=float)
                self._power.add(self.informed.frame.distribution_at(state, action), x @ x)
                if declared is not None:
                    self._power.adopt(declared)
            self._check(self.informed, self.blank, ends_segment=declared is not None)

    def _check(
        self, informed: CalibrationFreeLearner, blank: CalibrationFreeLearner, ends_segment: bool
    ) -> None:
        """Add the last signal's log matches to the segment's, update ``D`` and decide."""
        matches = [informed.last_log_match, blank.last_log_match]
        if any(m is not None for m in matches):
            uniform = -np.log(informed.frame.n_classes)  # no decoder yet: 1/K each
            for row, match in zip(self._segment, matches, strict=True):
                row += uniform if match is None else match
            scores = informed.beliefs().scores
            posterior = np.exp(scores - logsumexp(scores))
            self._difference = float(posterior @ (self._segment[0] - self._segment[1]))
            self.decision.statistic.append(
                self._settled + self._difference + self._veto(posterior))
        if ends_segment:  # a target: both learners adopt its labels, a segment starts
            self._settled += self._difference
            self._difference = 0.0
            self._segment[:] = 0.0
        statistic, check = self.statistic, self.check
        if statistic <= -check.refute:
            self._decide("fallen back")
        elif statistic >= check.trust:
            self._decide("trusted")
        elif check.horizon is not None and informed.n_signals >= check.horizon:
            self._decide("trusted" if statistic >= 0 else "fallen back")

    def _veto(self, posterior: np.ndarray) -> float:
        """The power premise's part of ``D``: today's signals' log-power evidence under
        the informed learner's posterior where it is negative (the prior leads to tasks
        whose errors carry less power), else 0; 0 without the power prior."""
        if self._power is None:
            return 0.0
        return min(0.0, float(posterior @ self._power.scores()))

    def _decide(self, outcome: str) -> None:
        """Keep the informed learner alone ("trusted") or the blank one ("fallen back")."""
        acting = self.informed if outcome == "trusted" else self.blank
        assert acting is not None
        self.decision.outcome, self.decision.step = outcome, acting.n_signals
        self.informed, self.blank = (acting, None) if outcome == "trusted" else (None, acting)

    def beliefs(self) -> Beliefs:
        return self.acting.beliefs()

    def follow_declaration(self, task: int) -> None:
        """Every learner counts the next observation as reaching ``task`` (open-loop
        re-analysis)."""
        self._declared = task

    @property
    def n_signals(self) -> int:
        return self.acting.n_signals

    @property
    def world(self) -> World:
        return self.acting.world

    @property
    def frame(self) -> Frame:
        return self.acting.frame

    @property
    def config(self) -> LearnerConfig:
        return self.acting.config

    @property
    def history(self) -> TaskHistory:
        return self.acting.history

    def balanced_accuracy(self, task: int, label_weights: np.ndarray | None = None) -> float | None:
        return self.acting.balanced_accuracy(task, label_weights)

    @property
    def evidence_temperature(self) -> float:
        return self.acting.evidence_temperature

    @property
    def shrinkage_in_use(self) -> float | str:
        return self.acting.shrinkage_in_use


def adopted_labels(
    frame: Frame, moves: Sequence[tuple[int, int]], declared: Mapping[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """The labels a session's learner adopted at its declared targets.

    At a declared target the learner adopts, for every signal since the previous target,
    the label weights the declared task gives it (method.md §5). The segment before the
    session's first target and the open segment after its last one are not labelled (the
    first target is declared by decoders that no label had confirmed yet, and the last
    segment's task is unknown); nor are signals to which the task gives no label weight
    (guidance at the task's own state).

    Parameters
    ----------
    frame : Frame
        The session's frame on its world.
    moves : sequence of (int, int)
        Every step's (state, action), in order: signal ``i`` answers move ``i``.
    declared : mapping of int to int
        The index of every move that declared a target, to the task it declared.

    Returns
    -------
    indices : ndarray, shape (m,), int
        The labelled signals, in order.
    labels : ndarray, shape (m, n_classes)
        Their label weights (rows sum to 1).
    """
    ends = sorted(declared)
    indices: list[int] = []
    rows: list[np.ndarray] = []
    for start, end in pairwise(ends):
        task = declared[end]
        for index in range(start + 1, end + 1):
            state, action = moves[index]
            row = frame.weights_at(state, action)[task]
            if row.sum() > 0:
                indices.append(index)
                rows.append(row / row.sum())
    labels = np.array(rows) if rows else np.zeros((0, frame.n_classes))
    return np.array(indices, dtype=np.intp), labels


def power_premise(signals: np.ndarray, labels: np.ndarray, weights: np.ndarray) -> float:
    """How far a prior's feedback labels agree with the ErrP power premise (errors carry
    more power): the power prior's log-power evidence
    (`calibration_free.power_prior.LogPowerEvidence`) of the prior's labels, every sum
    weighted by the signals' weights (copies of an epoch sharing its weight count as that
    epoch once): positive where its error-labelled signals carry more power than its
    correct ones, negative where less (labels adopted wrongly), in nats; 0 where a class
    has no weight or the powers do not vary.

    Parameters
    ----------
    signals : ndarray, shape (n, n_features)
    labels : ndarray, shape (n, 2)
        Correct and error weights.
    weights : ndarray, shape (n,)
    """
    x = np.asarray(signals, dtype=float)
    z = np.log(np.maximum(np.einsum("ij,ij->i", x, x), np.finfo(float).tiny))
    w = np.asarray(weights, dtype=float)
    by_class = w[:, None] * np.asarray(labels, dtype=float)
    counts, sums = by_class.sum(axis=0), by_class.T @ z
    n, total = w.sum(), w @ z
    scatter = w @ (z * z) - total * total / n
    if not scatter > 0 or np.any(counts <= 0):
        return 0.0
    means = sums / counts
    within = np.clip(scatter - (sums @ means - total * total / n), scatter * 1e-12, scatter)
    return float(np.sign(means[1] - means[0]) * 0.5 * n * np.log(scatter / within))
