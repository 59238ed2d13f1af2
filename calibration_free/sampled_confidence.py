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

from dataclasses import dataclass

import numpy as np
from scipy.special import log_softmax, ndtr

from decoding.statistics import ClassStatistics, shrink_towards_identity, spd_inverse


def soft_class_statistics(signals: np.ndarray, weights: np.ndarray) -> ClassStatistics:
    """Class statistics of every hypothesis's soft labels, by matrix products.

    Parameters
    ----------
    signals : ndarray, shape (*S, n, d)
    weights : ndarray, shape (*S, H, n, K)
        ``S``: optional leading axes, each entry its own signals (e.g. the folds of a
        cross-validation).

    Returns
    -------
    ClassStatistics
        Batch shape (*S, H): counts (*S, H, K), sums (*S, H, K, d), scatters
        (*S, H, K, d, d).
    """
    d = signals.shape[-1]
    by_class = np.swapaxes(weights, -1, -2)  # (*S, H, K, n)
    outer = (signals[..., :, None] * signals[..., None, :]).reshape(*signals.shape[:-1], d * d)
    return ClassStatistics(
        counts=by_class.sum(axis=-1),
        sums=by_class @ signals[..., None, :, :],
        scatters=(by_class @ outer[..., None, :, :]).reshape(*by_class.shape[:-1], d, d),
    )


def shrunk_class_moments(
    statistics: ClassStatistics, signals: np.ndarray, shrinkage: float
) -> tuple[np.ndarray, np.ndarray]:
    """Class means and shrunk class covariances of every hypothesis.

    Parameters
    ----------
    statistics : ClassStatistics
        ``soft_class_statistics(signals, weights)``, weights (n_hypotheses, n, K) being the
        soft labels of each signal under each hypothesis (computed once by the caller, who
        shares them with the uncertainty map).
    signals : ndarray, shape (n, d)
    shrinkage : float
        Weight of the scaled identity (see `decoding.statistics.shrink_towards_identity`).

    Returns
    -------
    means : ndarray, shape (n_hypotheses, K, d)
    covariances : ndarray, shape (n_hypotheses, K, d, d)
        Weighted (biased) covariances, shrunk; a class with no weight gets the covariance
        of all signals.
    """
    means, covariances = statistics.class_moments()
    empty = statistics.counts <= np.finfo(float).eps
    if np.any(empty):
        covariances[empty] = np.cov(signals, rowvar=False, bias=True)
    return means, shrink_towards_identity(covariances, shrinkage)


@dataclass(frozen=True)
class SampledClassifiers:
    """Gaussian classifiers drawn from the class posteriors, laid out batch last: class,
    hypothesis, draw (K, H, J), so that each class's densities are one contiguous block.

    Attributes
    ----------
    means : ndarray, shape (d, K, H, J)
    factors : ndarray, shape (d, d, K, H, J)
        Lower-triangular ``B`` with precision ``B B^T`` (Bartlett decomposition).
    log_det : ndarray, shape (K, H, J)
        Log-determinant of each precision.
    """

    means: np.ndarray
    factors: np.ndarray
    log_det: np.ndarray


