"""Confidence from classifiers sampled from the decoder's posterior (method-extensions §3).

Per hypothesis, each class's Gaussian (weighted mean and shrunk weighted covariance of the
history under the hypothesis's soft labels) gets the Jeffreys-prior posterior of the thesis
code, with ``n`` the total number of signals for every class and ``nu = n - d``:

* ``Sigma_l ~ InverseWishart(S_l, n - 1)`` with ``S_l = Sigma_hat_l (n - 1)``,
* ``mu_l ~ t_nu(mean_l, S_l / (n nu))``.

Each of ``J`` draws is a plain Gaussian classifier with equal class priors. A hypothesis's
log-likelihood under draw ``j`` is the batch matching of the whole history (no confusion
matrix): ``sum_i log(sum_k p(l_k | x_i, t) p_j(l_k | e_i))``. Normalised across
hypotheses within each draw, the ``J`` values give a mean ``m_t`` and an unbiased variance
``v_t`` per hypothesis; the confidence that ``t`` beats ``u`` is the normal-difference
probability ``Phi((m_t - m_u) / sqrt(v_t + v_u))`` and ``W_t = min_{u != t}`` of it.
"""

from __future__ import annotations

import numpy as np
from scipy.special import log_softmax, ndtr

from decoding.statistics import ClassStatistics, shrink_towards_identity


def soft_class_statistics(signals: np.ndarray, weights: np.ndarray) -> ClassStatistics:
    """Class statistics of every hypothesis's soft labels, by matrix products.

    Parameters
    ----------
    signals : ndarray, shape (n, d)
    weights : ndarray, shape (H, n, K)

    Returns
    -------
    ClassStatistics
        Batch shape (H,): counts (H, K), sums (H, K, d), scatters (H, K, d, d).
    """
    n, d = signals.shape
    by_class = np.swapaxes(weights, 1, 2)  # (H, K, n)
    outer = (signals[:, :, None] * signals[:, None, :]).reshape(n, d * d)
    return ClassStatistics(
        counts=by_class.sum(axis=-1),
        sums=by_class @ signals,
        scatters=(by_class @ outer).reshape(*by_class.shape[:2], d, d),
    )


def weighted_class_moments(
    signals: np.ndarray, weights: np.ndarray, shrinkage: float
) -> tuple[np.ndarray, np.ndarray]:
    """Class means and shrunk class covariances of every hypothesis.

    Parameters
    ----------
    signals : ndarray, shape (n, d)
    weights : ndarray, shape (n_hypotheses, n, K)
        Soft labels of each signal under each hypothesis.
    shrinkage : float
        Weight of the scaled identity (see :func:`decoding.statistics.shrink_towards_identity`).

    Returns
    -------
    means : ndarray, shape (n_hypotheses, K, d)
    covariances : ndarray, shape (n_hypotheses, K, d, d)
        Weighted (biased) covariances, shrunk; a class with no weight gets the covariance
        of all signals.
    """
    statistics = soft_class_statistics(signals, weights)
    means, covariances = statistics.class_moments()
    empty = statistics.counts <= np.finfo(float).eps
    if np.any(empty):
        covariances[empty] = np.cov(signals, rowvar=False, bias=True)
    return means, shrink_towards_identity(covariances, shrinkage)


