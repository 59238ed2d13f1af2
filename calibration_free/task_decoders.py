"""The decoders of all task hypotheses, computed together from shared statistics.

All T tasks see the same signals and differ only in their labels. :class:`TaskHistory`
keeps, for every task, fold and class, the weighted count, sum and scatter of the signals,
updated with one rank-one step per new signal. The full decoder of task t, and its k-fold
decoders (trained on all folds but one), are then functions of these statistics
(totals minus one fold), fitted for all tasks and folds in one batched solve: no task is
ever refitted from its raw history. Fold ``f`` holds the signals ``i`` with
``i % n_folds == f`` (0-based arrival order), so folds never move as the history grows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calibration_free.likelihood import confusion_matrices, corrected_proba
from decoding.lda import fit_lda
from decoding.statistics import BatchedDecoders, ClassStatistics, HeldOutStatistics, Statistics
from decoding.student_t import fit_student_t

DecoderFit = Callable[[Statistics], BatchedDecoders]
DEFAULT_FOLDS = 10


def decoder_fit(decoder: str, shrinkage: float) -> DecoderFit:
    """The function fitting decoders of kind ``decoder`` ("lda" or "student_t")."""
    fit = fit_student_t if decoder == "student_t" else fit_lda
    return lambda statistics: fit(statistics, shrinkage)


class TaskHistory:
    """Signals seen so far and each task's labels and per-fold class statistics.

    Parameters
    ----------
    n_tasks : int
    n_classes : int
    n_features : int
    n_folds : int, default 10
    """

    def __init__(
        self, n_tasks: int, n_classes: int, n_features: int, n_folds: int = DEFAULT_FOLDS
    ) -> None:
        if n_folds < 2:
            raise ValueError(f"n_folds must be >= 2; got {n_folds}")
        self.n_tasks, self.n_classes, self.n_features, self.n_folds = (
            n_tasks,
            n_classes,
            n_features,
            n_folds,
        )
        self._signals = np.empty((64, n_features))
        self._weights = np.empty((n_tasks, 64, n_classes))
        self.n_signals = 0
        shape = (n_tasks, n_folds, n_classes)
        self._per_fold = ClassStatistics(
            np.zeros(shape),
            np.zeros((*shape, n_features)),
            np.zeros((*shape, n_features, n_features)),
        )
        self._totals = ClassStatistics(
            *(np.zeros((n_tasks, *a.shape[2:])) for a in self._per_fold.arrays())
        )

    @property
    def signals(self) -> np.ndarray:
        """Signals in arrival order, shape (n_signals, n_features), float64."""
        return self._signals[: self.n_signals]

    @property
    def label_weights(self) -> np.ndarray:
        """Each task's label weights, shape (n_tasks, n_signals, n_classes)."""
        return self._weights[:, : self.n_signals]

    def add(self, signal: np.ndarray, weights: np.ndarray) -> None:
        """Append ``signal`` (n_features,) with every task's label weights (n_tasks, K)."""
        if self.n_signals == len(self._signals):
            self._signals = np.concatenate([self._signals, np.empty_like(self._signals)])
            self._weights = np.concatenate([self._weights, np.empty_like(self._weights)], axis=1)
        index = self.n_signals
        self._signals[index] = signal
        self._weights[:, index] = weights
        fold = index % self.n_folds
        increments = (
            weights,
            weights[:, :, None] * signal,
            np.multiply.outer(weights, np.outer(signal, signal)),
        )
        for per_fold, total, increment in zip(
            self._per_fold.arrays(), self._totals.arrays(), increments, strict=True
        ):
            per_fold[:, fold] += increment
            total += increment
        self.n_signals += 1

    def relabel(self, task: int) -> None:
        """Give every task the labels of ``task`` on the whole history (method.md §5)."""
        for array in (*self._per_fold.arrays(), *self._totals.arrays()):
            array[:] = array[task]
        self._weights[:, : self.n_signals] = self._weights[task, : self.n_signals]

    def statistics(self) -> tuple[ClassStatistics, HeldOutStatistics]:
        """Class statistics of the whole history (n_tasks, ...) and of each fold's
        training set, i.e. all signals but that fold's (n_tasks, n_folds, ...)."""
        return self._totals, HeldOutStatistics(self._totals, self._per_fold)

    def cross_validated_proba(self, fold_decoders: BatchedDecoders) -> np.ndarray:
        """Out-of-fold class probabilities, shape (n_tasks, n_signals, n_classes).

        ``fold_decoders`` has batch shape (n_tasks, n_folds). Signal ``i`` is in fold
        ``i % n_folds`` at position ``i // n_folds``, so the signals, zero-padded to a
        multiple of ``n_folds``, reshape to (n_folds, per_fold, n_features) and every
        fold's decoders score their own fold in one batched call.
        """
        n_signals, n_folds = self.n_signals, self.n_folds
        per_fold = -(-n_signals // n_folds)
        padded = np.zeros((per_fold * n_folds, self.n_features))
        padded[:n_signals] = self._signals[:n_signals]
        by_fold = np.ascontiguousarray(
            padded.reshape(per_fold, n_folds, self.n_features).swapaxes(0, 1)
        )
        log_proba = fold_decoders.log_proba(by_fold)  # (n_tasks, n_folds, per_fold, K)
        in_order = log_proba.swapaxes(1, 2).reshape(self.n_tasks, -1, self.n_classes)
        return np.exp(in_order[:, :n_signals])


@dataclass(frozen=True)
class TaskModels:
    """Every task's decoder on the whole history, with its cross-validated confusion.

    Attributes
    ----------
    decoders : BatchedDecoders (LDA or Student-t), batch shape (n_tasks,)
    confusion : ndarray, shape (n_tasks, n_classes, n_classes)
        ``p(true label i | predicted j)`` from k-fold cross-validation.
    cv_proba : ndarray, shape (n_tasks, n_signals, n_classes)
        The out-of-fold class probabilities the confusion matrices were built from.
    """

    decoders: BatchedDecoders
    confusion: np.ndarray
    cv_proba: np.ndarray

    @classmethod
    def fit(
        cls, history: TaskHistory, fit: DecoderFit, smoothing: float, balanced: bool = True
    ) -> TaskModels:
        """Fit all tasks' decoders and their k-fold confusion matrices on ``history``.

        ``smoothing`` and ``balanced``: see :func:`~calibration_free.likelihood.confusion_matrices`.
        """
        totals, training = history.statistics()
        decoders = fit(totals)
        cv_proba = history.cross_validated_proba(fit(training))
        confusion = confusion_matrices(
            history.label_weights, cv_proba, decoders.present, smoothing, balanced
        )
        return cls(decoders=decoders, confusion=confusion, cv_proba=cv_proba)

    def balanced_accuracy(self, task: int, label_weights: np.ndarray) -> float | None:
        """Cross-validated balanced accuracy of ``task``'s decoder.

        Every signal's predicted class is the argmax of its out-of-fold probabilities (ties
        to the lower class); a class's recall is the weight of its signals predicted as it
        over its total weight (``label_weights`` (n_signals, K) are the task's, possibly
        soft); the result is the mean recall over the classes that have signals, or None
        while fewer than two have.
        """
        totals = label_weights.sum(axis=0)
        present = totals > 0
        if present.sum() < 2:
            return None
        predicted = self.cv_proba[task].argmax(axis=1)
        hits = label_weights[np.arange(len(predicted)), predicted]
        correct = np.bincount(predicted, weights=hits, minlength=len(totals))
        return float(np.mean(correct[present] / totals[present]))

    @property
    def informative(self) -> np.ndarray:
        """Tasks whose decoder has enough data in every class, shape (n_tasks,), bool."""
        return self.decoders.informative

    def corrected_proba(self, signals: np.ndarray) -> np.ndarray:
        """``q = C p`` for signals (n, d): (n_tasks, n, K).

        A task's decoder may not know every class yet (too few signals of it). Under equal
        class priors a new signal belongs to a known class with probability
        ``n_known / K``: the known classes share that mass as ``q`` says, and every unknown
        class gets ``1 / K``. A decoder that cannot tell its classes apart thus gives 1/K
        everywhere, like an uninformative one, whatever the number of classes it knows.
        """
        q = corrected_proba(self.confusion, np.exp(self.decoders.log_proba(signals)))
        n_classes = q.shape[-1]
        known = self.decoders.present & self.informative[:, None]
        share = known.sum(axis=1)[:, None, None] / n_classes
        return np.where(known[:, None, :], q * share, 1.0 / n_classes)
