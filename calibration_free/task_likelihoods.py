"""The learner's likelihoods as plug-ins: how every task is scored within its task segment.

A likelihood keeps every task's log pseudo-likelihood since the last target (the current
*task segment*) and is told, for each new signal, the label distribution every task
expected (`TaskLikelihood.take`, before the signal joins the history, with the
decoders trained before it) and then that the signal has joined
(`TaskLikelihood.after_signal`); at a target it restarts
(`TaskLikelihood.restart`). `LIKELIHOODS`:

* ``"matching"`` (the default; method.md §3, the thesis's Eq.
  matchingfiltercrossvalidation): a filter, ``log L_t += log sum_l p(l | s, a, t)
  q_t(l | e)`` with the prediction ``q = C p`` corrected by each task's cross-validated
  confusion matrix ``C``.
* ``"simple"`` (Eq. matchingfilter, method-extensions §7.3): the same filter on the
  decoders' raw prediction ``p``; no confusion matrix, so no cross-validation fits at all.
* ``"batch"`` (Eq. matchingoverfitting, §5): after every signal the log-likelihood of every
  task is recomputed over the whole current task segment, each signal matched against the
  raw prediction of the decoder fitted on the whole history *including that signal*
  (every decoder of the learner is trained on the whole history: the relabelled past
  segments and the current one); no cross-validation. Each signal keeps the label
  distribution it was matched with when it arrived (with any ambiguous guidance label
  resolved then, see `calibration_free.learner.expect_the_chosen_label`).
* ``"bhattacharyya"`` (method-extensions §1, thesis §7.3): until the first target,
  ``log L_t += log(1 - rho_t + tiny)`` per signal, ``rho_t`` the Bhattacharyya
  coefficient of the two class Gaussians of task t's labelling of the whole history (shrunk
  as the decoders are); a task is declared when its normalised likelihood
  ``L_t / sum_u L_u`` exceeds `BHATTACHARYYA_THRESHOLD` (0.99), whatever the
  configured confidence rule. Steps at which some task's labelling leaves a class with less
  than two signals' weight add nothing to any task (an undefined overlap would favour or
  penalise the tasks whose classes fill first, whatever the signals say). At the first
  target the learner relabels the history as always and this likelihood switches, for
  good, to the matching filter (and the configured confidence rule): once hypotheses share
  most labels their overlaps stop discriminating.

The matching filter may also be preceded, until the first target, by the Gaussian evidence
(``LearnerConfig.first_target_evidence="gaussian"``, `FirstTargetGaussianEvidence`):
after every signal each task's log-likelihood is the log marginal likelihood of the whole
history under that task's labels (`calibration_free.gaussian_evidence`), and a task
is declared when its normalised likelihood exceeds ``evidence_beta``; from the first target
on, the matching filter as always.

The prediction a likelihood matches (`TaskLikelihood.predict`) is also what the
learner splits ambiguous guidance labels with and what the meaning-space planner samples:
with ``"simple"`` or ``"batch"`` (or Bhattacharyya before its switch) no confusion matrix
is ever needed.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from calibration_free.bhattacharyya import (
    defined_classes,
    overlap_log_factor,
    overlap_of_classes,
)
from calibration_free.gaussian_evidence import log_evidence
from calibration_free.likelihood import log_match
from calibration_free.task_decoders import TaskHistory, TaskModels
from decoding.validation import check_option

LIKELIHOODS: tuple[str, ...] = ("matching", "simple", "batch", "bhattacharyya")
#: What scores the tasks until the first target: the likelihood itself ("filter") or, before
#: the matching filter, the Gaussian evidence ("gaussian").
FIRST_TARGET_EVIDENCE: tuple[str, ...] = ("filter", "gaussian")
#: Normalised likelihood above which the Bhattacharyya likelihood declares a task.
BHATTACHARYYA_THRESHOLD = 0.99

#: The learner's decoders fitted on the history so far (fitted when first asked for).
ModelsSource = Callable[[], TaskModels]


class TaskLikelihood:
    """The matching filter: every task's log-likelihood grows by one match per signal.

    Parameters
    ----------
    n_tasks : int
    corrected : bool, default True
        Match the confusion-corrected prediction ``C p`` ("matching") or the decoders'
        raw ``p`` ("simple").

    Attributes
    ----------
    log_likelihood : ndarray, shape (n_tasks,)
        Every task's log pseudo-likelihood within the current task segment.
    needs_class_scatters : bool
        Whether the history must keep per-class scatter matrices for it.
    """

    needs_class_scatters = False

    def __init__(self, n_tasks: int, corrected: bool = True) -> None:
        self.log_likelihood = np.zeros(n_tasks)
        self._corrected = corrected

    @property
    def name(self) -> str:
        """The likelihood in use (one of `LIKELIHOODS`)."""
        return "matching" if self._corrected else "simple"

    @property
    def corrects_confusion(self) -> bool:
        """Whether the decoders' cross-validated confusion matrices are needed."""
        return self._corrected

    def predict(self, models: TaskModels, signals: np.ndarray) -> np.ndarray:
        """The class probabilities this likelihood matches, of signals (n, d): (n_tasks, n, K)."""
        if self.corrects_confusion:
            return models.corrected_proba(signals)
        return models.proba(signals)

    def take(
        self, expected: np.ndarray, predicted: np.ndarray | None, temperature: float = 1.0
    ) -> None:
        """A new signal: every task's expected label distribution (n_tasks, K) and the
        prediction of it (n_tasks, K) by the decoders trained before it (None before any
        decoder: the first signal adds nothing); its log match is multiplied by
        ``temperature`` (the calibrated evidence's,
        `calibration_free.evidence_temperature`)."""
        if predicted is not None:
            self.log_likelihood += temperature * log_match(expected, predicted)

    def after_signal(self, history: TaskHistory, models: ModelsSource) -> None:
        """The new signal has joined ``history`` (and any target switch is done)."""

    def restart(self) -> None:
        """A target was reached: a new task segment starts."""
        self.log_likelihood[:] = 0.0

    def decision_rule(self) -> tuple[str, float] | None:
        """(confidence rule, threshold) this likelihood imposes, or None for the
        configured ones."""
        return None


