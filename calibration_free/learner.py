"""The calibration-free learner: one decoder per task hypothesis, the best explanation wins.

The learner's only inputs are (state, action, signal): it never sees a label nor the
user's target. Signals enter as float32 (the service's wire format) and are computed on
in float64, so every path sees the same numbers.

Its parts are plug-ins chosen by `LearnerConfig`: the
likelihood (`calibration_free.task_likelihoods`), the confidence rule
(`calibration_free.likelihood.CONFIDENCES`), the decoders
(`calibration_free.task_decoders`) and the planner (`calibration_free.planning`).
The decoders are fitted when first needed after each signal (by the next observation or
proposal), with cross-validation only for a likelihood that corrects by the confusion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration_free.config import LearnerConfig
from calibration_free.evidence_temperature import fit_temperature
from calibration_free.frames import Frame
from calibration_free.likelihood import (
    CONFIDENCES,
    label_log_matches,
    log_match,
    normalised_likelihood,
)
from calibration_free.planning import PlanningInputs, greedy_action, make_planner, random_action
from calibration_free.power_prior import make_power_prior
from calibration_free.shrinkage_choice import (
    CHOSEN_SHRINKAGE,
    FIRST_CHOICE_PERIOD,
    FIRST_CHOICE_START,
    FIRST_TARGET_GRID,
    FIRST_TARGET_STANDARD_ERRORS,
    choose_shrinkage,
    shrinkage_grid,
)
from calibration_free.task_decoders import (
    DecoderFit,
    TaskHistory,
    TaskModels,
    balanced_accuracy,
    decoder_fit,
    in_signal_order,
)
from calibration_free.task_likelihoods import make_likelihood
from calibration_free.ties import first_best
from calibration_free.world import World
from decoding.scatter_eigen import refresh_period
from decoding.validation import check_array


@dataclass(frozen=True)
class Proposal:
    """The next action, and whether performing it declares a target reached.

    Attributes
    ----------
    action : int
        Index into `calibration_free.world.ACTIONS`.
    declares_target : bool
        True when the action is the world's declaration action (the grid's ``goal``)
        performed while confident, in the state of the task the learner is confident
        about: a target reached (correct or not, the learner cannot know).
    """

    action: int
    declares_target: bool


def first_target_requirement(threshold: float, n_signals: int, signals: int) -> float:
    """The confidence a first target needs after ``n_signals`` signals: ``1 - (1 -
    threshold) min(1, n_signals / signals)``, relaxing from 1 to ``threshold`` over the
    first ``signals`` (0: ``threshold`` throughout). While no target has confirmed any
    label, a short history's confidence overstates (its decoders fit the few signals they
    are judged on): the README's "A stricter first target while the history is short"."""
    if signals == 0:
        return threshold
    return 1.0 - (1.0 - threshold) * min(1.0, n_signals / signals)


@dataclass(frozen=True)
class Beliefs:
    """What the learner currently believes about the tasks.

    Attributes
    ----------
    log_likelihood : ndarray, shape (n_tasks,)
        The likelihood's log pseudo-likelihood within the current task segment (since the
        last target; no power prior).
    scores : ndarray, shape (n_tasks,)
        ``log_likelihood`` plus the power prior where it applies.
    confidence : ndarray, shape (n_tasks,)
        The confidence rule's value of every task, in [0, 1] (pairwise-min ``W_t`` by
        default, see ``LearnerConfig.confidence``).
    best_task : int
    confident : bool
        ``confidence[best_task]`` above ``required``.
    n_signals : int
        Signals observed so far.
    rule : str
        The confidence rule in force (a key of
        `CONFIDENCES`): ``LearnerConfig.confidence``, or
        "normalised" while the evidence is calibrated.
    threshold : float
        The rule's threshold (``beta``, ``calibrated_beta`` while the evidence is
        calibrated, or the one the likelihood imposes: Bhattacharyya's 0.99 before its
        switch).
    required : float
        The confidence a target needs now: ``threshold``, or more until the first target
        while the history is short (`first_target_requirement`).
    """

    log_likelihood: np.ndarray
    scores: np.ndarray
    confidence: np.ndarray
    best_task: int
    confident: bool
    n_signals: int
    rule: str
    threshold: float
    required: float

    def normalised_likelihood(self) -> np.ndarray:
        """``L_t / sum_u L_u`` of `log_likelihood` (no power prior), shape (n_tasks,)."""
        return normalised_likelihood(self.log_likelihood)