def sample_classifiers(
    means: np.ndarray,
    covariances: np.ndarray,
    n_signals: int,
    n_draws: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw Gaussian classifiers from the Jeffreys posterior of each class.

    Parameters
    ----------
    means : ndarray, shape (H, K, d)
    covariances : ndarray, shape (H, K, d, d)
    n_signals : int
        ``n``, the history's length; must exceed ``d``.
    n_draws : int
        ``J``.
    rng : Generator
        Draws the Bartlett factors, then the mean offsets.

    Returns
    -------
    sampled_means : ndarray, shape (H, J, K, d)
    precision_factors : ndarray, shape (H, J, K, d, d)
        Lower-triangular ``B`` with precision ``B B^T`` (Bartlett decomposition).
    log_det_precision : ndarray, shape (H, J, K)
    """
    n_hyp, n_classes, d = means.shape
    if n_signals <= d:
        raise ValueError(
            f"sampled classifiers need more signals than dimensions ({n_signals} <= {d})"
        )
    dof = n_signals - 1
    nu = n_signals - d
    scale = covariances * dof  # S_l
    # Precision ~ Wishart(S^-1, n - 1): B = L A with L = chol(S^-1), A Bartlett-lower.
    chol_inverse = np.linalg.cholesky(np.linalg.inv(scale))  # (H, K, d, d)
    shape = (n_hyp, n_draws, n_classes)
    bartlett = np.zeros((*shape, d, d))
    bartlett[(..., *np.tril_indices(d, k=-1))] = rng.standard_normal((*shape, d * (d - 1) // 2))
    diagonal = np.sqrt(rng.chisquare(dof - np.arange(d), size=(*shape, d)))
    index = np.arange(d)
    bartlett[..., index, index] = diagonal
    factors = chol_inverse[:, None] @ bartlett
    log_det = 2 * (
        np.log(np.diagonal(chol_inverse, axis1=-2, axis2=-1)).sum(-1)[:, None]
        + np.log(diagonal).sum(-1)
    )
    # mu ~ t_nu(mean, S / (n nu)): a Gaussian offset divided by sqrt(chi2_nu / nu).
    chol_scale = np.linalg.cholesky(scale / (n_signals * nu))
    gaussian = rng.standard_normal((*shape, d))
    mixing = np.sqrt(rng.chisquare(nu, size=(*shape, 1)) / nu)
    offsets = (chol_scale[:, None] @ gaussian[..., None])[..., 0] / mixing
    return means[:, None] + offsets, factors, log_det


def sampled_log_likelihoods(
    signals: np.ndarray,
    label_distributions: np.ndarray,
    sampled_means: np.ndarray,
    precision_factors: np.ndarray,
    log_det_precision: np.ndarray,
) -> np.ndarray:
    """Batch matching log-likelihood of every hypothesis under every sampled classifier.

    Parameters
    ----------
    signals : ndarray, shape (n, d)
    label_distributions : ndarray, shape (H, n, K)
        ``p(l | x_i, t)`` of each hypothesis's frame at each step.
    sampled_means, precision_factors, log_det_precision
        From :func:`sample_classifiers`.

    Returns
    -------
    ndarray, shape (H, J)
    """
    n, d = signals.shape
    n_hyp, n_draws, n_classes = sampled_means.shape[:3]
    centre = signals.mean(axis=0)  # the quadratic form is translation invariant
    signals, sampled_means = signals - centre, sampled_means - centre
    # Classifiers ordered class first, (K, H, J), so that each class's densities are one
    # contiguous block of the product below.
    factors = np.moveaxis(precision_factors, 2, 0)
    flat = (factors @ np.swapaxes(factors, -1, -2)).reshape(-1, d, d)  # precisions
    means = np.moveaxis(sampled_means, 2, 0).reshape(-1, d)
    # (x - mu)^T P (x - mu) = x^T P x - 2 (P mu)^T x + mu^T P mu, with x^T P x summed over
    # the upper triangle of the symmetric P (off-diagonal terms twice): the first two
    # terms for every classifier and signal are one float32 matrix product with the
    # signals' pairwise products (d (d + 3) / 2 columns; rounding of about 1e-6 relative,
    # far below the sampling noise), and the densities stay float32 to the matching.
    row, column = np.triu_indices(d)
    projected = np.einsum("bij,bj->bi", flat, means)
    left = np.concatenate(
        [flat[:, row, column] * np.where(row == column, 1.0, 2.0), -2 * projected], axis=1
    )
    right = np.concatenate([signals[:, row] * signals[:, column], signals], axis=1)
    quadratic = left.astype(np.float32) @ right.T.astype(np.float32)
    offset = np.einsum("bi,bi->b", projected, means) - np.moveaxis(
        log_det_precision, 2, 0
    ).reshape(-1)
    quadratic += offset.astype(np.float32)[:, None]
    quadratic *= np.float32(-0.5)
    log_density = quadratic.reshape(n_classes, n_hyp, n_draws, n)
    labels = np.moveaxis(label_distributions, 2, 0)[:, :, None].astype(np.float32)
    matched = _match(labels, log_density)
    # A signal no label of the frame allows (alpha = 0) under a draw sure of another
    # class: a finite penalty (log of float32's smallest normal, -87) rather than -inf.
    np.maximum(matched, np.finfo(np.float32).tiny, out=matched)
    return np.log(matched).sum(axis=-1, dtype=float)


def _match(label_distributions: np.ndarray, log_density: np.ndarray) -> np.ndarray:
    """``sum_k p(l_k | x_i, t) p_j(l_k | e_i)`` with ``p_j`` the softmax of ``log_density``
    (K, H, J, n) over its class axis (equal priors); ``label_distributions`` (K, H, 1, n).
    Returns (H, J, n), in the inputs' dtype. Elementwise over the K classes: numpy's
    reductions over a short axis are several times slower."""
    top = log_density[0].copy()
    for log_class in log_density[1:]:
        np.maximum(top, log_class, out=top)
    total = np.zeros_like(top)
    matched = np.zeros_like(top)
    density = np.empty_like(top)
    for labels, log_class in zip(label_distributions, log_density, strict=True):
        np.subtract(log_class, top, out=density)
        np.exp(density, out=density)
        total += density
        density *= labels
        matched += density
    matched /= total
    return matched


def normal_difference_confidence(log_likelihoods: np.ndarray) -> np.ndarray:
    """``W_t`` of every hypothesis from its log-likelihood under every sampled classifier.

    Parameters
    ----------
    log_likelihoods : ndarray, shape (H, J)

    Returns
    -------
    ndarray, shape (H,)
        :func:`pairwise_normal_difference` of the mean and unbiased variance over draws of
        the likelihoods normalised across hypotheses within each draw.
    """
    normalised = np.exp(log_softmax(log_likelihoods, axis=0))  # P_t^(j), per draw
    return pairwise_normal_difference(normalised.mean(axis=1), normalised.var(axis=1, ddof=1))


def pairwise_normal_difference(mean: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """``W_t = min_{u != t} Phi((m_t - m_u) / sqrt(v_t + v_u))``.

    Parameters
    ----------
    mean, variance : ndarray, shape (H,)

    Returns
    -------
    ndarray, shape (H,)
        In [0, 1]; at most one hypothesis exceeds 0.5. Where ``v_t + v_u = 0`` the pair's
        confidence is 1, 0.5 or 0 by the sign of ``m_t - m_u``.
    """
    gap = mean[:, None] - mean[None, :]
    spread = np.sqrt(variance[:, None] + variance[None, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        pairwise = np.where(spread > 0, ndtr(gap / spread), 0.5 * (1 + np.sign(gap)))
    np.fill_diagonal(pairwise, np.inf)
    return pairwise.min(axis=1)
