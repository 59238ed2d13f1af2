"""Shrinkage linear discriminant analysis with a pooled covariance, for many labellings of
the same signals at once.

The model is the textbook Fisher LDA as scikit-learn fits it by default
(``LinearDiscriminantAnalysis(solver="lsqr", shrinkage=shrinkage)``, empirical priors):
the pooled within-class covariance ``W / N`` of the training set, shrunk towards the
identity scaled to its mean variance, ``Sigma = (1 - lambda) W / N + lambda tr(W) / (N d)
I``. Decisions are made with equal priors among the classes present:
``log p(k | x) = log_softmax(x Sigma^-1 mu_k - mu_k Sigma^-1 mu_k / 2 + log(1 / K))``,
i.e. scikit-learn's scores with ``log(1 / K) - log(prior_k)`` added.

Why it is cheap for many labellings (tasks): with uncentred scatter ``S`` of the training
set and class sums ``s_k`` and counts ``n_k``, ``W = S - sum_k s_k s_k^T / n_k``: one
shared ``S`` minus a rank-K correction per task. One eigendecomposition ``S = V diag(e)
V^T`` per training set makes ``c S + nu I`` (``c = (1 - lambda) / N``, ``nu`` a scalar
per task) diagonal for every task, and the rank-K correction is a K x K solve per task
(Woodbury identity). Decoders are kept in the basis ``V``: signals are projected once per
training set, and every task's scores are then one matrix product. A decomposition may
also be an earlier one plus the signals added since (`decoding.scatter_eigen`): those
join the Woodbury step, eliminated first.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from decoding.estimator import StatisticsClassifier
from decoding.scatter_eigen import ScatterEigen
from decoding.statistics import (
    EMPTY_WEIGHT,
    BatchedDecoders,
    ClassStatistics,
    PooledStatistics,
    at_least,
    log_softmax,
)
from decoding.validation import check_option

DEFAULT_SHRINKAGE = 0.5
#: Shrinkage intensities chosen from the data (besides a fixed number).
SHRINKAGE_RULES: tuple[str, ...] = ("oas",)
#: A class needs this much (weighted) data before a decoder that uses it is informative.
MIN_CLASS_COUNT = 2.0
#: Relative size of the smallest eigenvalue of ``Sigma``'s diagonal part below which a
#: decoder is solved by least squares instead (no shrinkage and fewer signals than
#: features), as scikit-learn's ``lsqr`` solver does.
_SINGULAR = 1e-12


@dataclass(frozen=True)
class PooledLinearDecoders(BatchedDecoders):
    """A batch of linear decoders over shared training sets, kept in each set's basis.

    ``log p(k | x) = log_softmax((x V) coef_k + intercept_k)``, batch shape ``(*J, *T)``
    (training sets, then tasks).

    Attributes
    ----------
    basis : ndarray, shape (*J, n_features, n_features)
        Orthonormal eigenvectors ``V`` of each training set's scatter (columns).
    coef : ndarray, shape (*J, *T, n_classes, n_features)
        ``V^T Sigma^-1 mu_k`` per task and class (0 for absent classes).
    intercept : ndarray, shape (*J, *T, n_classes)
        ``-mu_k Sigma^-1 mu_k / 2 + log(1 / K_present)``; -inf for absent classes.
    present : ndarray, shape (*J, *T, n_classes), bool
        Classes with at least ``MIN_CLASS_COUNT`` weight; the others get probability 0.
        A decoder with fewer than two present classes is uninformative (uniform).
    """

    basis: np.ndarray
    coef: np.ndarray
    intercept: np.ndarray
    present: np.ndarray

    def _scores(self, X: np.ndarray, coef: np.ndarray, intercept: np.ndarray) -> np.ndarray:
        """``(X V) coef + intercept`` with tasks last: (*J, n, *T, C).

        ``X`` (n, d), or (*J, 1.., n, d) with unit axes for the tasks; ``coef`` (*J, *T,
        C, d), ``intercept`` (*J, *T, C). Two matrix products per training set (BLAS reads
        ``coef`` transposed in place), in the cheaper order: the signals projected on the
        basis first when there are fewer of them than scores per signal (``n d^2 + n d
        TC`` operations), else the decoders taken out of the basis first (``d^2 TC + n d
        TC``).
        """
        n_sets = self.basis.ndim - 2
        X = np.asarray(X, dtype=float)
        if X.ndim > 2:  # the task axes broadcast: drop them
            X = X.reshape(*X.shape[: min(n_sets, X.ndim - 2)], *X.shape[-2:])
        flat = coef.reshape(*coef.shape[:n_sets], -1, coef.shape[-1])  # (*J, T*C, d)
        if X.shape[-2] <= flat.shape[-2]:
            scores = (X @ self.basis) @ np.swapaxes(flat, -1, -2)
        else:
            scores = X @ (self.basis @ np.swapaxes(flat, -1, -2))
        scores = scores.reshape(*scores.shape[:-1], *coef.shape[n_sets:-1])
        scores += intercept[(*(slice(None),) * n_sets, None)]
        return scores

    def _known_log_proba(self, X: np.ndarray) -> np.ndarray:
        n_sets = self.basis.ndim - 2
        scores = self._scores(X, self.coef, self.intercept)
        return log_softmax(np.moveaxis(scores, n_sets, -2))  # (*J, *T, n, K)

    def proba(self, X: np.ndarray) -> np.ndarray:
        """As `log_proba`, exponentiated; with two classes, from the score
        difference alone (half the products, one exponential)."""
        if self.present.shape[-1] != 2:
            return super().proba(X)
        n_sets = self.basis.ndim - 2
        # An informative two-class decoder knows both classes: every score is finite.
        informative = self.informative
        coef = self.coef[..., 1:, :] - self.coef[..., :1, :]
        with np.errstate(invalid="ignore"):  # -inf - -inf where uninformative
            difference = self.intercept[..., 1:] - self.intercept[..., :1]
        intercept = np.where(informative[..., None], difference, 0.0)
        difference = self._scores(X, coef, intercept)  # (*J, n, *T, 1)
        uniform = ~informative[(*(slice(None),) * n_sets, None)][..., None]
        with np.errstate(over="ignore"):  # exp(+large) = inf gives p = 0, as it should
            error = np.exp(-difference, out=difference)
        error += 1.0
        np.reciprocal(error, out=error)  # p(class 1) = logistic(difference)
        if np.any(uniform):
            np.copyto(error, 0.5, where=uniform)
        proba = np.empty((*error.shape[:-1], 2))
        np.subtract(1.0, error, out=proba[..., :1])
        proba[..., 1:] = error
        return np.moveaxis(proba, n_sets, -2)  # (*J, *T, n, 2)


def fit_pooled_lda(
    statistics: PooledStatistics, shrinkage: float | np.ndarray | str = DEFAULT_SHRINKAGE
) -> PooledLinearDecoders:
    """Pooled-covariance shrinkage LDA for every training set and labelling at once.

    Only the classes with at least ``MIN_CLASS_COUNT`` weight take part in the decisions
    (equal priors among them); every class's within-class spread, and that of the
    unlabelled signals around their own mean, make up the pooled covariance.
    ``shrinkage``: a fixed intensity in [0, 1]; an array of them broadcasting to the
    labelling axes (``*T``), one per labelling (several intensities fitted at once on
    repeats of one labelling); or ``"oas"`` for each training set and labelling's own
    (`oas_shrinkage`).

    With ``statistics.eigen`` and positive fixed shrinkages, the scatters are not
    decomposed here: the signals added since their last decomposition join the Woodbury
    solve (``S = V diag(e) V^T + Y^T Y``), with the class sums.
    """
    if not isinstance(shrinkage, str):
        intensities = np.asarray(shrinkage, dtype=float)
        if not np.all((intensities >= 0.0) & (intensities <= 1.0)):  # NaN fails too
            raise ValueError(f"shrinkage must be in [0, 1]; got {shrinkage!r}")
    eigen = statistics.eigen
    if eigen is None or isinstance(shrinkage, str) or not np.all(intensities > 0):
        eigenvalues, basis = np.linalg.eigh(statistics.scatter)  # (*J, d), (*J, d, d)
        eigen = ScatterEigen(basis, eigenvalues, np.zeros((*eigenvalues.shape[:-1], 0, 0)))
    decoders = _fit_in_basis(statistics, eigen, shrinkage)
    if decoders is None:  # singular with pending signals: decompose the whole scatter
        return fit_pooled_lda(replace(statistics, eigen=None), shrinkage)
    return decoders


def _fit_in_basis(
    statistics: PooledStatistics, eigen: ScatterEigen, shrinkage: float | np.ndarray | str
) -> PooledLinearDecoders | None:
    """`fit_pooled_lda` in the basis of ``eigen``; None if a decoder's diagonal
    part is singular while signals are pending (only the least-squares path, which needs
    the whole scatter decomposed, can solve it)."""
    n_sets = statistics.n_signals.ndim
    n_features = statistics.scatter.shape[-1]
    n_classes = statistics.counts.shape[-1]
    n_signals = statistics.per_task(np.asarray(statistics.n_signals, dtype=float), 0)
    counts, sums = statistics.counts, statistics.sums
    unlabelled = n_signals - counts.sum(axis=-1)
    if np.any(unlabelled > EMPTY_WEIGHT):
        rest = statistics.per_task(statistics.signal_sum, 1) - sums.sum(axis=-2)
        counts = np.concatenate([counts, unlabelled[..., None]], axis=-1)
        sums = np.concatenate([sums, rest[..., None, :]], axis=-2)
    filled = counts > EMPTY_WEIGHT
    scale = np.where(filled, 1.0 / np.sqrt(np.where(filled, counts, 1.0)), 0.0)
    basis, eigenvalues = eigen.basis, statistics.per_task(eigen.eigenvalues, 1)
    n_pending = eigen.pending.shape[-2]
    # u_k = V^T s_k / sqrt(n_k): W = S - sum_k (V u_k)(V u_k)^T.
    flat_sums = sums.reshape(*sums.shape[:n_sets], -1, n_features)
    projected = (flat_sums @ basis).reshape(sums.shape)
    projected *= scale[..., None]
    within_trace = statistics.per_task(np.trace(statistics.scatter, axis1=-2, axis2=-1), 0)
    within_trace = within_trace - np.einsum("...kd,...kd->...", projected, projected)
    size = np.maximum(n_signals, 1.0)
    if isinstance(shrinkage, str):
        check_option("shrinkage", shrinkage, SHRINKAGE_RULES)
        shrinkage = oas_shrinkage(eigenvalues, projected, within_trace, size)
    c = (1.0 - shrinkage) / size
    nu = shrinkage * within_trace / (size * n_features)
    # Sigma in the basis: diag(a) + c L diag(sign) L^T, a = c e + nu, L = [Y V, U]: the
    # pending signals with sign +1, the classes with -1.
    diagonal = c[..., None] * eigenvalues + nu[..., None]
    # c >= 0 and the eigenvalues ascend: the diagonal's extremes are at its ends.
    smallest, largest = diagonal[..., 0], diagonal[..., -1]
    singular = smallest <= _SINGULAR * np.maximum(np.abs(smallest), np.abs(largest))
    any_singular = bool(singular.any())
    if n_pending and any_singular:
        return None
    safe_diagonal = np.where(singular[..., None], 1.0, diagonal) if any_singular else diagonal
    scaled = projected / safe_diagonal[..., None, :]  # U^T A^-1
    gram = _symmetric_dots(scaled, projected)  # H = U^T A^-1 U
    present = at_least(statistics.counts, MIN_CLASS_COUNT)
    n_present = present.sum(axis=-1, keepdims=True)
    # An uninformative decoder is never used: its system, which may be exactly singular
    # (every class one signal: no within-class spread), is not solved.
    unsolved = singular | (n_present[..., 0] < 2)
    identity = np.eye(counts.shape[-1])
    system = np.where(unsolved[..., None, None], identity, identity - c[..., None, None] * gram)
    if n_pending:
        # Sigma = A + c Z^T Z - c U U^T (Z: the pending signals in the basis): eliminate Z
        # first, Z's own r x r system being positive definite; (I - c H) becomes its
        # Schur complement (I - c H) + c (U^T A^-1 Z^T) E.
        pending = eigen.pending @ basis  # (*J, r, d)
        pending_gram, cross = _pending_blocks(pending, scaled, safe_diagonal)
        cc = c[..., None, None]
        eliminated = np.linalg.solve(  # E = (I + c Z A^-1 Z^T)^-1 c Z A^-1 U
            np.eye(n_pending) + cc * pending_gram, cc * np.swapaxes(cross, -1, -2)
        )
        system += np.where(unsolved[..., None, None], 0.0, cc * (cross @ eliminated))
    # Sigma^-1 U = A^-1 U (I - c H)^-1 (with pending signals, A^-1 (U - Z^T E) times the
    # Schur complement's inverse), so V^T Sigma^-1 mu_k = sum_l M_kl (A^-1 u_l) with M =
    # diag(scale) (I - c H)^-1 (symmetric), rows of absent classes zeroed: only small
    # matrices per decoder, then one combination of the rows of U^T A^-1 (and of Z A^-1).
    mixing = _inverse_small(system)[..., :n_classes, :]
    mixing *= (scale[..., :n_classes] * present)[..., None]
    # mu_k Sigma^-1 mu_k = scale_k (M H)_kk.
    quadratic = np.einsum("...kl,...lk->...k", mixing, gram[..., :, :n_classes])
    if n_pending:
        pending_mixing = -(mixing @ np.swapaxes(eliminated, -1, -2))  # (*J, *T, C, r)
        coef = mixing @ projected  # (*J, *T, C, d), times A^-1 below
        coef += _per_set_product(pending_mixing, pending)
        coef /= safe_diagonal[..., None, :]
        quadratic += np.einsum("...kl,...kl->...k", pending_mixing, cross[..., :n_classes, :])
    else:
        coef = mixing @ scaled
    quadratic *= scale[..., :n_classes]
    singular &= n_present[..., 0] >= 2  # an uninformative decoder is never used
    if any_singular and np.any(singular):
        _least_squares_decoders(
            singular, diagonal, projected, c, scale[..., :n_classes] * present, coef, quadratic
        )
    with np.errstate(divide="ignore"):
        log_priors = np.where(present, -np.log(np.maximum(n_present, 1)), -np.inf)
    return PooledLinearDecoders(
        basis=basis,
        coef=coef,
        intercept=-0.5 * np.where(present, quadratic, 0.0) + log_priors,
        present=present,
    )


def _pending_blocks(
    pending: np.ndarray, scaled: np.ndarray, diagonal: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``Z A^-1 Z^T`` (*J, *T, r, r) and ``U^T A^-1 Z^T`` (*J, *T, K', r) from the pending
    signals in the basis ``Z`` (*J, r, d), ``scaled = U^T A^-1`` (*J, *T, K', d) and
    ``diagonal = a`` (*J, *T, d)."""
    r = pending.shape[-2]
    outer = pending[..., :, None, :] * pending[..., None, :, :]  # (*J, r, r, d)
    flat = outer.reshape(*outer.shape[:-3], r * r, outer.shape[-1])
    pending_gram = _per_set_product(1.0 / diagonal[..., None, :], np.swapaxes(flat, -1, -2))
    pending_gram = pending_gram.reshape(*diagonal.shape[:-1], r, r)
    return pending_gram, _per_set_product(scaled, np.swapaxes(pending, -1, -2))