class BatchMatching(TaskLikelihood):
    """Eq. matchingoverfitting: the segment's matches recomputed with the latest decoders."""

    def __init__(self, n_tasks: int) -> None:
        super().__init__(n_tasks, corrected=False)
        self._expected: list[np.ndarray] = []

    @property
    def name(self) -> str:
        return "batch"

    def take(
        self, expected: np.ndarray, predicted: np.ndarray | None, temperature: float = 1.0
    ) -> None:
        self._expected.append(expected)

    def after_signal(self, history: TaskHistory, models: ModelsSource) -> None:
        if not self._expected:
            return
        segment = history.signals[history.n_signals - len(self._expected) :]
        expected = np.stack(self._expected, axis=1)  # (n_tasks, n, K)
        self.log_likelihood[:] = log_match(expected, models().proba(segment)).sum(axis=1)

    def restart(self) -> None:
        super().restart()
        self._expected.clear()


class UntilFirstTarget(TaskLikelihood):
    """A scoring of its own until the first target, then the matching filter for good.

    Until the first target a task is declared when its normalised likelihood exceeds
    ``threshold``, whatever the configured confidence rule; subclasses name the scoring
    (`first_name`) and update the scores from the history after every signal
    (`score_history`).

    Parameters
    ----------
    n_tasks : int
    threshold : float
    """

    first_name: str

    def __init__(self, n_tasks: int, threshold: float) -> None:
        super().__init__(n_tasks, corrected=True)
        self.threshold = threshold
        self.switched = False

    @property
    def name(self) -> str:
        return "matching" if self.switched else self.first_name

    def take(
        self, expected: np.ndarray, predicted: np.ndarray | None, temperature: float = 1.0
    ) -> None:
        if self.switched:
            super().take(expected, predicted, temperature)

    def after_signal(self, history: TaskHistory, models: ModelsSource) -> None:
        if not self.switched:
            self.score_history(history)

    def score_history(self, history: TaskHistory) -> None:
        """Update `log_likelihood` now that the newest signal has joined ``history``."""
        raise NotImplementedError

    def restart(self) -> None:
        super().restart()
        self.switched = True

    def decision_rule(self) -> tuple[str, float] | None:
        return None if self.switched else ("normalised", self.threshold)


class BhattacharyyaOverlap(UntilFirstTarget):
    """The overlap pseudo-likelihood until the first target (declared above
    `BHATTACHARYYA_THRESHOLD`), then the matching filter.

    Parameters
    ----------
    n_tasks : int
    shrinkage : float
        Shrinkage of the class covariances.
    """

    first_name = "bhattacharyya"
    needs_class_scatters = True

    def __init__(self, n_tasks: int, shrinkage: float) -> None:
        super().__init__(n_tasks, BHATTACHARYYA_THRESHOLD)
        self.shrinkage = shrinkage

    @property
    def corrects_confusion(self) -> bool:
        return self.switched

    def score_history(self, history: TaskHistory) -> None:
        statistics, _ = history.class_statistics(with_folds=False)
        if np.all(defined_classes(statistics)):
            rho = overlap_of_classes(statistics, self.shrinkage)
            self.log_likelihood += overlap_log_factor(rho)


class FirstTargetGaussianEvidence(UntilFirstTarget):
    """The Gaussian evidence of every task's labelling until the first target (declared
    above ``threshold``), then the matching filter.

    Until the first target the decoders are still fitted, cross-validated and corrected by
    their confusion at every signal, as for the matching filter: the planner samples
    their predictions and the first-target shrinkage is chosen on them; only the scores
    come from the evidence.
    """

    first_name = "gaussian-evidence"

    def score_history(self, history: TaskHistory) -> None:
        # Tasks whose labels agree on every signal share their evidence: once per labelling.
        labelling, representatives = history.labellings
        statistics = history.pooled_statistics(with_folds=False, tasks=representatives)
        self.log_likelihood[:] = log_evidence(statistics)[labelling]


def make_likelihood(
    kind: str,
    n_tasks: int,
    shrinkage: float,
    first_target_evidence: str,
    evidence_beta: float,
) -> TaskLikelihood:
    """A fresh likelihood of kind ``kind`` (one of `LIKELIHOODS`) for ``n_tasks``;
    with ``first_target_evidence="gaussian"`` (the "matching" kind only), preceded by the
    Gaussian evidence until the first target, declared above ``evidence_beta``."""
    check_option("likelihood", kind, LIKELIHOODS)
    check_option("first_target_evidence", first_target_evidence, FIRST_TARGET_EVIDENCE)
    if first_target_evidence == "gaussian":
        if kind != "matching":
            raise ValueError(
                "first_target_evidence 'gaussian' precedes the matching filter: it needs "
                f"likelihood 'matching'; got {kind!r}"
            )
        return FirstTargetGaussianEvidence(n_tasks, evidence_beta)
    if kind == "batch":
        return BatchMatching(n_tasks)
    if kind == "bhattacharyya":
        return BhattacharyyaOverlap(n_tasks, shrinkage)
    return TaskLikelihood(n_tasks, corrected=kind == "matching")