class TaskLearner:
    """What the calibration-free learner and the calibrated baseline share.

    Subclasses provide `log_likelihood`, `observe`,
    `_predicted_samples` and `_class_means`, and may override `_scores`
    and `_decision_rule`.
    """

    log_likelihood: np.ndarray

    def __init__(
        self,
        world: World,
        config: LearnerConfig | None = None,
        rng: np.random.Generator | int | None = None,
    ) -> None:
        self.world = world
        self.config = config or LearnerConfig()
        self.frame = Frame(world, self.config.frame, self.config.eps)
        self.rng = np.random.default_rng(rng)
        self.n_signals = 0
        self.n_targets = 0
        #: Whether the learner started from a prior's adopted labels (`adopt_prior`).
        self.prior_adopted = False
        self._n_features: int | None = None
        self._pending_target: int | None = None
        self._visits = np.zeros(world.n_states)
        first = self.config.shrinkage_before_first_target
        if first == CHOSEN_SHRINKAGE:  # until the first choice, the heaviest
            first = FIRST_TARGET_GRID[-1]
        # A chosen shrinkage starts as the first phase's, until labels are adopted.
        after = first if self.config.chooses_shrinkage else self.config.resolved_shrinkage
        self._fits = tuple(
            decoder_fit(self.config.decoder, shrinkage, self.config.student_t_counts)
            for shrinkage in (first, after)
        )
        self._planner = make_planner(
            self.config.planner, self.frame, self.config.discount, self.config.epsilon
        )

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        """Take in the signal the user produced after ``action`` was taken in ``state``."""
        raise NotImplementedError

    @property
    def labels_adopted(self) -> bool:
        """Whether some labels have been adopted: at a target, or from a prior. Until then
        the learner is in its first phase (the first-target shrinkage, the stricter first
        target, the novelty bonus)."""
        return self.n_targets > 0 or self.prior_adopted

    @property
    def _fit(self) -> DecoderFit:
        """How the decoders are fitted now: with ``first_target_shrinkage`` until labels
        are adopted (the first target, or a prior), then with ``shrinkage``."""
        return self._fits[int(self.labels_adopted)]

    @property
    def shrinkage_in_use(self) -> float | str:
        """The decoders' shrinkage now (with ``shrinkage="cv"``, the latest choice)."""
        return self._fit.shrinkage

    @property
    def evidence_temperature(self) -> float:
        """The factor of the current task segment's evidence: 1 (the tempered filter)
        unless the learner calibrates it (``calibrated_evidence``)."""
        return 1.0

    def _choose_shrinkage(self, history: TaskHistory, task: int) -> None:
        """With ``shrinkage="cv"``, choose the shrinkage from now on from ``history``'s
        signals and ``task``'s labels of them (trusted: adopted at a target, or the
        baseline's calibration), on the history's own statistics and decomposed scatters;
        a choice that cannot be measured (a class too rare) keeps the current one."""
        if not self.config.chooses_shrinkage:
            return
        grid = shrinkage_grid(self.config.shrinkage_floor)
        fit = self._chosen_fit(history, task, grid, self.config.shrinkage_margin)
        if fit is not None:
            self._fits = (self._fits[0], fit)

    def _chosen_fit(
        self, history: TaskHistory, task: int, grid: tuple[float, ...], margin: float
    ) -> DecoderFit | None:
        """The decoders' fit at the shrinkage of ``grid`` chosen on ``task``'s labels of
        ``history`` within ``margin`` standard errors; None if it cannot be measured."""
        chosen = choose_shrinkage(
            history,
            task,
            eps=self.config.eps,
            smoothing=self.config.confusion_smoothing,
            balanced=self.config.balanced_confusion,
            grid=grid,
            margin=margin,
        )
        if chosen is None:
            return None
        return decoder_fit(self.config.decoder, chosen, self.config.student_t_counts)

    def _scores(self) -> np.ndarray:
        """Log scores of the tasks, shape (n_tasks,): a copy (the beliefs keep it, and the
        log-likelihood is updated in place)."""
        return self.log_likelihood.copy()

    def _predicted_samples(self) -> np.ndarray | None:
        """Predictions ``q_t(e)`` of sampled past signals (n_tasks, n, K), or None before
        any model."""
        raise NotImplementedError

    def _class_means(self) -> np.ndarray | None:
        """Every task decoder's class means (n_tasks, K, d), or None before any signal."""
        raise NotImplementedError

    def _decision_rule(self) -> tuple[str, float]:
        """(confidence rule, threshold): by default the configured ones."""
        return self.config.confidence, self.config.frame_beta

    def normalised_likelihood(self) -> np.ndarray:
        """``L_t / sum_u L_u`` of every task, shape (n_tasks,): the plain log-likelihood
        of the current task segment (no power prior), normalised (it restarts uniform at
        every target)."""
        return normalised_likelihood(self.log_likelihood)

    def beliefs(self) -> Beliefs:
        """The current beliefs over tasks."""
        scores = self._scores()
        rule, threshold = self._decision_rule()
        confidence = CONFIDENCES[rule](scores)
        best = first_best(scores)
        required = threshold
        if not self.labels_adopted:
            required = first_target_requirement(
                threshold, self.n_signals, self.config.frame_first_target_signals
            )
        return Beliefs(
            log_likelihood=self.log_likelihood.copy(),
            scores=scores,
            confidence=confidence,
            best_task=best,
            confident=bool(confidence[best] > required),
            n_signals=self.n_signals,
            rule=rule,
            threshold=threshold,
            required=required,
        )

    def propose(self, state: int) -> Proposal:
        """The next action from ``state``.

        Confident about task t: walk greedily to t and perform ``goal`` there (declaring a
        target reached). Otherwise, or always without ``declare_targets``, explore with the
        configured planner.
        """
        state = self._check_state(state)
        beliefs = self.beliefs()
        self._pending_target = None
        if beliefs.confident and self.config.declare_targets:
            action = greedy_action(self.world, state, beliefs.best_task, self.rng)
            declares = self.world.declares(state, action, beliefs.best_task)
            if declares:
                self._pending_target = beliefs.best_task
            return Proposal(action, declares)
        return Proposal(self._explore(state, beliefs), False)

    def follow_declaration(self, task: int) -> None:
        """Count the next observation, ``goal`` in ``task``, as a target reached.

        For open-loop re-analysis of a recorded history, where the learner observes the
        recorded (state, action, signal) sequence without choosing the actions: when the
        recorded device declared ``task`` reached (``goal`` there while confident), the
        user moved on to a new target, so the learner must switch task at that step, to
        that task, whether or not it is confident itself. Call this instead of
        `propose` before `observe` of that step; the observation then counts
        the target and relabels the history exactly as after a `propose` that
        declared ``task``. Like a declaring proposal, it has no effect if the next
        observation is not ``goal`` performed in ``task``. Draws nothing from the rng.
        """
        self._pending_target = self._check_state(task)

    def withdraw_declaration(self) -> None:
        """Forget the target the last proposal declared: the next observation counts no
        target, whatever its action (a caller that performs another learner's proposal
        instead, `calibration_free.prior.ReturningLearner`). Draws nothing."""
        self._pending_target = None

    def _explore(self, state: int, beliefs: Beliefs) -> int:
        # The random warm-up waits for decoders to train; a prior's are trained already.
        if self.n_signals < self.config.warmup_steps and not self.prior_adopted:
            return random_action(self.world, self.rng)
        if self.config.planning_weights == "posterior":
            weights = np.exp(beliefs.scores - beliefs.scores.max())
        else:
            weights = beliefs.confidence.copy()
        weights /= weights.sum()
        inputs = PlanningInputs(
            beliefs.best_task,
            weights,
            self._state_bonus(beliefs, weights),
            self._predicted_samples,
            self._class_means,
        )
        return self._planner.action(state, inputs, self.rng)

    def _state_bonus(self, beliefs: Beliefs, task_weights: np.ndarray) -> np.ndarray | None:
        """The planner's bonus of every state, shape (n_states,), or None without one.

        The novelty bonus (``novelty_bonus``, until the first target, fading as the best
        task's confidence grows) plus the goal pull (``goal_pull`` times the planning
        weight of the tasks whose state each state is).
        """
        bonus = None
        if self.config.frame_novelty_bonus > 0 and not self.labels_adopted:
            fade = 2.0 * (1.0 - beliefs.confidence[beliefs.best_task])
            bonus = fade * self.config.frame_novelty_bonus / np.sqrt(1.0 + self._visits)
        if self.config.goal_pull > 0:
            goals = np.bincount(
                self.world.task_states, task_weights, minlength=self.world.n_states
            )
            pull = self.config.goal_pull * goals
            bonus = pull if bonus is None else bonus + pull
        return bonus

    def _sample_indices(self, n_available: int) -> np.ndarray:
        size = min(self.config.n_planning_signals, n_available)
        return np.sort(self.rng.choice(n_available, size=size, replace=False))

    def _take_target_reached(self, state: int, action: int) -> int | None:
        """The declared target if this (state, action) performs it, and clear it."""
        target, self._pending_target = self._pending_target, None
        if target is not None and self.world.declares(state, action, target):
            self.n_targets += 1
            return target
        return None

    def _check_state(self, state: int) -> int:
        if not 0 <= int(state) < self.world.n_states or int(state) != state:
            raise ValueError(
                f"state must be a cell index in [0, {self.world.n_states}); got {state!r}"
            )
        return int(state)

    def _check_input(self, state: int, action: int, signal: np.ndarray) -> np.ndarray:
        """Validate one observation; return the signal as float64 from its float32 value."""
        self._check_state(state)
        if not 0 <= int(action) < self.world.n_actions or int(action) != action:
            raise ValueError(f"action must be in [0, {self.world.n_actions}); got {action!r}")
        shape = (self._n_features,) if self._n_features is not None else (None,)
        x = check_array("signal", signal, shape=shape, dtype=np.float32)
        if x.shape[0] == 0:
            raise ValueError("signal is empty")
        self._n_features = x.shape[0]
        return x.astype(np.float64)


