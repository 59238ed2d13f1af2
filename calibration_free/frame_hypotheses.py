"""Interaction-frame hypotheses (method-extensions §4): hypotheses are (task, frame) pairs.

The learner does not know the user's frame either: every candidate frame labels the history
its own way and trains its own decoders, with its own number of classes (feedback 2,
guidance one per guidance action). One `CalibrationFreeLearner`
per frame keeps those decoders and every task's matching log-likelihood; the hypotheses are
all their (task, frame) pairs, hypothesis ``h = f * n_tasks + t``.

**Chance levels made comparable.** A matching term is ``J = sum_l p(l | s, a, t) q(l | e)``:
for a decoder that knows nothing (``q`` uniform over its ``K`` classes) it is ``1 / K``, so
frames with more classes would lose ``log K`` per step to the others whatever the signals.
Each frame's log-likelihood is therefore scored against its own chance level,
``sum_i log(K J_i)``. This is the likelihood ratio of the signal against its marginal: a
decoder with equal class priors ``1/K`` has ``p(e | l) = K q(l | e) p(e)``, so
``p(e | s, a, t) = sum_l p(l | s, a, t) p(e | l) = K J p(e)``, and ``p(e)`` is the same for
every pair. Uninformative signals leave every (task, frame) pair at 0 whatever its class
count (tested), and the pairwise confidence compares what the signals explain beyond chance.

**Confident only beyond chance.** Pseudo-likelihoods of hypotheses that all explain noise
still drift apart like random walks (the pairwise confidence of the best pair passes 0.9 by
step 200 in 10 to 20 % of shuffled-label sessions), so a pair is confident only when its
pairwise confidence exceeds ``beta`` *and* its decoder's cross-validated balanced accuracy
on its own labels beats chance by `CHANCE_MARGIN_Z` standard errors, counted per
class (`beats_chance`). A shuffled-label control then stays undecided (tested).

**The thesis code's Student-t.** With ``decoder="student_t"`` frame hypotheses use, by
default (`FRAME_DEFAULTS`), the thesis code's count (``student_t_counts="total"``:
every class's predictive with the total number of signals): a class such as the line world's
no-move, labelled only at a goal, takes part from its second signal instead of its 12th
(11-D signals), and it is the class that tells the two goals apart under guidance.

Actions are uniform (the thesis code's setting: the uncertainty planner over pairs of
different class counts is not implemented), the power prior is off (it is feedback's own)
and no target is declared: a session identifies the (task, frame) pair.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calibration_free.config import LearnerConfig
from calibration_free.learner import CalibrationFreeLearner, Proposal
from calibration_free.likelihood import pairwise_confidence
from calibration_free.planning import random_action
from calibration_free.ties import first_best
from calibration_free.world import World

#: Standard errors by which a confident pair's decoder must beat chance: a one-sided 1 %
#: level, Bonferroni-corrected for the 800 looks of a 200-step session at 4 pairs
#: (``scipy.stats.norm.isf(0.01 / 800)``).
CHANCE_MARGIN_Z = 4.21
#: Learner settings frame hypotheses start from (the thesis code's): uniform actions, no
#: power prior, the Student-t count of every class the total one, the pairwise threshold 0.9.
FRAME_DEFAULTS = {
    "planner": "random", "power_prior": False, "student_t_counts": "total", "beta": 0.9
}


@dataclass(frozen=True)
class PairBeliefs:
    """Beliefs over (task, frame) pairs.

    Attributes
    ----------
    scores : ndarray, shape (n_frames * n_tasks,)
        Log-likelihood against chance of every pair.
    confidence : ndarray, shape (n_frames * n_tasks,)
        Pairwise-min confidence.
    best : int
        Best pair ``f * n_tasks + t``.
    confident : bool
    """

    scores: np.ndarray
    confidence: np.ndarray
    best: int
    confident: bool

    def normalised(self) -> np.ndarray:
        """``L_h / sum_u L_u`` of every pair."""
        weights = np.exp(self.scores - self.scores.max())
        return weights / weights.sum()


class FrameHypothesesLearner:
    """Learns the user's task *and* frame from unlabelled signals.

    Parameters
    ----------
    world : World
    frames : tuple of str
        The candidate frames.
    config : LearnerConfig
        Shared settings (its ``frame`` and ``power_prior`` are overridden per frame).
    rng : Generator
        Draws the actions.
    """

    def __init__(
        self,
        world: World,
        frames: tuple[str, ...] = ("feedback", "guidance"),
        config: LearnerConfig | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        config = config or LearnerConfig(**FRAME_DEFAULTS)
        self.world, self.frames, self.config = world, frames, config
        self.rng = np.random.default_rng(rng)
        self._learners = [
            CalibrationFreeLearner(world, replace(config, frame=f, power_prior=False), self.rng)
            for f in frames
        ]
        self._chance = np.array([np.log(learner.frame.n_classes) for learner in self._learners])
        self._n_terms = 0

    @property
    def n_hypotheses(self) -> int:
        return len(self.frames) * self.world.n_tasks

    @property
    def n_signals(self) -> int:
        """Signals observed so far."""
        return self._learners[0].n_signals

    def pair(self, hypothesis: int) -> tuple[int, str]:
        """(task, frame) of a hypothesis index."""
        frame, task = divmod(hypothesis, self.world.n_tasks)
        return task, self.frames[frame]

    def propose(self, state: int) -> Proposal:
        """A uniform action (never a declaration)."""
        return Proposal(random_action(self.world, self.rng), False)

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        """Every frame's learner takes in the signal."""
        scored = self._learners[0].n_signals > 0  # matching terms start with the 2nd signal
        for learner in self._learners:
            learner.observe(state, action, signal)
        self._n_terms += scored

    def beliefs(self) -> PairBeliefs:
        """The beliefs over all (task, frame) pairs."""
        scores = np.concatenate([
            learner.log_likelihood + self._n_terms * chance
            for learner, chance in zip(self._learners, self._chance, strict=True)
        ])
        confidence = pairwise_confidence(scores)
        best = first_best(scores)
        confident = bool(confidence[best] > self.config.frame_beta) and self._beats_chance(best)
        return PairBeliefs(scores, confidence, best, confident)

    def _beats_chance(self, hypothesis: int) -> bool:
        """Whether the pair's decoder beats chance on its own labels (`beats_chance`
        of its 10-fold balanced accuracy and its class weights)."""
        frame, task = divmod(hypothesis, self.world.n_tasks)
        learner = self._learners[frame]
        accuracy = learner.balanced_accuracy(task)
        if accuracy is None:
            return False
        return beats_chance(accuracy, learner.history.task_label_weights(task).sum(axis=0))


