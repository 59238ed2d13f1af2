"""Every knob of the learners, with its documented default."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

from calibration_free.frames import FRAMES
from calibration_free.likelihood import CONFIDENCES, DEFAULT_CONFUSION_SMOOTHING
from calibration_free.planning import DEFAULT_DISCOUNT, DEFAULT_EPSILON, PLANNERS
from calibration_free.power_prior import POWER_PRIOR_KINDS
from calibration_free.shrinkage_choice import (
    CHOSEN_SHRINKAGE,
    FIRST_TARGET_GRID,
    SHRINKAGE_GRID,
    STANDARD_ERRORS,
)
from calibration_free.task_decoders import DECODERS, DEFAULT_FOLDS
from calibration_free.task_likelihoods import FIRST_TARGET_EVIDENCE, LIKELIHOODS
from decoding.lda import DEFAULT_SHRINKAGE, SHRINKAGE_RULES
from decoding.student_t import STUDENT_T_COUNTS
from decoding.validation import check_option, check_range

PLANNING_WEIGHTS: tuple[str, ...] = ("posterior", "confidence")
#: The normalised-likelihood threshold while the evidence is calibrated, and the fewest
#: signals at a target for it to be (tuned on synthetic data, seeds 100-199: the README's
#: "Calibrated evidence after the first target").
DEFAULT_CALIBRATED_BETA = 0.995
DEFAULT_CALIBRATION_SIGNALS = 100
#: The normalised-likelihood threshold of the Gaussian evidence until the first target: the
#: lowest of the thresholds measured on the synthetic tuning seeds 100-199 whose wrong-target
#: rate at 0.65 stays under the filter's (0.995: 3.4 %, 0.998: 1.6 %, against 2.5 %; the
#: README's "The Gaussian evidence before the first target"; the evidence itself is not
#: the default).
DEFAULT_EVIDENCE_BETA = 0.998
#: The novelty bonus of each frame when none is given (tuned on synthetic data, seeds
#: 100-119: the README's tuning table).
DEFAULT_NOVELTY_BONUS: dict[str, float] = {"feedback": 1.0, "guidance": 3.0}


#: The confidence threshold of each frame when none is given (tuned on synthetic data).
#: Feedback: the thesis's 0.9 until the power prior became evidence before the first
#: target; then 0.93, the lower of 0.9 and 0.93 that keeps the ErrP tuning rows' wrong-target
#: rates (seeds 100-299) at most the previous defaults' (the README's "The power prior as
#: evidence"). Guidance, where the issue's bar on wrong targets is 1 %: the smallest
#: threshold that keeps both 2-D guidance tuning rows (seeds 100-199) under it with a
#: margin (the README's "A stricter threshold in guidance").
DEFAULT_BETA: dict[str, float] = {"feedback": 0.93, "guidance": 0.92}

#: The signals over which the confidence a first target needs relaxes from 1 to the
#: threshold, per frame (tuned on synthetic data: the README's "A stricter first target while
#: the history is short"). Feedback: before the first target the confidence of a short
#: history overstates (at 0.65, tuning seeds 100-299, 16 % of the first targets declared
#: before step 80 were wrong, 1 % after); 90 is the earliest of 60, 90 and 120 whose ErrP
#: tuning rows all meet the issue's bars. Guidance: 0 (the threshold from the first
#: signal), where 90 made the harder 2-D tuning row's wrong targets more, not fewer.
DEFAULT_FIRST_TARGET_SIGNALS: dict[str, int] = {"feedback": 90, "guidance": 0}


#: The decoders' covariance shrinkage until the first target is reached, per frame, where it
#: cannot be chosen from the data (tuned on synthetic data, seeds 100-199: the README's
#: "Issue 13's levers"): while no task's labels have been confirmed by a target, every
#: decoder is fitted on few signals, many of them mislabelled, and heavy shrinkage (towards
#: the nearest-mean classifier) is what they can afford. Where it can be chosen (the LDA,
#: the matching likelihood, declared targets) feedback chooses it ("cv", among
#: `FIRST_TARGET_GRID`, this value the heaviest:
#: README, "A first-target shrinkage chosen from the data"). Guidance has none of its own
#: (``shrinkage`` throughout): its tuning showed no gain.
DEFAULT_FIRST_TARGET_SHRINKAGE: dict[str, float] = {"feedback": FIRST_TARGET_GRID[-1]}


#: What a task expects of a signal whose label allows several classes but not all
#: (``LearnerConfig.ambiguous_match``).
AMBIGUOUS_MATCHES: tuple[str, ...] = ("resolved", "even")

#: Settings added after recordings began to hold every learner setting, each with the value
#: that reproduces the learner from before it existed: a recording that lacks one ran
#: without it (`session.config.recorded_config` fills them in when a recording is read;
#: a missing ``first_target_shrinkage`` becomes the recording's own ``shrinkage``). The
#: shrinkage choice's floor and margin: the rule of its first day (2026-12-03 18:56 to
#: 2026-12-04 17:18, grid from 0.05, one standard error); a recording of the two hours
#: between that and the settings (from 0.01, half a standard error) re-runs with it and
#: may diverge from its targets on, which the re-run's report shows.
SETTINGS_BEFORE_THEY_EXISTED: dict[str, Any] = {
    "ambiguous_match": "resolved",
    "calibrated_evidence": False,
    "first_target_evidence": "filter",
    "first_target_signals": 0,
    "goal_pull": 0.0,
    "power_prior_kind": "ratio",
    "resplit_labels": False,
    "shrinkage_floor": 0.05,
    "shrinkage_margin": 1.0,
}


@dataclass(frozen=True)
class LearnerConfig:
    """Settings of the calibration-free learner (and of the calibrated baseline).

    Parameters
    ----------
    frame : {"feedback", "guidance"}, default "feedback"
        Interaction frame (method.md §2).
    eps : float, default 0.1
        The user error rate the learner assumes when matching labels.
    likelihood : {"matching", "simple", "batch", "bhattacharyya"}, default "matching"
        How tasks are scored (`calibration_free.task_likelihoods`): the matching
        filter with cross-validated confusion correction; the same filter on the raw
        decoder posterior (no confusion, no cross-validation fits); every step's
        recomputation of the segment's matches with the latest decoders (Eq.
        matchingoverfitting, no cross-validation); or the Bhattacharyya overlap until the
        first target (declared at a normalised likelihood above 0.99), then the matching
        filter. Feedback frame only for "bhattacharyya".
    confidence : {"pairwise", "normalised"}, default "pairwise"
        The confidence compared with ``beta``: the pairwise-min ``W_t = min_u L_t / (L_t +
        L_u)`` or the normalised likelihood ``L_t / sum_u L_u`` of the scores.
    decoder : {"lda", "student_t", "gaussian", "categorical"}, default "lda"
        Shrinkage LDA with the pooled within-class covariance, deciding with equal
        priors (`decoding.lda`); the thesis's Student-t predictive (per-class
        scatters: a slower per-task path, see `calibration_free.task_decoders`); a
        plain Gaussian per class (QDA: weighted mean and covariance shrunk by
        ``shrinkage``, equal priors, `decoding.gaussian`); or, for symbolic signals
        (a one-hot vector of the button pressed), per-class button frequencies
        (`decoding.categorical`).
    shrinkage : float, "oas", "cv" or None, default "cv" where it can be chosen, else 0.5
        Covariance shrinkage towards the scaled identity, in [0, 1]; or, with the "lda"
        decoder, "oas": each task and training set's Oracle Approximating Shrinkage
        intensity, from its pooled covariance (`decoding.lda.oas_shrinkage`); or,
        with the "lda" decoder, the "matching" likelihood and ``declare_targets``, "cv":
        chosen at every target (the calibrated baseline: at the end of its calibration)
        from the cross-validated matching evidence on the adopted labels, the heaviest of
        `SHRINKAGE_GRID` (0.01 to 0.5) not clearly
        less discriminating than the best (`calibration_free.shrinkage_choice`; tuned
        on synthetic data: the README's "Issue 13's levers"). None: "cv" where it can be
        chosen, else 0.5 (`resolved_shrinkage`). From the first target on; before
        it, ``first_target_shrinkage``.
    first_target_shrinkage : float, "oas", "cv" or None, default the frame's
        The decoders' shrinkage until the first target is reached, as ``shrinkage``; or,
        with the "lda" decoder, the "matching" likelihood and ``declare_targets``, "cv": every
        `FIRST_CHOICE_PERIOD` (5) signals from the
        `FIRST_CHOICE_START`-th (40) on, chosen
        by the same rule on the leading task's labels (no label is trusted yet) among
        `FIRST_TARGET_GRID` (0.3, 0.5, 0.7, 0.9),
        the heaviest within one standard error of the best; 0.9 until the first choice.
        None: the frame's default: in feedback "cv" where it can be chosen, else
        `DEFAULT_FIRST_TARGET_SHRINKAGE` (0.9); in guidance and sessions without
        ``declare_targets`` (which never reach a first target), ``shrinkage``. Set it
        equal to ``shrinkage`` for one shrinkage throughout (the thesis's). The decoders
        only: the Bhattacharyya overlap, a distance between the classes rather than a
        decoder, and the calibrated baseline, which has no such phase, use ``shrinkage``.
    shrinkage_floor : float, default 0.01
        With ``shrinkage="cv"``: the lightest intensity the choice may take, in [0.01, 0.5];
        the grid is `SHRINKAGE_GRID`'s values from
        it up (0.05 gives 0.05, 0.1, 0.2, 0.3, 0.5, the rule's first grid).
    shrinkage_margin : float, default 0.5
        With ``shrinkage="cv"``: how far below the most discriminating intensity's evidence
        a heavier one may be and still be chosen, in standard errors of that evidence (1:
        the textbook's one-standard-error rule; 0: the best evidence).
    student_t_counts : {"class", "total"}, default "class"
        With ``decoder="student_t"``: the count in each class's predictive, the class's own
        weight or the training set's total (the thesis code's, which lets a rarely labelled
        class take part from its second signal; `decoding.student_t.fit_student_t`).
    n_folds : int, default 10
        Folds of the cross-validated confusion matrices.
    confusion_smoothing : float, default 1.0
        Pseudo-count added to every confusion-matrix cell.
    balanced_confusion : bool, default True
        Weigh every true class equally in the confusion matrices (see
        `calibration_free.likelihood.confusion_matrices`); False is method.md's
        plain column normalisation.
    power_prior : bool, default True
        Add the ErrP power prior to the scores (feedback frame only).
    power_prior_kind : {"evidence_then_ratio", "evidence", "ratio"}, default "evidence_then_ratio"
        Its form (`calibration_free.power_prior`): "evidence", the signed likelihood
        ratio of the signals' log powers under each task's labels (grows with the data);
        "ratio", method.md's log ratio of the classes' mean powers (bounded); the default,
        the evidence until the first target and the ratio from then on.
    calibrated_evidence : bool or None, default True in feedback where it applies
        At every target reached once the history holds ``calibration_signals`` signals,
        fit the temperature ``tau`` that makes the matches calibrated class probabilities
        of the adopted labels (`calibration_free.evidence_temperature`); until the
        next target every signal then adds ``tau log m`` and a task is declared when its
        normalised likelihood exceeds ``calibrated_beta`` (before that, and after a target
        with fewer signals, the tempered filter and ``confidence``/``beta``). Needs the
        feedback frame, the "matching" likelihood and ``declare_targets``; None: True
        where it applies, else False (`uses_calibrated_evidence`; tuned on synthetic
        data: the README's "Calibrated evidence after the first target").
    calibrated_beta : float, default 0.995
        The normalised-likelihood threshold while the evidence is calibrated, in (0.5, 1).
    calibration_signals : int, default 100
        The fewest signals the history must hold at a target for the evidence to be
        calibrated there: labels adopted on fewer are too often wrong, and a calibrated
        filter on a wrong mapping locks it in.
    first_target_evidence : {"filter", "gaussian"}, default "filter"
        What scores the tasks until the first target: the likelihood's filter (with
        ``confidence``/``beta``), or "gaussian": after every signal, the log marginal
        likelihood of the whole history under each task's labels, a Gaussian model of
        the classes with its parameters integrated out
        (`calibration_free.gaussian_evidence`), a task declared when its normalised
        likelihood exceeds ``evidence_beta``. Needs the feedback frame, the "matching"
        likelihood and ``declare_targets``.
    evidence_beta : float, default 0.998
        The normalised-likelihood threshold of the Gaussian evidence, in (0.5, 1).
    beta : float, default the frame's (`DEFAULT_BETA`: 0.93 for feedback, 0.92 for
        guidance)
        Confidence threshold on the ``confidence`` rule, in (0.5, 1); the one in force is
        `frame_beta`.
    first_target_signals : int, default the frame's (`DEFAULT_FIRST_TARGET_SIGNALS`:
        90 for feedback, 0 for guidance)
        Until the first target, the confidence a target needs relaxes from 1 to the
        rule's threshold over this many signals: ``1 - (1 - threshold) min(1, n /
        first_target_signals)`` after ``n`` signals (whatever the rule: ``beta``, or the
        one the likelihood imposes). 0: the threshold from the first signal (the
        thesis's). From the first target on, the threshold. The one in force is
        `frame_first_target_signals`.
    planner : str, default "information"
        One of "uncertainty", "information", "greedy", "random", "signal", "epsilon-greedy".
        How actions are chosen while not confident (`calibration_free.planning`):
        meaning-space uncertainty (the weighted variance of expected matches), the expected
        information of the answer about the task (mutual information on the same sampled
        signals), or signal-space uncertainty (class means), each with value iteration;
        greedy on the most likely task, epsilon-greedy, or uniform.
    epsilon : float, default 0.1
        The "epsilon-greedy" planner's probability of a uniform action, in [0, 1].
    planning_weights : {"posterior", "confidence"}, default "posterior"
        How the uncertainty planner weighs the tasks: their posterior (softmax of the
        scores), which focuses on the leading hypotheses, or their normalised pairwise
        confidence W of method.md §6, which is flatter.
    novelty_bonus : float, default the frame's (`DEFAULT_NOVELTY_BONUS`: 1 for
        feedback, 3 for guidance)
        Exploration bonus ``c * 2 (1 - W_best) / sqrt(1 + visits(s))`` added to the
        reward of the "uncertainty", "information" and "signal" planners (scaled to a
        maximum of 1) until the first target is reached: while no decoder is calibrated
        by use, it draws the agent to cells it has seen little, where the hypotheses'
        labels can be told apart (guidance needs cells in the target's row or column),
        and fades as the best task's confidence W_best grows. The thesis's planners have
        no such bonus (0 reproduces them). Feedback is faster with a light bonus (the
        information planner finds the telling cells itself); guidance needs the strong
        one (see the README's tuning table).
    goal_pull : float, default 0
        Progress toward the likely goals, added to the reward of the "uncertainty",
        "information" and "signal" planners (scaled to a maximum of 1) while not confident:
        every state gets ``goal_pull`` times the planning weight of the tasks whose state it
        is, so that value iteration draws the agent toward the leading hypotheses' goals as
        it explores. The thesis's lesson of its world-properties study (method-extensions
        §7.2): uncertainty planning alone leaves the agent far from the goal when it
        becomes confident (pick-and-place: about 16 moves away). 0 reproduces the thesis's
        planners; on the grid with ErrP feedback it delays the first target (README:
        "World properties").
    resplit_labels : bool, default True
        Where a task's label allows several classes but not all (guidance: two optimal
        directions), split it among them again at every signal by the task's latest
        out-of-fold class probabilities (one EM step on the user's choice,
        `resplit_own_labels`), for the
        signals since the last target; False keeps the split made when each signal
        arrived. No effect in the feedback frame, nor with a likelihood that does not
        cross-validate ("simple", "batch": the split needs out-of-fold probabilities).
    ambiguous_match : {"resolved", "even"}, default "resolved"
        What a task expects of a signal whose label allows several classes but not all
        (guidance: two optimal directions). "resolved": the split the decoder resolved
        for that signal (`expect_the_chosen_label`),
        which spares the true task the mixture's cost of log 2 but lets a task whose
        labels are mostly ambiguous (a corner's) fit a signal of either direction.
        "even": the user picks either with equal probability, so the expected label is
        the frame's even split and the match the mixture of the two classes' matches
        (method.md's matching). README: "Ambiguous labels matched as the even mixture".
    n_planning_signals : int, default 20
        Past signals sampled per step by the uncertainty planner.
    discount : float, default 0.9
        Discount of the planner's value iteration.
    warmup_steps : int, default 10
        Random actions taken first, before decoders can be trained.
    declare_targets : bool, default True
        False: the device never declares a target and keeps acting with its planner
        whatever its confidence (the thesis's chapter 4 runs, where the teacher teaches one
        task for the whole run and the figure is that task's normalised likelihood).
    """

    frame: str = "feedback"
    eps: float = 0.1
    likelihood: str = "matching"
    confidence: str = "pairwise"
    decoder: str = "lda"
    shrinkage: float | str | None = None
    first_target_shrinkage: float | str | None = None
    shrinkage_floor: float = SHRINKAGE_GRID[0]
    shrinkage_margin: float = STANDARD_ERRORS
    student_t_counts: str = "class"
    n_folds: int = DEFAULT_FOLDS
    confusion_smoothing: float = DEFAULT_CONFUSION_SMOOTHING
    balanced_confusion: bool = True
    power_prior: bool = True
    power_prior_kind: str = "evidence_then_ratio"
    calibrated_evidence: bool | None = None
    calibrated_beta: float = DEFAULT_CALIBRATED_BETA
    calibration_signals: int = DEFAULT_CALIBRATION_SIGNALS
    first_target_evidence: str = "filter"
    evidence_beta: float = DEFAULT_EVIDENCE_BETA
    beta: float | None = None
    first_target_signals: int | None = None
    planner: str = "information"
    epsilon: float = DEFAULT_EPSILON
    planning_weights: str = "posterior"
    novelty_bonus: float | None = None
    goal_pull: float = 0.0
    resplit_labels: bool = True
    ambiguous_match: str = "resolved"
    n_planning_signals: int = 20
    discount: float = DEFAULT_DISCOUNT
    warmup_steps: int = 10
    declare_targets: bool = True

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if field.type == "bool" and not isinstance(value, bool):
                raise ValueError(f"{field.name} must be true or false; got {value!r}")
            if field.type == "bool | None" and not isinstance(value, bool | None):
                raise ValueError(f"{field.name} must be true, false or null; got {value!r}")
        check_option("frame", self.frame, FRAMES)
        check_option("likelihood", self.likelihood, LIKELIHOODS)
        check_option("confidence", self.confidence, tuple(CONFIDENCES))
        check_option("decoder", self.decoder, DECODERS)
        check_option("planner", self.planner, PLANNERS)
        check_option("first_target_evidence", self.first_target_evidence, FIRST_TARGET_EVIDENCE)
        check_option("power_prior_kind", self.power_prior_kind, POWER_PRIOR_KINDS)
        check_option("ambiguous_match", self.ambiguous_match, AMBIGUOUS_MATCHES)
        if self.first_target_evidence == "gaussian" and not self._matches_feedback_targets:
            raise ValueError(
                "first_target_evidence 'gaussian' scores two-class labellings until a "
                "declared first target: it needs frame 'feedback', likelihood 'matching' "
                f"and declare_targets; got frame {self.frame!r}, likelihood "
                f"{self.likelihood!r}, declare_targets {self.declare_targets}"
            )
        if self.likelihood == "bhattacharyya" and self.frame != "feedback":
            raise ValueError(
                "likelihood 'bhattacharyya' compares two classes: it needs frame "
                f"'feedback'; got frame {self.frame!r}"
            )
        check_option("planning_weights", self.planning_weights, PLANNING_WEIGHTS)
        check_range("eps", self.eps, 0.0, 0.5)
        check_range("epsilon", self.epsilon, 0.0, 1.0)
        if self.shrinkage is not None:
            self._check_shrinkage("shrinkage", self.shrinkage)
        if self.first_target_shrinkage is not None:
            self._check_shrinkage("first_target_shrinkage", self.first_target_shrinkage)
        check_range(
            "shrinkage_floor", self.shrinkage_floor, SHRINKAGE_GRID[0], SHRINKAGE_GRID[-1]
        )
        check_range("shrinkage_margin", self.shrinkage_margin, 0.0, 100.0)
        check_option("student_t_counts", self.student_t_counts, STUDENT_T_COUNTS)
        if self.beta is not None:
            check_range("beta", self.beta, 0.5, 1.0, inclusive=False)
        check_range("discount", self.discount, 0.0, 1.0, inclusive=False)
        check_range("confusion_smoothing", self.confusion_smoothing, 0.0, 1e6)
        check_range("n_folds", self.n_folds, 2, 100)
        if self.novelty_bonus is not None:
            check_range("novelty_bonus", self.novelty_bonus, 0.0, 1e6)
        if self.first_target_signals is not None:
            check_range("first_target_signals", self.first_target_signals, 0, 1_000_000)
        check_range("goal_pull", self.goal_pull, 0.0, 1e6)
        check_range("n_planning_signals", self.n_planning_signals, 1, 10_000)
        check_range("warmup_steps", self.warmup_steps, 0, 1_000_000)
        check_range("calibrated_beta", self.calibrated_beta, 0.5, 1.0, inclusive=False)
        check_range("evidence_beta", self.evidence_beta, 0.5, 1.0, inclusive=False)
        check_range("calibration_signals", self.calibration_signals, 1, 1_000_000)
        if self.calibrated_evidence and not self._matches_feedback_targets:
            raise ValueError(
                "calibrated_evidence needs frame 'feedback', likelihood 'matching' and "
                f"declare_targets; got frame {self.frame!r}, likelihood "
                f"{self.likelihood!r}, declare_targets {self.declare_targets}"
            )

    def _check_shrinkage(self, name: str, value: float | str) -> None:
        if not isinstance(value, str):
            check_range(name, value, 0.0, 1.0)
            return
        if value == CHOSEN_SHRINKAGE:
            self._check_chosen_shrinkage(name)
            return
        if value not in (*SHRINKAGE_RULES, CHOSEN_SHRINKAGE):
            forms = ", ".join(repr(v) for v in (*SHRINKAGE_RULES, CHOSEN_SHRINKAGE))
            raise ValueError(
                f"{name} must be a number in [0, 1] or one of {forms}; got {value!r}"
            )
        if self.decoder != "lda" or self.likelihood == "bhattacharyya":
            raise ValueError(
                f"{name} {value!r} is chosen from the pooled covariance: it needs decoder "
                f"'lda' and a likelihood other than 'bhattacharyya'; got decoder "
                f"{self.decoder!r}, likelihood {self.likelihood!r}"
            )

    def _check_chosen_shrinkage(self, name: str) -> None:
        """``name = "cv"`` is chosen from the LDA's matching evidence, on labels that targets
        confirm (or, before the first target, the leading task's)."""
        if not self.declare_targets:
            raise ValueError(
                f"{name} {CHOSEN_SHRINKAGE!r} is chosen on labels that targets confirm: it "
                "needs declare_targets"
            )
        if not self._can_choose_shrinkage:
            raise ValueError(
                f"{name} {CHOSEN_SHRINKAGE!r} measures the LDA's confusion-corrected "
                f"evidence: it needs decoder 'lda' and likelihood 'matching'; got decoder "
                f"{self.decoder!r}, likelihood {self.likelihood!r}"
            )

    @property
    def _can_choose_shrinkage(self) -> bool:
        """Whether the decoders are the LDA scored by the matching likelihood."""
        return self.decoder == "lda" and self.likelihood == "matching"

    @property
    def resolved_shrinkage(self) -> float | str:
        """The shrinkage in force from the first target on: the given one, else "cv" where
        it can be chosen (decoder "lda", likelihood "matching", declared targets), else
        `DEFAULT_SHRINKAGE` (unresolved in the field, as
        `frame_novelty_bonus`)."""
        if self.shrinkage is not None:
            return self.shrinkage
        choosable = self._can_choose_shrinkage and self.declare_targets
        return CHOSEN_SHRINKAGE if choosable else DEFAULT_SHRINKAGE

    @property
    def chooses_shrinkage(self) -> bool:
        """Whether the shrinkage is chosen from the data at every target."""
        return self.resolved_shrinkage == CHOSEN_SHRINKAGE

    @property
    def shrinkage_before_first_target(self) -> float | str:
        """The decoders' shrinkage until the first target: the given one, else the frame's
        default ("cv" in feedback where it can be chosen, else 0.9), else ``shrinkage``
        (unresolved in the field, as ``frame_novelty_bonus``). A session that declares no
        targets has no first phase: the default is then ``shrinkage`` throughout."""
        if self.first_target_shrinkage is not None:
            return self.first_target_shrinkage
        if not self.declare_targets:
            return self.resolved_shrinkage
        if self.frame in DEFAULT_FIRST_TARGET_SHRINKAGE:
            if self._can_choose_shrinkage:
                return CHOSEN_SHRINKAGE
            return DEFAULT_FIRST_TARGET_SHRINKAGE[self.frame]
        # The rule after the first target needs adopted labels: until then, the default.
        return DEFAULT_SHRINKAGE if self.chooses_shrinkage else self.resolved_shrinkage

    @property
    def chooses_first_target_shrinkage(self) -> bool:
        """Whether the shrinkage is chosen from the data until the first target."""
        return self.shrinkage_before_first_target == CHOSEN_SHRINKAGE

    @property
    def _matches_feedback_targets(self) -> bool:
        """Whether targets confirm labels (declared targets) and the evidence is the
        matching filter's on two-class feedback labels: where the evidence can be
        calibrated at targets, and where the Gaussian evidence can precede the filter."""
        return self.frame == "feedback" and self.likelihood == "matching" and self.declare_targets

    @property
    def uses_calibrated_evidence(self) -> bool:
        """Whether the evidence is calibrated at targets: the given setting, else where it
        applies (unresolved in the field, as `frame_novelty_bonus`)."""
        if self.calibrated_evidence is None:
            return self._matches_feedback_targets
        return self.calibrated_evidence

    @property
    def frame_novelty_bonus(self) -> float:
        """The novelty bonus in force: the given one, or the frame's default (unresolved in
        the field, so that ``dataclasses.replace(config, frame=...)`` takes the new frame's)."""
        if self.novelty_bonus is None:
            return DEFAULT_NOVELTY_BONUS[self.frame]
        return self.novelty_bonus

    @property
    def frame_beta(self) -> float:
        """The confidence threshold in force: the given one, or the frame's default
        (unresolved in the field, as `frame_novelty_bonus`)."""
        if self.beta is None:
            return DEFAULT_BETA[self.frame]
        return self.beta

    @property
    def frame_first_target_signals(self) -> int:
        """The signals over which a first target's confidence relaxes to the threshold in
        force: the given ones, or the frame's default (unresolved in the field, as
        `frame_novelty_bonus`)."""
        if self.first_target_signals is None:
            return DEFAULT_FIRST_TARGET_SIGNALS[self.frame]
        return self.first_target_signals

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dictionary of every setting, the threshold, novelty bonus and
        shrinkages in force included (a recording replays with the values it ran with,
        whatever later defaults say)."""
        return asdict(self) | {
            "novelty_bonus": self.frame_novelty_bonus,
            "beta": self.frame_beta,
            "first_target_signals": self.frame_first_target_signals,
            "shrinkage": self.resolved_shrinkage,
            "first_target_shrinkage": self.shrinkage_before_first_target,
            "calibrated_evidence": self.uses_calibrated_evidence,
        }

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