def _per_set_product(per_task: np.ndarray, shared: np.ndarray) -> np.ndarray:
    """``per_task @ shared`` for ``per_task`` (*J, *T, m, n) and a matrix per training set
    ``shared`` (*J, n, p): (*J, *T, m, p), as one product per set (the tasks' rows
    stacked), not one per task and set (a few microseconds each)."""
    n_sets = shared.ndim - 2
    rows = per_task.reshape(*per_task.shape[:n_sets], -1, per_task.shape[-1])
    return (rows @ shared).reshape(*per_task.shape[:-1], shared.shape[-1])


def oas_shrinkage(
    eigenvalues: np.ndarray, projected: np.ndarray, within_trace: np.ndarray, size: np.ndarray
) -> np.ndarray:
    """The Oracle Approximating Shrinkage intensity of each pooled covariance ``W / N``.

    scikit-learn's ``OAS(assume_centered=True)`` on the class-centred signals (Chen et al.
    2010, Eq. 23 without the 2 / p factor, as scikit-learn computes it): with ``C = W /
    N``, ``mu = tr C / p`` and ``alpha = tr C^2 / p^2``, ``min(1, (alpha + mu^2) / ((N + 1)
    (alpha - mu^2 / p)))``. It needs only ``tr W`` and ``tr W^2``, which the shared
    statistics give: in the eigenbasis of the scatter ``W = diag(e) - U U^T`` (rows
    ``u_k`` of ``projected``), so ``tr W^2 = sum e^2 - 2 sum_k u_k diag(e) u_k +
    ||U U^T||_F^2``.

    Parameters
    ----------
    eigenvalues : ndarray, shape (*J, 1.., d)
        Of each training set's scatter, with unit axes for the labellings.
    projected : ndarray, shape (*J, *T, K', d)
        ``u_k = V^T s_k / sqrt(n_k)`` of every class (and of the unlabelled rest).
    within_trace : ndarray, shape (*J, *T)
        ``tr W``.
    size : ndarray, broadcasting to (*J, *T)
        ``N``, the training set's number of signals.

    Returns
    -------
    ndarray, shape (*J, *T), in [0, 1]
    """
    n_features = projected.shape[-1]
    gram = projected @ np.swapaxes(projected, -1, -2)
    square_trace = (
        np.sum(eigenvalues**2, axis=-1)
        - 2.0 * np.einsum("...kd,...d->...", projected**2, eigenvalues)
        + np.sum(gram**2, axis=(-2, -1))
    )
    mu = within_trace / size / n_features
    alpha = square_trace / size**2 / n_features**2
    numerator = alpha + mu**2
    denominator = (size + 1.0) * (alpha - mu**2 / n_features)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(denominator > 0, numerator / denominator, 1.0)
    return np.minimum(ratio, 1.0)