def resolve_ambiguous_labels(weights: np.ndarray, corrected: np.ndarray) -> np.ndarray:
    """Split a signal's ambiguous label among its allowed classes by the decoder's opinion.

    When a task allows several labels for a signal (guidance: several optimal directions),
    the signal is shared among them in proportion to the task's corrected probabilities
    ``q`` of the signal, computed once, when it arrives, with the decoder trained before
    it (an incremental, one-pass EM step). Unambiguous labels (feedback) are unchanged.
    ``weights`` and ``corrected`` (n_tasks, K) -> (n_tasks, K).
    """
    shared = weights * corrected
    total = shared.sum(axis=1, keepdims=True)
    return np.where(total > 0, shared / np.where(total > 0, total, 1.0), weights)


def expect_the_chosen_label(
    expected: np.ndarray, weights: np.ndarray, resolved: np.ndarray
) -> np.ndarray:
    """The expected label once the user's choice among several optimal labels is resolved.

    Where a task allows some but not all classes (guidance: two optimal directions), the
    user picked one of them; matching against the uniform split would cost the true task
    ``log 2`` at every such step against any task that labels the same signals
    unambiguously. The allowed classes' expected mass (``1 - eps``) is instead split as
    the decoder resolved the choice (``resolved``, see `resolve_ambiguous_labels`).
    Labels allowing one class (feedback) or every class (the task's own cell) are kept.
    All arrays (n_tasks, K).
    """
    support = weights > 0
    n_allowed = support.sum(axis=1, keepdims=True)
    partial = (n_allowed > 1) & (n_allowed < weights.shape[1])
    allowed_mass = np.sum(expected * support, axis=1, keepdims=True)
    return np.where(partial & support, resolved * allowed_mass, expected)