def sample_classifiers(
    means: np.ndarray,
    covariances: np.ndarray,
    n_signals: int,
    n_draws: int,
    rng: np.random.Generator,
) -> SampledClassifiers:
    """Draw ``n_draws`` Gaussian classifiers from the Jeffreys posterior of each class.

    Parameters
    ----------
    means : ndarray, shape (H, K, d)
    covariances : ndarray, shape (H, K, d, d)
    n_signals : int
        ``n``, the history's length; must exceed ``d``.
    n_draws : int
        ``J``.
    rng : Generator
        Draws the Bartlett factors' normals, then their chi-squares, then the means'
        normals and chi-squares, each as one array in the batch-last layout.
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
    chol_inverse = _batch_last(np.linalg.cholesky(spd_inverse(scale)[0]))  # (d, d, K, H)
    shape = (n_classes, n_hyp, n_draws)
    lower = np.tril_indices(d, k=-1)
    bartlett = np.zeros((d, d, *shape))
    bartlett[lower] = rng.standard_normal((len(lower[0]), *shape))
    degrees = (dof - np.arange(d)).reshape(d, 1, 1, 1)
    diagonal = np.sqrt(rng.chisquare(degrees, size=(d, *shape)))
    bartlett[np.arange(d), np.arange(d)] = diagonal
    factors = np.zeros_like(bartlett)
    for r, m in zip(*np.tril_indices(d), strict=True):  # B_r. = sum_{m <= r} L_rm A_m.
        factors[r, : m + 1] += chol_inverse[r, m, ..., None] * bartlett[m, : m + 1]
    log_det = 2 * (
        np.log(np.diagonal(chol_inverse)).sum(axis=-1)[..., None] + np.log(diagonal).sum(axis=0)
    )
    # mu ~ t_nu(mean, S / (n nu)): a Gaussian offset divided by sqrt(chi2_nu / nu).
    chol_scale = _batch_last(np.linalg.cholesky(scale / (n_signals * nu)))
    gaussian = rng.standard_normal((d, *shape))
    mixing = np.sqrt(rng.chisquare(nu, size=shape) / nu)
    offsets = np.einsum("rmkh,mkhj->rkhj", chol_scale, gaussian) / mixing
    return SampledClassifiers(_batch_last(means)[..., None] + offsets, factors, log_det)


def _batch_last(array: np.ndarray) -> np.ndarray:
    """(H, K, *trailing) -> (*trailing, K, H), contiguous."""
    moved = np.moveaxis(array, (0, 1), (-1, -2))
    return np.ascontiguousarray(moved)


def sampled_log_likelihoods(
    signals: np.ndarray, label_distributions: np.ndarray, classifiers: SampledClassifiers
) -> np.ndarray:
    """Batch matching log-likelihood of every hypothesis under every sampled classifier.

    Parameters
    ----------
    signals : ndarray, shape (n, d)
    label_distributions : ndarray, shape (H, n, K)
        ``p(l | x_i, t)`` of each hypothesis's frame at each step.
    classifiers : SampledClassifiers
        From `sample_classifiers`.

    Returns
    -------
    ndarray, shape (H, J)
    """
    n, d = signals.shape
    n_classes, n_hyp, n_draws = classifiers.log_det.shape
    centre = signals.mean(axis=0)  # the quadratic form is translation invariant
    signals = signals - centre
    means = classifiers.means.reshape(d, -1) - centre[:, None]
    upper, projected, offset = _precision_terms(classifiers.factors.reshape(d, d, -1), means)
    # (x - mu)^T P (x - mu) = x^T P x - 2 (P mu)^T x + mu^T P mu, with x^T P x summed over
    # the upper triangle of the symmetric P (off-diagonal terms twice): the first two
    # terms for every classifier and signal are one float32 matrix product with the
    # signals' pairwise products (d (d + 3) / 2 columns; rounding of about 1e-6 relative,
    # far below the sampling noise), and the densities stay float32 to the matching.
    row, column = np.triu_indices(d)
    upper *= np.where(row == column, 1.0, 2.0)[:, None]
    left = np.concatenate([upper, -2 * projected]).T.astype(np.float32)
    right = np.concatenate([signals[:, row] * signals[:, column], signals], axis=1)
    quadratic = left @ right.T.astype(np.float32)
    offset -= classifiers.log_det.reshape(-1)
    quadratic += offset.astype(np.float32)[:, None]
    quadratic *= np.float32(-0.5)
    log_density = quadratic.reshape(n_classes, n_hyp, n_draws, n)
    labels = np.moveaxis(label_distributions, 2, 0)[:, :, None].astype(np.float32)
    matched = _match(labels, log_density)
    # A signal no label of the frame allows (alpha = 0) under a draw sure of another
    # class: a finite penalty (log of float32's smallest normal, -87) rather than -inf.
    np.maximum(matched, np.finfo(np.float32).tiny, out=matched)
    return np.log(matched).sum(axis=-1, dtype=float)


def _precision_terms(
    factors: np.ndarray, means: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The precisions ``P = B B^T`` of lower-triangular factors ``B`` (d, d, N), batch last:
    their upper triangles (d (d + 1) / 2, N) in ``np.triu_indices`` order, ``P mu``
    (d, N) and ``mu^T P mu`` (N,) for means ``mu`` (d, N). Row by row over the whole
    batch (``P_rc = sum_{k <= r} B_rk B_ck`` for r <= c): numpy's batched product of
    small matrices costs about a microsecond per matrix."""
    d = factors.shape[0]
    upper = np.empty((d * (d + 1) // 2, factors.shape[-1]))
    start = 0
    for r in range(d):
        upper[start : start + d - r] = np.einsum(
            "kn,ckn->cn", factors[r, : r + 1], factors[r:, : r + 1]
        )
        start += d - r
    whitened = np.einsum("kin,kn->in", factors, means)  # B^T mu
    return upper, np.einsum("ikn,kn->in", factors, whitened), np.square(whitened).sum(axis=0)


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
        `pairwise_normal_difference` of the mean and unbiased variance over draws of
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
