"""A continuous set of goal hypotheses in the plane, kept as a resampled pool of particles.

method-extensions §3: the device probes points of ``[0, 1]^2`` (it teleports there), the
teacher answers each probe with a cardinal direction towards a goal point it has in mind,
and the device keeps ``H`` goal hypotheses (particles). Each step, in the thesis code's
order:

1. resample the pool from the previous step's weights (``random``: ``H - 1`` uniform points;
   ``active``: ``H - 1`` draws from a mixture of a Gaussian of covariance 0.01 I around every
   particle, weighted 0.8 in proportion to ``w + 1e-6``, and a broad Gaussian around the
   centre of covariance 0.1 I, weight 0.2, clipped to the square); the best particle is kept
   in slot 0 either way;
2. probe the point of largest uncertainty computed at the end of the previous step
   (``uncertainty``) or a uniform point (``random``);
3. relabel the whole history for every particle with the cardinal frame (noise ``alpha``);
4. score every particle with the sampled-classifier confidence
   (`calibration_free.sampled_confidence`);
5. (``uncertainty``) compute the uncertainty of candidate points: the weighted variance over
   particles of the expected match ``J_t(x', e_s) = sum_k p(l_k | x', t) q_t(l_k | e_s)``,
   summed over up to 20 signals of the history, with ``q_t`` the confusion-corrected
   prediction of particle t's Student-t decoder (10-fold cross-validated confusion).

The first ``n_initial`` probes are uniform and compute nothing. The estimate is the
particle with the largest confidence. Random draws come from the learner's generator, in
the order: resampling, probe, sampled classifiers, candidates, signals for the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration_free.cardinal import cardinal_guidance
from calibration_free.likelihood import confusion_matrices, corrected_proba
from calibration_free.sampled_confidence import (
    normal_difference_confidence,
    sample_classifiers,
    sampled_log_likelihoods,
    shrunk_class_moments,
    soft_class_statistics,
)
from decoding.statistics import ClassStatistics
from decoding.student_t import fit_student_t
from decoding.validation import check_at_least, check_option

SAMPLINGS = ("random", "active")
PROBINGS = ("random", "uncertainty")


@dataclass(frozen=True)
class ContinuousConfig:
    """Settings of the continuous-goal learner (defaults: the thesis code's).

    Attributes
    ----------
    n_hypotheses : int
        Particles in the pool.
    sampling : {"random", "active"}
        How the pool is resampled.
    probing : {"random", "uncertainty"}
        How the next probe point is chosen.
    alpha : float
        The learner's frame noise.
    n_initial : int
        Uniform probes before the first likelihood.
    n_draws : int
        Classifiers sampled per particle.
    n_candidates : int
        Candidate probe points of the uncertainty map.
    n_map_signals : int
        History signals the uncertainty map averages over.
    shrinkage : float
        Covariance shrinkage of the class Gaussians.
    n_folds : int
        Folds of the cross-validated confusion of the uncertainty map.
    """

    n_hypotheses: int = 50
    sampling: str = "active"
    probing: str = "uncertainty"
    alpha: float = 0.01
    n_initial: int = 12
    n_draws: int = 20
    n_candidates: int = 1000
    n_map_signals: int = 20
    shrinkage: float = 0.5
    n_folds: int = 10

    def __post_init__(self) -> None:
        check_option("sampling", self.sampling, SAMPLINGS)
        check_option("probing", self.probing, PROBINGS)
        check_at_least("n_hypotheses", self.n_hypotheses, 2)


def resample(
    particles: np.ndarray, weights: np.ndarray, sampling: str, rng: np.random.Generator
) -> np.ndarray:
    """A new pool of the same size, the best particle of ``weights`` in slot 0.

    Parameters
    ----------
    particles : ndarray, shape (H, 2)
    weights : ndarray, shape (H,)
        Non-negative, normalised.
    sampling : {"random", "active"}

    Returns
    -------
    ndarray, shape (H, 2)
        In ``[0, 1]^2``.
    """
    n = len(particles)
    best = particles[np.argmax(weights)]
    if sampling == "random":
        drawn = rng.uniform(size=(n - 1, 2))
    else:
        mixture = np.append(0.8 * (weights + 1e-6) / np.sum(weights + 1e-6), 0.2)
        component = rng.choice(n + 1, size=n - 1, p=mixture)
        centres = np.vstack([particles, [0.5, 0.5]])[component]
        spread = np.where(component == n, np.sqrt(0.1), np.sqrt(0.01))[:, None]
        drawn = np.clip(centres + spread * rng.standard_normal((n - 1, 2)), 0.0, 1.0)
    return np.vstack([best, drawn])


class ContinuousGoalLearner:
    """The learner of a goal point in the plane from unlabelled cardinal-direction signals.

    Parameters
    ----------
    config : ContinuousConfig
    rng : Generator
        The learner's stream (see the module docstring for the order of its draws).

    Attributes
    ----------
    particles : ndarray, shape (H, 2)
        The current pool.
    confidence : ndarray, shape (H,)
        ``W`` of each particle after the last observation (uniform before the first).
    """

    def __init__(self, config: ContinuousConfig, rng: np.random.Generator) -> None:
        self.config, self.rng = config, rng
        self.particles = rng.uniform(size=(config.n_hypotheses, 2))
        self.confidence = np.full(config.n_hypotheses, 0.5)
        self._points: list[np.ndarray] = []
        self._signals: list[np.ndarray] = []
        self._uncertainty: tuple[np.ndarray, np.ndarray] | None = None  # (candidates, U)

    @property
    def n_signals(self) -> int:
        return len(self._signals)

    def propose(self) -> np.ndarray:
        """Resample the pool (after the initial probes) and return the next probe point."""
        if self.n_signals >= self.config.n_initial:
            self.particles = resample(
                self.particles, self._weights(), self.config.sampling, self.rng
            )
        if self._uncertainty is not None and self.config.probing == "uncertainty":
            candidates, uncertainty = self._uncertainty
            return candidates[np.argmax(uncertainty)]
        return self.rng.uniform(size=2)

    def observe(self, point: np.ndarray, signal: np.ndarray) -> None:
        """Add the teacher's signal (shape (d,)) at ``point``; rescore the pool."""
        self._points.append(np.asarray(point, dtype=float))
        self._signals.append(np.asarray(signal, dtype=float))
        if self.n_signals < max(self.config.n_initial, len(signal) + 1):
            return
        points, signals = np.array(self._points), np.array(self._signals)
        labels = np.swapaxes(
            cardinal_guidance(points, self.particles, self.config.alpha), 0, 1
        )  # (H, n, K)
        statistics = soft_class_statistics(signals, labels)  # (H,): each particle's classes
        means, covariances = shrunk_class_moments(statistics, signals, self.config.shrinkage)
        draws = sample_classifiers(
            means, covariances, len(signals), self.config.n_draws, self.rng
        )
        self.confidence = normal_difference_confidence(
            sampled_log_likelihoods(signals, labels, draws)
        )
        if self.config.probing == "uncertainty":
            self._uncertainty = self._map(signals, labels, statistics)

    def estimate(self) -> np.ndarray:
        """The best particle, shape (2,)."""
        return self.particles[np.argmax(self.confidence)]

    def uncertainty_map(self) -> tuple[np.ndarray, np.ndarray]:
        """Candidate probe points (n_candidates, 2) and their uncertainty (n_candidates,)
        under the current pool and weights (draws candidates and signals from the rng)."""
        points, signals = np.array(self._points), np.array(self._signals)
        labels = np.swapaxes(cardinal_guidance(points, self.particles, self.config.alpha), 0, 1)
        return self._map(signals, labels, soft_class_statistics(signals, labels))

    def _weights(self) -> np.ndarray:
        return self.confidence / self.confidence.sum()

    def _map(
        self, signals: np.ndarray, labels: np.ndarray, statistics: ClassStatistics
    ) -> tuple[np.ndarray, np.ndarray]:
        """Draw the candidates (C, 2) and the chosen signals; their uncertainty (C,).
        ``statistics``: ``soft_class_statistics(signals, labels)``."""
        candidates = self.rng.uniform(size=(self.config.n_candidates, 2))
        chosen = self.rng.choice(
            len(signals), size=min(self.config.n_map_signals, len(signals)), replace=False
        )
        corrected = _corrected_predictions(signals, labels, statistics, chosen, self.config)
        frame = cardinal_guidance(candidates, self.particles, self.config.alpha)
        return candidates, map_uncertainty(frame, corrected, self._weights())


def map_uncertainty(
    frame: np.ndarray, corrected: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """The weighted variance over particles t of the expected matches
    ``J_t(x', e_s) = sum_k p(l_k | x', t) q_t(l_k | e_s)``, summed over the signals s.

    As ``sum_s (E_w[J^2] - E_w[J]^2)``: ``sum_s J^2`` needs only ``sum_s q q^T`` per
    particle, and ``E_w[J]`` is one matrix product, so the (H, C, S) array of matches is
    never formed.

    Parameters
    ----------
    frame : ndarray, shape (C, H, K)
        ``p(l | x', t)`` at every candidate point under every particle.
    corrected : ndarray, shape (H, S, K)
        ``q_t(l | e_s)`` of every particle's decoder for the chosen signals.
    weights : ndarray, shape (H,)
        Normalised particle weights.

    Returns
    -------
    ndarray, shape (C,)
        Non-negative.
    """
    by_particle = np.swapaxes(frame, 0, 1)  # (H, C, K)
    second = weights[:, None, None] * (np.swapaxes(corrected, 1, 2) @ corrected)  # (H, K, K)
    mean_square = np.einsum("tck,tck->c", by_particle @ second, by_particle)
    weighted = np.swapaxes(weights[:, None, None] * corrected, 1, 2)  # (H, K, S)
    mean = frame.reshape(len(frame), -1) @ weighted.reshape(-1, corrected.shape[1])  # (C, S)
    return np.maximum(mean_square - np.einsum("cs,cs->c", mean, mean), 0.0)


def _corrected_predictions(
    signals: np.ndarray,
    labels: np.ndarray,
    whole: ClassStatistics,
    chosen: np.ndarray,
    config: ContinuousConfig,
) -> np.ndarray:
    """``q_t(. | e_s)`` of every particle's Student-t decoder for the chosen signals,
    corrected by its 10-fold cross-validated confusion: (H, len(chosen), K).

    Signal i is in fold ``i % n_folds``. All folds at once: the history, padded with
    zero-weight rows to whole rows of ``n_folds``, is laid out (n_folds, rows, ...), and
    each fold's decoders (trained without it) score their own fold's signals. ``whole``:
    the class statistics of the whole history, ``soft_class_statistics(signals, labels)``."""
    n, n_folds = len(signals), config.n_folds
    rows = -(-n // n_folds)
    padded_signals = np.zeros((rows * n_folds, signals.shape[1]))
    padded_signals[:n] = signals
    padded_labels = np.zeros((labels.shape[0], rows * n_folds, labels.shape[2]))
    padded_labels[:, :n] = labels
    by_fold = np.swapaxes(padded_signals.reshape(rows, n_folds, -1), 0, 1)  # (F, rows, d)
    fold_labels = np.moveaxis(padded_labels.reshape(len(labels), rows, n_folds, -1), 2, 0)
    part = soft_class_statistics(by_fold, fold_labels)  # batch (F, H)
    held_out = ClassStatistics(
        whole.counts - part.counts, whole.sums - part.sums, whole.scatters - part.scatters
    )
    fold_log = fit_student_t(held_out, config.shrinkage).log_proba(by_fold[:, None])
    cv_log = np.moveaxis(fold_log, 0, 2).reshape(len(labels), rows * n_folds, -1)[:, :n]
    full = fit_student_t(whole, config.shrinkage)
    label_counts = np.swapaxes(labels, -1, -2) @ np.exp(cv_log)  # (H, K, K)
    confusion = confusion_matrices(label_counts, full.present, smoothing=1.0)
    return corrected_proba(confusion, np.exp(full.log_proba(signals[chosen])))
