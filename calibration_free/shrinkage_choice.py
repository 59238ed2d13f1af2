"""The decoders' shrinkage chosen from the data (``LearnerConfig.shrinkage="cv"``).

The learner tells tasks apart by the matching evidence its decoders give: per signal, the
log match of the label a task expects against that of the other labels
(`calibration_free.likelihood`). A task's score pulls away from the others sooner
when that evidence is large *relative to its spread*. So the shrinkage that serves the
learner is the one whose decoders give the most discriminating evidence, measured as the
learner computes it: out-of-fold (signal ``i`` in fold ``i % n_folds``),
confusion-corrected, tempered by the user error rate ``eps``, on labels the learner trusts
(the history it adopted at its targets).

`evidence_discriminability` measures it for a grid of shrinkages;
`choose_shrinkage` picks the heaviest that is not clearly worse than the best (the
grid's floor and the margin are the learner settings ``shrinkage_floor`` and
``shrinkage_margin``); before the first target it is made on the leading task's labels
(``first_target_shrinkage="cv"``: `FIRST_TARGET_GRID`). The grid after the first
target stops at the fixed default, 0.5: where the data show no clear gain from less
shrinkage (the synthetic ErrP data) the learner keeps its tuned default, and where they do
(correlated features whose class difference is spread over weak directions: the mixed
Gaussian signals of `acquisition.gaussian`, and the real ErrP features of ``s4.mat``)
it takes less. README: "Issue 13's levers".
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calibration_free.likelihood import confusion_matrices, corrected_proba, label_log_matches
from calibration_free.task_decoders import TaskHistory, in_signal_order
from decoding.lda import MIN_CLASS_COUNT, fit_pooled_lda
from decoding.scatter_eigen import ScatterEigen
from decoding.statistics import at_least

#: The setting's value that asks for the choice.
CHOSEN_SHRINKAGE = "cv"
#: The shrinkages the choice is made among by default: none heavier than the fixed default,
#: 0.5 (heavier ones after the first target were measured to commit wrongly more often), down
#: to 0.01 (the mixed Gaussian tuning signals chose 0.05 at most targets when it was the
#: floor; with 0.01 they choose 0.02 most: README, "The shrinkage choice's grid and
#: margin"). The setting ``shrinkage_floor`` keeps its values from a floor up
#: (`shrinkage_grid`).
SHRINKAGE_GRID: tuple[float, ...] = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5)
#: How far below the best evidence a heavier shrinkage may be and still be chosen, in
#: standard errors of that evidence, by default (the setting ``shrinkage_margin``; tuned on
#: synthetic data, seeds 100-139 and 100-199: 1, the textbook's rule, left the mixed Gaussian
#: signals 0.6-1.1 correct targets per session short of 0.5, and 0 lost the ErrP data 0.5
#: target: README, "The shrinkage choice's grid and margin").
STANDARD_ERRORS = 0.5


#: The shrinkages chosen among until the first target (``first_target_shrinkage="cv"``),
#: before any label is trusted: on the leading task's labels, every
#: `FIRST_CHOICE_PERIOD` signals from the `FIRST_CHOICE_START`-th, the heaviest
#: within `FIRST_TARGET_STANDARD_ERRORS` of the best. Heavier than after the first
#: target (few signals, many mislabelled), and a wider margin: a leader's labels may be
#: wrong, and the choice must not follow their noise (tuned on synthetic data, seeds
#: 100-199: README, "A first-target shrinkage chosen from the data").
FIRST_TARGET_GRID: tuple[float, ...] = (0.3, 0.5, 0.7, 0.9)
#: The first-target choice's margin, in standard errors (after the first target: 0.5).
FIRST_TARGET_STANDARD_ERRORS = 1.0
#: The signal count of the first choice (before it, 0.9: the grid's heaviest).
FIRST_CHOICE_START = 40
#: Signals between two choices until the first target.
FIRST_CHOICE_PERIOD = 5


def shrinkage_grid(floor: float) -> tuple[float, ...]:
    """`SHRINKAGE_GRID`'s intensities from ``floor`` up (at least its heaviest, 0.5)."""
    return tuple(s for s in SHRINKAGE_GRID if s >= min(floor, SHRINKAGE_GRID[-1]))