def _inverse_small(system: np.ndarray) -> np.ndarray:
    """Inverses of a batch of small matrices (*B, m, m).

    Two classes (the feedback frame): the closed-form 2 x 2 inverse, elementwise over the
    batch (LAPACK's per-matrix call would dominate the step); otherwise LAPACK.
    """
    if system.shape[-1] != 2:
        return np.linalg.inv(system)
    a, b = system[..., 0, 0], system[..., 0, 1]
    c, d = system[..., 1, 0], system[..., 1, 1]
    # Only an uninformative decoder (never used) can have a singular system.
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse_determinant = 1.0 / (a * d - b * c)
    inverse = np.stack([d, -b, -c, a], axis=-1) * inverse_determinant[..., None]
    return inverse.reshape(system.shape)


def _symmetric_dots(rows: np.ndarray, other: np.ndarray) -> np.ndarray:
    """``rows @ other^T`` for a batch of few rows (*B, m, d) each, when the result is
    symmetric (``rows = other A^-1``, A diagonal): (*B, m, m).

    One elementwise dot per pair k <= j over the batch, mirrored (a matrix product per
    2 x d batch item would cost more than the arithmetic).
    """
    m = rows.shape[-2]
    out = np.empty((*rows.shape[:-2], m, m))
    for k in range(m):
        for j in range(k, m):
            out[..., k, j] = np.einsum("...d,...d->...", rows[..., k, :], other[..., j, :])
            out[..., j, k] = out[..., k, j]
    return out


