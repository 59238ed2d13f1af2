"""The matching pseudo-likelihood of method.md §3 (confusion correction, match) and the
confidence rules read from the tasks' log scores (the power prior:
`calibration_free.power_prior`)."""

from __future__ import annotations

import numpy as np

#: Pseudo-count added to every cell of a cross-validated confusion matrix before its columns
#: are normalised: with little data the correction stays close to "trust nothing".
DEFAULT_CONFUSION_SMOOTHING = 1.0
_TINY = np.finfo(float).tiny


def confusion_matrices(
    label_counts: np.ndarray,
    present: np.ndarray,
    smoothing: float,
    balanced: bool = True,
) -> np.ndarray:
    """Soft cross-validated confusion matrices, columns normalised.

    Parameters
    ----------
    label_counts : ndarray, shape (n_tasks, n_classes, n_classes)
        ``sum_i w_ik(t) p_ij(t)``: each task's (true) label weights of the signals against
        their out-of-fold predicted class probabilities (see
        `label_confusion_counts`).
    present : ndarray, shape (n_tasks, n_classes), bool
        Classes each task's decoder knows; the matrix is restricted to them (other rows
        and columns are 0).
    smoothing : float
        Pseudo-count added to every cell.
    balanced : bool, default True
        Weigh every true class equally before normalising the columns, as the decoders'
        equal priors do. Without it, ``p(true | predicted)`` carries the task's own label
        frequencies, and a task whose labels are mostly one class "matches" every signal
        with that class whatever the signal looks like.

    Returns
    -------
    confusion : ndarray, shape (n_tasks, n_classes, n_classes)
        ``confusion[t, i, j] = p(true label i | predicted j)``.
    """
    mask = present[:, :, None] & present[:, None, :]
    counts = np.where(mask, label_counts + smoothing, 0.0)
    if balanced:
        counts = counts / np.maximum(counts.sum(axis=2, keepdims=True), np.finfo(float).tiny)
    return counts / np.maximum(counts.sum(axis=1, keepdims=True), np.finfo(float).tiny)


def corrected_proba(confusion: np.ndarray, proba: np.ndarray) -> np.ndarray:
    """``q = C p``: label probabilities corrected by the confusion matrix.

    ``confusion`` (n_tasks, K, K), ``proba`` (n_tasks, n_signals, K) -> (n_tasks, n_signals, K).
    """
    return proba @ np.swapaxes(confusion, -1, -2)


def match(label_distribution: np.ndarray, corrected: np.ndarray) -> np.ndarray:
    """``m_t = sum_l p(l | s, a, t) q_t[l]`` for one signal: (n_tasks, K) x (n_tasks, K)."""
    return np.einsum("tk,tk->t", label_distribution, corrected)


def log_match(label_distribution: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """``log m``, batched over leading axes ((..., K) x (..., K) -> (...)), floored at the
    log of the smallest positive float so that a zero match (possible with ``eps = 0``)
    stays finite; the floor changes no match above about 1e-292."""
    matches = np.einsum("...k,...k->...", label_distribution, predicted)
    return np.log(np.maximum(matches, _TINY))


def label_log_matches(corrected: np.ndarray, eps: float) -> np.ndarray:
    """``log m_c`` of a signal for every class ``c`` as the label expected of it.

    Parameters
    ----------
    corrected : ndarray, shape (n_signals, K)
        Confusion-corrected class probabilities ``q``.
    eps : float
        The user error rate: the expected distribution of label ``c`` puts ``1 - eps`` on
        ``c`` and ``eps / (K - 1)`` on each other class.

    Returns
    -------
    ndarray, shape (n_signals, K)
        `log_match` of each label's expected distribution against ``q``.
    """
    n_classes = corrected.shape[1]
    expected = (1.0 - eps) * np.eye(n_classes) + eps / (n_classes - 1) * (
        1.0 - np.eye(n_classes)
    )
    return log_match(expected[None], corrected[:, None])


def pairwise_confidence(scores: np.ndarray) -> np.ndarray:
    """``W_t = min_{x != t} L_t / (L_t + L_x)`` from log scores, computed stably.

    ``W_t`` is the logistic of the gap between ``scores[t]`` and the best other score.
    ``scores`` (n_tasks,) -> (n_tasks,) in (0, 1).
    """
    order = np.argsort(scores)[::-1]
    best, second = scores[order[0]], scores[order[1]]
    best_other = np.full_like(scores, best)
    best_other[order[0]] = second
    gap = np.clip(scores - best_other, -700.0, 700.0)
    return 1.0 / (1.0 + np.exp(-gap))


def normalised_likelihood(scores: np.ndarray) -> np.ndarray:
    """``L_t / sum_u L_u`` from log scores (n_tasks,), computed stably (a softmax)."""
    weights = np.exp(scores - scores.max())
    return weights / weights.sum()


#: The confidence rules (``LearnerConfig.confidence``): log scores (n_tasks,) -> each
#: task's confidence (n_tasks,) in [0, 1], compared with the threshold ``beta``.
CONFIDENCES = {"pairwise": pairwise_confidence, "normalised": normalised_likelihood}