def evidence_discriminability(
    history: TaskHistory,
    task: int,
    shrinkages: tuple[float, ...],
    *,
    eps: float,
    smoothing: float,
    balanced: bool = True,
) -> np.ndarray:
    """The cross-validated matching evidence's mean over its spread, per shrinkage.

    For every signal ``i`` of ``history`` of true class ``k`` (``task``'s label weight
    ``w_ik``) and every other class ``l``, the increment ``log m_k(i) - log m_l(i)``:
    ``m_c = sum_j E_cj q_j`` is the match of the label ``c`` expected with certainty ``1 -
    eps`` (``eps`` spread over the other classes) against the out-of-fold (the history's
    folds), confusion-corrected prediction ``q`` of the pooled LDA at that shrinkage. The
    result is the increments' mean over the classes (each class's weighted mean, then their
    average) divided by their pooled within-class standard deviation. The history's
    statistics are used as they are (its decomposed scatters too, if it keeps them).

    Parameters
    ----------
    history : TaskHistory
    task : int
        Whose labels are the truth.
    shrinkages : tuple of float
        Fixed intensities in [0, 1].
    eps, smoothing, balanced
        The learner's user error rate, confusion smoothing and balancing.

    Returns
    -------
    ndarray, shape (len(shrinkages),)
        NaN for every shrinkage when a class has less than ``MIN_CLASS_COUNT`` weight in
        some fold's training set (no decoder knows it) or the increments do not vary.
    """
    # The task's labelling once per shrinkage: every intensity fitted in one call.
    statistics = history.pooled_statistics(tasks=np.full(len(shrinkages), task))
    if not np.all(at_least(statistics.counts, MIN_CLASS_COUNT)):
        return np.full(len(shrinkages), np.nan)
    if statistics.eigen is None:  # decomposed once for every shrinkage
        eigenvalues, basis = np.linalg.eigh(statistics.scatter)
        pending = np.zeros((eigenvalues.shape[0], 0, eigenvalues.shape[1]))  # none
        statistics = replace(statistics, eigen=ScatterEigen(basis, eigenvalues, pending))
    weights = history.task_label_weights(task)
    present = np.ones((1, weights.shape[1]), dtype=bool)
    result = np.full(len(shrinkages), np.nan)
    folds = fit_pooled_lda(statistics, np.asarray(shrinkages, dtype=float))
    by_fold = history.cross_validated_proba(folds.select(slice(0, -1)))
    for index in range(len(shrinkages)):
        proba = in_signal_order(by_fold, history.n_signals, task=index)  # (n, K)
        confusion = confusion_matrices((weights.T @ proba)[None], present, smoothing, balanced)
        corrected = corrected_proba(confusion, proba[None])[0]
        result[index] = _mean_over_spread(label_log_matches(corrected, eps), weights)
    return result


def choose_shrinkage(
    history: TaskHistory,
    task: int,
    *,
    eps: float,
    smoothing: float,
    balanced: bool = True,
    grid: tuple[float, ...] = SHRINKAGE_GRID,
    margin: float = STANDARD_ERRORS,
) -> float | None:
    """The heaviest shrinkage of ``grid`` whose evidence is within ``margin`` standard errors
    (default `STANDARD_ERRORS`, 0.5) of the most discriminating
    (`evidence_discriminability` of ``task``'s labels of ``history``), or None when
    it cannot be measured (a class too rare).

    The one-standard-error rule of cross-validation (Hastie, Tibshirani and Friedman, *The
    Elements of Statistical Learning*, §7.10), by default with half the margin: the most
    regularised model that the data do not clearly reject. The standard error of a mean-over-spread
    ``r`` estimated from ``n`` labelled signals (the label weights' sum) is about ``sqrt((1
    + r^2 / 2) / n)``.
    """
    scores = evidence_discriminability(
        history, task, grid, eps=eps, smoothing=smoothing, balanced=balanced
    )
    if np.all(np.isnan(scores)):
        return None
    best = np.nanmax(scores)
    labelled = history.task_label_weights(task).sum()
    tolerance = margin * np.sqrt((1.0 + best**2 / 2.0) / labelled)
    return max(s for s, score in zip(grid, scores, strict=True) if score >= best - tolerance)


def labelled_history(
    signals: np.ndarray, weights: np.ndarray, n_folds: int = 10
) -> TaskHistory:
    """A one-task history of ``signals`` (n, d) labelled by ``weights`` (n, K), for the
    functions above outside a learner (analyses, tests)."""
    signals = np.asarray(signals, dtype=float)
    weights = np.asarray(weights, dtype=float)
    if signals.ndim != 2 or weights.ndim != 2 or len(signals) != len(weights):
        raise ValueError(
            f"signals (n, d) and weights (n, K) must have the same n; got shapes "
            f"{signals.shape} and {weights.shape}"
        )
    if weights.shape[1] < 2:
        raise ValueError(f"weights need at least two classes; got shape {weights.shape}")
    history = TaskHistory(1, weights.shape[1], signals.shape[1], n_folds)
    for signal, row in zip(signals, weights, strict=True):
        history.add(signal, row[None])
    return history


def _mean_over_spread(log_matches: np.ndarray, weights: np.ndarray) -> float:
    """Increments ``log m_k - log m_l`` (true class ``k``, ``l != k``) of signals with class
    weights ``weights`` (n, K): class-balanced mean over pooled within-class SD."""
    n_classes = weights.shape[1]
    means, variances = [], []
    for k in range(n_classes):
        increments = log_matches[:, k : k + 1] - np.delete(log_matches, k, axis=1)
        w = np.repeat(weights[:, k : k + 1], n_classes - 1, axis=1)
        mean = np.sum(w * increments) / np.sum(w)
        means.append(mean)
        variances.append(np.sum(w * (increments - mean) ** 2) / np.sum(w))
    spread = np.sqrt(np.mean(variances))
    return float(np.mean(means) / spread) if spread > 0 else float("nan")