class CalibrationFreeLearner(TaskLearner):
    """Learns the user's task and a signal decoder at once (method.md §2-§6).

    The likelihood, confidence rule, decoder and planner are plug-ins chosen by the
    config (``likelihood``, ``confidence``, ``decoder``, ``planner``).

    Parameters
    ----------
    world : World
    config : LearnerConfig, optional
    rng : numpy Generator or seed, optional
        Used by the planners (random choices, tie breaks, sampled signals).

    Examples
    --------
    >>> learner = CalibrationFreeLearner(GridWorld(5))
    >>> proposal = learner.propose(state=12)
    >>> learner.observe(12, proposal.action, signal)  # doctest: +SKIP
    """

    def __init__(
        self,
        world: World,
        config: LearnerConfig | None = None,
        rng: np.random.Generator | int | None = None,
    ) -> None:
        super().__init__(world, config, rng)
        self._likelihood = make_likelihood(
            self.config.likelihood,
            world.n_tasks,
            self.config.resolved_shrinkage,
            self.config.first_target_evidence,
            self.config.evidence_beta,
        )
        self._history: TaskHistory | None = None
        self._models: TaskModels | None = None
        self._power_prior = make_power_prior(
            self.config.power_prior_kind, world.n_tasks, self.frame.n_classes
        )
        #: Whether the current task segment's evidence is calibrated
        #: (``calibrated_evidence``), and its temperature once measured (None until the
        #: segment's first signal: measured then, on the decoders fitted for it).
        self._calibrated_segment = False
        self._evidence_temperature: float | None = None
        #: Every task's log match ``log m_t`` of the last signal observed against the
        #: prediction of the decoders fitted before it, untempered, shape (n_tasks,); None
        #: before any decoder and at a declared target's step (no prediction made).
        self.last_log_match: np.ndarray | None = None

    @property
    def evidence_temperature(self) -> float:
        """The measured temperature where the segment's evidence is calibrated
        (`calibration_free.evidence_temperature`), else 1."""
        return self._evidence_temperature or 1.0

    @property
    def log_likelihood(self) -> np.ndarray:
        """Every task's log pseudo-likelihood within the current task segment."""
        return self._likelihood.log_likelihood

    @property
    def _resplits_labels(self) -> bool:
        """Whether ambiguous labels are split again at every signal: the setting, where the
        frame has labels that allow several classes but not all and the likelihood
        cross-validates (the split needs out-of-fold probabilities: a decoder's own
        probabilities of the signals it was fitted on confirm its errors, and batch
        matching then locked a pick-and-place speech session onto a wrong task)."""
        return (
            self.config.resplit_labels
            and self.frame.has_ambiguous_labels
            and self._likelihood.corrects_confusion
        )

    @property
    def likelihood_in_use(self) -> str:
        """The likelihood scoring the tasks now: the configured one, except that
        "bhattacharyya" becomes "matching" at the first target."""
        return self._likelihood.name

    @property
    def history(self) -> TaskHistory:
        """The signals seen and every task's labels of them (read-only use)."""
        if self._history is None:
            raise RuntimeError("the learner has not observed any signal yet")
        return self._history

    def balanced_accuracy(
        self, task: int, label_weights: np.ndarray | None = None
    ) -> float | None:
        """Cross-validated balanced accuracy of ``task``'s decoder on the history so far
        (see `balanced_accuracy`); None before two
        classes have signals.

        Against ``task``'s own labels by default, or against ``label_weights``
        (n_signals, n_classes), e.g. the true labels in an offline analysis. From the
        current models' out-of-fold predictions when they have them; otherwise (the
        decoders not yet fitted on the latest signal, or a likelihood without
        cross-validation) ``task``'s fold decoders alone are fitted here, not every
        task's: after a declared target the service asks for it before the next signal
        relabels the history, and fitting every task then, for nothing, was most of the
        next epoch's wait at 20 x 20.
        """
        history = self._history
        if history is None or history.n_signals == 0:
            return None
        if label_weights is None:
            label_weights = history.task_label_weights(task)
        models = self._models
        if models is not None and models.cv_by_fold is not None:
            return models.balanced_accuracy(task, label_weights)
        _, folds = self._fit(history, tasks=np.array([task]))
        assert folds is not None
        proba = in_signal_order(history.cross_validated_proba(folds), history.n_signals, 0)
        return balanced_accuracy(proba, label_weights)

    @property
    def uses_power_prior(self) -> bool:
        return self.config.power_prior and self.frame.kind == "feedback"

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        """Score every task with the signal, then add it to every task's decoder."""
        x = self._check_input(state, action, signal)
        self._visits[state] += 1
        if self._history is None:
            self._history = self._new_history(x.shape[0])
        expected = self.frame.distribution_at(state, action)
        frame_weights = weights = self.frame.weights_at(state, action)
        models = None if self._prediction_is_discarded(state, action) else self._current_models()
        predicted = None
        if self._calibrated_segment and self._evidence_temperature is None:
            self._calibrate_evidence(models if models is not None else self._current_models())
        if models is not None:
            if self._resplits_labels:
                history = self._history
                history.resplit_own_labels(models.held_out_proba(history.n_adopted))
            predicted = self._likelihood.predict(models, x[None])[:, 0]
            weights = resolve_ambiguous_labels(weights, predicted)
            if self.config.ambiguous_match == "resolved":
                expected = expect_the_chosen_label(expected, frame_weights, weights)
        self._likelihood.take(expected, predicted, self.evidence_temperature)
        self.last_log_match = None if predicted is None else log_match(expected, predicted)
        self._history.add(x, weights, frame_weights)
        self._models = None
        if self.uses_power_prior:
            self._power_prior.add(expected, float(x @ x))
        self.n_signals += 1
        self._choose_first_target_shrinkage()
        target = self._take_target_reached(state, action)
        if target is not None:
            self._switch_task(target)
        self._likelihood.after_signal(self._history, self._current_models)

    def _new_history(self, n_features: int) -> TaskHistory:
        """An empty history of signals of ``n_features`` features, keeping what the
        settings need."""
        return TaskHistory(
            self.world.n_tasks, self.frame.n_classes, n_features, self.config.n_folds,
            class_scatters=self._fit.class_scatters or self._likelihood.needs_class_scatters,
            keeps_frame_labels=self._resplits_labels,
            # Only where every step fits the folds' decoders too (the likelihoods that
            # correct by the confusion); the others fit the whole history alone.
            eigen_period=(
                refresh_period(self.world.n_tasks, n_features)
                if self._likelihood.corrects_confusion
                and all(fit.rolling_eigen for fit in self._fits)
                else None
            ),
        )

    def adopt_prior(
        self, signals: np.ndarray, label_weights: np.ndarray, weights: np.ndarray
    ) -> None:
        """Start from earlier sessions' signals and the labels adopted for them, before
        any observation (`calibration_free.prior`).

        Each signal joins the history as if it had been observed and its labels adopted at
        a target, counted with its weight in every statistic (a weighted pseudo-observation,
        `add`; weight 1 is exactly a
        signal observed live). The learner then starts as after a target on that history:
        every task has those labels, the shrinkage after a target is in force (chosen on
        them with ``shrinkage="cv"``), the power prior takes its form after a target, and
        the first segment's evidence is calibrated on them where ``calibrated_evidence``
        applies and the history holds ``calibration_signals``. Today's signals count from
        0 (`n_signals`); the stricter first target and the novelty bonus do not apply.

        Parameters
        ----------
        signals : ndarray, shape (n, n_features)
            Feature vectors (float32 values, as the wire's).
        label_weights : ndarray, shape (n, n_classes)
            The adopted label weights of each signal, each row summing to 1.
        weights : ndarray, shape (n,)
            Each signal's weight, > 0.

        Raises
        ------
        RuntimeError
            After an observation or an earlier prior.
        ValueError
            On arrays of the wrong shapes or values.
        """
        if self._history is not None:
            raise RuntimeError("a prior is adopted before any signal, once")
        x = check_array("prior signals", signals, shape=(None, None), dtype=np.float32)
        n, n_features = x.shape
        labels = check_array(
            "prior label weights", label_weights, shape=(n, self.frame.n_classes)
        )
        weight = check_array("prior weights", weights, shape=(n,))
        if n == 0 or n_features == 0:
            raise ValueError(f"prior signals must be non-empty; got shape {x.shape}")
        if np.any(weight <= 0) or not np.allclose(labels.sum(axis=1), 1.0):
            raise ValueError("prior weights must be > 0 and label weights rows sum to 1")
        self._n_features = n_features
        self._history = self._new_history(n_features)
        every_task = (self.world.n_tasks, self.frame.n_classes)
        for row, label, w in zip(x.astype(np.float64), labels, weight, strict=True):
            self._history.add(row, np.broadcast_to(w * label, every_task), weight=w)
        self._switch_task(0)
        self.prior_adopted = True

    def _choose_first_target_shrinkage(self) -> None:
        """With ``first_target_shrinkage="cv"``, until the first target, every
        `FIRST_CHOICE_PERIOD` signals from the `FIRST_CHOICE_START`-th, choose
        the decoders' shrinkage on the leading task's labels (the best score: no label is
        trusted yet) among `FIRST_TARGET_GRID`; a choice that cannot be measured
        keeps the current one."""
        if (
            not self.config.chooses_first_target_shrinkage
            or self.labels_adopted
            or self.n_signals < FIRST_CHOICE_START
            or self.n_signals % FIRST_CHOICE_PERIOD
        ):
            return
        assert self._history is not None
        leader = int(np.argmax(self._scores()))
        fit = self._chosen_fit(
            self._history, leader, FIRST_TARGET_GRID, FIRST_TARGET_STANDARD_ERRORS
        )
        if fit is not None:
            self._fits = (fit, self._fits[1])

    def _prediction_is_discarded(self, state: int, action: int) -> bool:
        """Whether the decoders' prediction of this step's signal would be thrown away: the
        step reaches the declared target, so the segment's likelihood restarts after it,
        and no label needs the decoders to split it (a frame without ambiguous labels).
        The step then skips fitting the decoders on the labels it is about to replace:
        at 20 x 20, that fit was a third of the target steps' cost, and those steps set
        the update's p99."""
        target = self._pending_target
        return (
            target is not None
            and not self.frame.has_ambiguous_labels
            and self.world.declares(state, action, target)
        )

    def _current_models(self) -> TaskModels | None:
        """Every task's decoders on the history so far (fitted on first use after each
        signal, with cross-validation only if the likelihood needs it); None before any
        signal."""
        if self._history is None or self._history.n_signals == 0:
            return None
        if self._models is None:
            self._models = self._fit_models(self._likelihood.corrects_confusion)
        return self._models

    def _fit_models(self, cross_validate: bool) -> TaskModels:
        assert self._history is not None
        return TaskModels.fit(
            self._history,
            self._fit,
            self.config.confusion_smoothing,
            self.config.balanced_confusion,
            cross_validate=cross_validate,
        )

    def _switch_task(self, task: int) -> None:
        """Adopt ``task``'s labels for the whole history and start the next task afresh."""
        assert self._history is not None
        self._history.relabel(task)
        self._choose_shrinkage(self._history, task)
        if self.uses_power_prior:
            self._power_prior.adopt(task)
        self._likelihood.restart()
        self._evidence_temperature = None
        self._calibrated_segment = (
            self.config.uses_calibrated_evidence
            and self._history.n_signals >= self.config.calibration_signals
        )

    def _calibrate_evidence(self, models: TaskModels | None) -> None:
        """Measure the segment's evidence temperature on the adopted labels: the models
        are fitted on the history right after the target, where every task has the
        adopted labels (one labelling: task 0's are everyone's)."""
        assert models is not None and self._history is not None
        corrected = models.held_out_corrected_proba(0)
        labels = self._history.task_label_weights(0)
        log_matches = label_log_matches(corrected, self.frame.eps)
        self._evidence_temperature = fit_temperature(log_matches, labels)

    def _scores(self) -> np.ndarray:
        if not self.uses_power_prior:
            return self.log_likelihood.copy()
        return self.log_likelihood + self._power_prior.scores()

    def _decision_rule(self) -> tuple[str, float]:
        if self._calibrated_segment:
            return "normalised", self.config.calibrated_beta
        return self._likelihood.decision_rule() or super()._decision_rule()

    def _predicted_samples(self) -> np.ndarray | None:
        models = self._current_models()
        if models is None or self._history is None:
            return None
        signals = self._history.signals[self._sample_indices(self._history.n_signals)]
        return self._likelihood.predict(models, signals)

    def _class_means(self) -> np.ndarray | None:
        if self._history is None or self._history.n_signals == 0:
            return None
        return self._history.class_means()