def beats_chance(
    balanced_accuracy: float, class_weights: np.ndarray, z: float = CHANCE_MARGIN_Z
) -> bool:
    """Whether a balanced accuracy is significantly above chance.

    Chance is ``1/K`` of the ``K`` classes with a positive weight. Under predictions
    independent of the labels each class's recall is a proportion of its ``n_k`` signals,
    of variance at most ``1 / (4 n_k)``, so the balanced accuracy (their mean, expected at
    most ``1/K``) has a standard error of at most ``sqrt(sum_k 1 / (4 n_k)) / K``; the
    accuracy must exceed chance by ``z`` of them. A rare class (the line world's no-move,
    labelled only at a goal) thus widens the margin, as it should: its recall rests on a
    few signals.

    Parameters
    ----------
    balanced_accuracy : float
        Mean recall over the classes with signals, in [0, 1].
    class_weights : ndarray, shape (n_classes,)
        Total label weight of each class (0 for a class without signals).
    z : float, default `CHANCE_MARGIN_Z`
    """
    weights = np.asarray(class_weights, dtype=float)
    weights = weights[weights > 0]
    if len(weights) < 2:
        return False
    standard_error = np.sqrt(np.sum(0.25 / weights)) / len(weights)
    return bool(balanced_accuracy > 1.0 / len(weights) + z * standard_error)