def _least_squares_decoders(
    singular: np.ndarray,
    diagonal: np.ndarray,
    projected: np.ndarray,
    c: np.ndarray,
    row_scale: np.ndarray,
    coef: np.ndarray,
    quadratic: np.ndarray,
) -> None:
    """Overwrite, in ``coef`` (*J, *T, C, d) and ``quadratic`` (*J, *T, C), the decoders
    whose covariance is singular (``singular`` (*J, *T)) by their least-squares solution.

    ``row_scale`` (*J, *T, C): each class's ``1 / sqrt(n_k)``, 0 for absent classes.
    """
    n_classes = quadratic.shape[-1]
    solved = _least_squares(
        diagonal[singular], projected[singular], np.broadcast_to(c, singular.shape)[singular]
    )  # (m, K', d) rows of Sigma^+ U
    rows = solved[:, :n_classes] * row_scale[singular][..., None]  # (m, C, d)
    quadratic[singular] = np.sum(rows * projected[singular][:, :n_classes], axis=-1) * (
        row_scale[singular]
    )
    coef[singular] = rows


def _least_squares(diagonal: np.ndarray, projected: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``Sigma^+ U`` rows for decoders whose covariance is singular: (m, K', d).

    ``diagonal`` (m, d), ``projected`` (m, K', d), ``c`` (m,): ``Sigma = diag(a) -
    c U U^T`` in the basis; the minimum-norm least-squares solution, as scikit-learn's.
    """
    out = np.empty_like(projected)
    for i, (a, u, scale) in enumerate(zip(diagonal, projected, c, strict=True)):
        sigma = np.diag(a) - scale * (u.T @ u)
        out[i] = np.linalg.lstsq(sigma, u.T, rcond=None)[0].T
    return out


def fit_lda(
    statistics: ClassStatistics, shrinkage: float = DEFAULT_SHRINKAGE
) -> PooledLinearDecoders:
    """Pooled LDA of labellings given by their class statistics (batch ``B`` as ``J``);
    every signal must be fully labelled (weights summing to 1)."""
    return fit_pooled_lda(PooledStatistics.from_class_statistics(statistics), shrinkage)


class ShrinkageLDA(StatisticsClassifier):
    """Pooled-covariance shrinkage LDA with equal class priors, as used by every task.

    scikit-learn's ``LinearDiscriminantAnalysis(solver="lsqr", shrinkage=shrinkage)``
    (empirical priors in the covariance) with the decision made under equal priors (see
    `fit_pooled_lda`), computed from class statistics.

    Parameters
    ----------
    shrinkage : float, default 0.5
        Weight of the scaled-identity target in the pooled covariance, in [0, 1].

    Attributes
    ----------
    classes_ : ndarray, shape (n_classes,)
    decoders_ : PooledLinearDecoders
        The fitted decoder (no batch axes).

    Examples
    --------
    >>> import numpy as np
    >>> X = np.r_[np.random.default_rng(0).normal(size=(20, 3)), np.ones((20, 3))]
    >>> ShrinkageLDA().fit(X, [0] * 20 + [1] * 20).predict(np.ones((1, 3)))
    array([1])
    """

    _fit_statistics = staticmethod(fit_lda)

    def __init__(self, shrinkage: float = DEFAULT_SHRINKAGE) -> None:
        super().__init__(shrinkage)

    def _min_count(self, n_features: int) -> float:
        return MIN_CLASS_COUNT
