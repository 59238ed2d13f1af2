"""Every knob of the learners, with its documented default."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

from calibration_free.frames import FRAMES
from calibration_free.likelihood import DEFAULT_CONFUSION_SMOOTHING
from calibration_free.planning import DEFAULT_DISCOUNT, PLANNERS
from calibration_free.task_decoders import DEFAULT_FOLDS
from decoding.lda import DEFAULT_SHRINKAGE
from decoding.validation import check_option, check_range

DECODERS: tuple[str, ...] = ("lda", "student_t")
PLANNING_WEIGHTS: tuple[str, ...] = ("posterior", "confidence")


@dataclass(frozen=True)
class LearnerConfig:
    """Settings of the calibration-free learner (and of the calibrated baseline).

    Parameters
    ----------
    frame : {"feedback", "guidance"}, default "feedback"
        Interaction frame (method.md §2).
    eps : float, default 0.1
        The user error rate the learner assumes when matching labels.
    decoder : {"lda", "student_t"}, default "lda"
        Shrinkage LDA with the pooled within-class covariance, deciding with equal
        priors (:mod:`decoding.lda`), or the thesis's Student-t predictive (per-class
        scatters: a slower per-task path, see :mod:`calibration_free.task_decoders`).
    shrinkage : float, default 0.5
        Covariance shrinkage towards the scaled identity, in [0, 1].
    n_folds : int, default 10
        Folds of the cross-validated confusion matrices.
    confusion_smoothing : float, default 1.0
        Pseudo-count added to every confusion-matrix cell.
    balanced_confusion : bool, default True
        Weigh every true class equally in the confusion matrices (see
        :func:`calibration_free.likelihood.confusion_matrices`); False is method.md's
        plain column normalisation.
    power_prior : bool, default True
        Add the ErrP power prior to the scores (feedback frame only).
    beta : float, default 0.9
        Confidence threshold on the pairwise-min confidence.
    planner : {"uncertainty", "greedy", "random"}, default "uncertainty"
    planning_weights : {"posterior", "confidence"}, default "posterior"
        How the uncertainty planner weighs the tasks: their posterior (softmax of the
        scores), which focuses on the leading hypotheses, or their normalised pairwise
        confidence W of method.md §6, which is flatter.
    novelty_bonus : float, default 4.0
        Exploration bonus ``c * 2 (1 - W_best) / sqrt(1 + visits(s))`` added to the
        uncertainty reward (scaled to a maximum of 1) until the first target is reached:
        while no decoder is calibrated by use, it draws the agent to cells it has seen
        little, where the hypotheses' labels can be told apart (guidance needs cells in
        the target's row or column), and fades as the best task's confidence W_best grows.
    n_planning_signals : int, default 20
        Past signals sampled per step by the uncertainty planner.
    discount : float, default 0.9
        Discount of the planner's value iteration.
    warmup_steps : int, default 10
        Random actions taken first, before decoders can be trained.
    """

    frame: str = "feedback"
    eps: float = 0.1
    decoder: str = "lda"
    shrinkage: float = DEFAULT_SHRINKAGE
    n_folds: int = DEFAULT_FOLDS
    confusion_smoothing: float = DEFAULT_CONFUSION_SMOOTHING
    balanced_confusion: bool = True
    power_prior: bool = True
    beta: float = 0.9
    planner: str = "uncertainty"
    planning_weights: str = "posterior"
    novelty_bonus: float = 4.0
    n_planning_signals: int = 20
    discount: float = DEFAULT_DISCOUNT
    warmup_steps: int = 10

    def __post_init__(self) -> None:
        check_option("frame", self.frame, FRAMES)
        check_option("decoder", self.decoder, DECODERS)
        check_option("planner", self.planner, PLANNERS)
        check_option("planning_weights", self.planning_weights, PLANNING_WEIGHTS)
        check_range("eps", self.eps, 0.0, 0.5)
        check_range("shrinkage", self.shrinkage, 0.0, 1.0)
        check_range("beta", self.beta, 0.5, 1.0, inclusive=False)
        check_range("discount", self.discount, 0.0, 1.0, inclusive=False)
        check_range("confusion_smoothing", self.confusion_smoothing, 0.0, 1e6)
        check_range("n_folds", self.n_folds, 2, 100)
        check_range("novelty_bonus", self.novelty_bonus, 0.0, 1e6)
        check_range("n_planning_signals", self.n_planning_signals, 1, 10_000)
        check_range("warmup_steps", self.warmup_steps, 0, 1_000_000)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dictionary of every setting."""
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> LearnerConfig:
        """Build from a dictionary; unknown keys are an error naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(
                f"unknown learner setting(s) {unknown}; known: {sorted(known)}"
            )
        return cls(**values)
