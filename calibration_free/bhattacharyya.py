"""The Bhattacharyya overlap likelihood of method-extensions §1 (thesis §7.3).

Under each task hypothesis the history splits into two classes (feedback: correct,
error). A labelling that agrees with the data's structure leaves little overlap between
the two class Gaussians: with the Bhattacharyya coefficient ``rho = exp(-D_B)`` of the
two (shrunk) class Gaussians, ``1 - rho`` stands for the expected classification rate,
and the pseudo-likelihood accumulates one factor per step, each computed from all the data
up to that step: ``log L_t += log(1 - rho_t + tiny)``. The thesis declares a task when its
normalised likelihood ``L_t / sum_u L_u`` exceeds 0.99, then switches to the matching
filter for good (once hypotheses share most labels their overlaps stop discriminating).

Regularisation (not stated in §7.3): the BCI chapter's shrinkage 0.5 towards the scaled
identity. Log-determinants keep ``D_B`` stable in 34 dimensions.
"""

from __future__ import annotations

import numpy as np

from decoding.statistics import ClassStatistics, shrink_towards_identity


def bhattacharyya_coefficient(means: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """``rho = exp(-D_B)`` of two Gaussians, batched.

    Parameters
    ----------
    means : ndarray, shape (*B, 2, d)
    covariances : ndarray, shape (*B, 2, d, d)
        Symmetric positive definite.

    Returns
    -------
    ndarray, shape (*B,)
        In (0, 1]; 1 for identical Gaussians. With
        ``S = (S_0 + S_1) / 2``: ``D_B = (m_0 - m_1)^T S^-1 (m_0 - m_1) / 8
        + (ln det S - (ln det S_0 + ln det S_1) / 2) / 2``.
    """
    average = covariances.mean(axis=-3)
    gap = means[..., 0, :] - means[..., 1, :]
    mahalanobis = np.einsum("...i,...i->...", gap, np.linalg.solve(average, gap[..., None])[..., 0])
    _, log_det_average = np.linalg.slogdet(average)
    _, log_det_classes = np.linalg.slogdet(covariances)
    distance = mahalanobis / 8 + 0.5 * (log_det_average - log_det_classes.mean(axis=-1))
    return np.minimum(np.exp(-distance), 1.0)


def overlap_per_task(
    signals: np.ndarray, label_weights: np.ndarray, shrinkage: float
) -> np.ndarray:
    """Bhattacharyya coefficient of every task's two class Gaussians on the history.

    Parameters
    ----------
    signals : ndarray, shape (n, d)
    label_weights : ndarray, shape (n_tasks, n, 2)
        Each task's label weights of the signals (correct, error).
    shrinkage : float

    Returns
    -------
    ndarray, shape (n_tasks,)
        1 (no information) for a task with a class of fewer than two signals' weight.
    """
    statistics = ClassStatistics.from_signals(signals, np.swapaxes(label_weights, 0, 1))
    return overlap_of_classes(statistics, shrinkage)


def overlap_of_classes(statistics: ClassStatistics, shrinkage: float) -> np.ndarray:
    """Bhattacharyya coefficient of the two class Gaussians of every labelling.

    ``statistics`` has batch shape (n_tasks,) and two classes; returns (n_tasks,), 1 (no
    information) for a labelling with a class of fewer than two signals' weight (see
    `defined_classes`).
    """
    means, covariances = statistics.class_moments()
    covariances = shrink_towards_identity(covariances, shrinkage)
    defined = defined_classes(statistics)
    covariances[~defined] = np.eye(means.shape[-1])
    return np.where(defined, bhattacharyya_coefficient(means, covariances), 1.0)


def defined_classes(statistics: ClassStatistics) -> np.ndarray:
    """Labellings whose every class has at least two signals' weight, shape (n_tasks,)."""
    return np.all(statistics.counts >= 2, axis=-1)


def overlap_log_factor(rho: np.ndarray) -> np.ndarray:
    """``log(1 - rho + tiny)``: one step's factor of the overlap pseudo-likelihood (<= 0)."""
    return np.log1p(-rho + np.finfo(float).tiny)
