"""The signal-space uncertainty of method-extensions §1(a)7 and §6.3 (the code's
``'signal_trace'``): how far apart the hypotheses' *expected signals* are at each (s, a).

For each (s, a) and task t, take the frame's most probable label ``l*_t(s, a)`` and the mean
``mu_t(s, a)`` of that class in task t's decoder; the uncertainty is the trace of the weighted
covariance of those means,

    U(s, a) = sum_t w_t ||mu_t(s, a) - mu_bar(s, a)||^2,   mu_bar = sum_t w_t mu_t(s, a),

which equals ``(1/2) sum_tu w_t w_u ||mu_t - mu_u||^2`` (the thesis's ``-sum_ij S_ij w_i w_j``
with ``S_ij = -||mu_i - mu_j||^2 / 2``). It is computed as ``sum_t w_t ||mu_t||^2 -
||mu_bar||^2``, one matrix product per class, without forming the (T, S, A, d) means.
"""

from __future__ import annotations

import numpy as np

#: Indicator elements built at a time (bounds the temporaries' size).
_CHUNK_ELEMENTS = 1 << 22


def signal_space_uncertainty(
    class_means: np.ndarray, most_probable: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """The signal-space uncertainty of every state and action.

    Parameters
    ----------
    class_means : ndarray, shape (n_tasks, n_classes, n_features)
        Each task decoder's class means.
    most_probable : ndarray of int, shape (n_tasks, n_states, n_actions)
        The frame's most probable label of each (s, a) under each task (any trailing
        shape: e.g. (n_tasks, n_states, 1) where labels do not depend on the action).
    weights : ndarray, shape (n_tasks,)
        Normalised task probabilities.

    Returns
    -------
    ndarray, shape ``most_probable.shape[1:]``
        Non-negative; 0 where every weighted task expects the same mean.
    """
    n_tasks, n_classes, n_features = class_means.shape
    shape = most_probable.shape[1:]
    flat = most_probable.reshape(n_tasks, -1)
    squared_norms = np.einsum("tkd,tkd->tk", class_means, class_means)
    weighted_means = weights[:, None, None] * class_means  # (T, K, d)
    uncertainty = np.empty(flat.shape[1])
    chunk = max(1, _CHUNK_ELEMENTS // n_tasks)
    for start in range(0, flat.shape[1], chunk):
        block = flat[:, start : start + chunk]
        second = np.zeros(block.shape[1])
        mean = np.zeros((n_features, block.shape[1]))
        for k in range(n_classes):
            chosen = (block == k).astype(float)  # (T, columns)
            second += (weights * squared_norms[:, k]) @ chosen
            mean += weighted_means[:, k].T @ chosen
        uncertainty[start : start + chunk] = second - np.einsum("ds,ds->s", mean, mean)
    return np.maximum(uncertainty, 0.0).reshape(shape)
