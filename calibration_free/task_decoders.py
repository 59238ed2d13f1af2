"""The decoders of all task hypotheses, computed together from shared statistics.

All T tasks see the same signals and differ only in their labels. `TaskHistory`
keeps, per fold, the signals' uncentred scatter matrix, sum and count, shared by every
task, and per task, fold and class only the weighted count and sum of the signals, each
updated in one step per new signal. Every task's full decoder and its k-fold decoders
(trained on all folds but one) are functions of these (totals minus one fold): one
eigendecomposition per training set (kept, and refreshed every few signals in turn, by the
learner: ``eigen_period``) and a K x K solve per task
(`fit_pooled_lda`); no task is ever refitted from its raw history.
Fold ``f`` holds the signals ``i`` with ``i % n_folds == f`` (0-based arrival order), so
folds never move as the history grows.

The Student-t and Gaussian (QDA) decoders need each class's own scatter matrix: with
them, the history also keeps per task, fold and class a d x d scatter (T x F x K x d^2
numbers, updated every step), the cost the shared form avoids. The categorical decoder
(symbolic signals) needs only the class counts and sums.

Tasks whose labels agree on every signal since the last switch have the same statistics,
so the same decoders: `TaskHistory.labellings` groups them (each new signal splits a
group by the label it gets; a switch merges them all) and `TaskModels` fits,
cross-validates and predicts once per labelling. In feedback a move's label depends on
which side of the agent's cell the target lies, so a few dozen labellings stand for the
400 tasks of a 20 x 20 grid; the results are every task's, exactly as if each were fitted.

A likelihood that matches the decoders' raw predictions (simple or batch matching) fits
the whole history's decoders only (``with_folds=False``): no cross-validation.

After a target, every task adopts that task's labels of the whole history (method.md
§5). No per-task statistic is copied: each is kept as a part shared by all tasks (the
adopted task's, up to the switch) plus each task's own part since the switch, which
restarts at zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration_free.likelihood import confusion_matrices, corrected_proba
from decoding.categorical import fit_categorical
from decoding.gaussian import fit_gaussian
from decoding.lda import fit_pooled_lda
from decoding.scatter_eigen import RollingScatterEigen
from decoding.statistics import BatchedDecoders, ClassStatistics, PooledStatistics
from decoding.student_t import STUDENT_T_COUNTS, fit_student_t
from decoding.validation import check_option

DEFAULT_FOLDS = 10


class FoldSums:
    """Per-task sums of per-signal increments, per fold and in total.

    Each task's value is a part shared by every task (what a target switch adopted) plus
    the task's own part since that switch.

    Parameters
    ----------
    n_tasks, n_folds : int
    shape : tuple of int
        Shape of one task's value in one fold.
    """

    def __init__(self, n_tasks: int, n_folds: int, shape: tuple[int, ...]) -> None:
        self.shared = np.zeros((n_folds, *shape))
        self.shared_total = np.zeros(shape)
        self.own = np.zeros((n_folds, n_tasks, *shape))
        self.own_total = np.zeros((n_tasks, *shape))

    def add(self, fold: int, increment: np.ndarray) -> None:
        """Add every task's ``increment`` (n_tasks, *shape) to ``fold``."""
        self.own[fold] += increment
        self.own_total += increment

    def adopt(self, task: int) -> None:
        """Give every task ``task``'s value: it becomes the shared part; own parts restart."""
        self.shared += self.own[:, task]
        self.shared_total += self.own_total[task]
        self.own.fill(0.0)
        self.own_total.fill(0.0)

    def replace_own(self, own: np.ndarray) -> None:
        """Set every task's own part since the last switch, per fold: (n_folds, n_tasks,
        *shape)."""
        self.own[:] = own
        self.own_total[:] = own.sum(axis=0)

    def total(self, tasks: np.ndarray | None = None) -> np.ndarray:
        """Every task's total over the folds, shape (n_tasks, *shape); or those of the
        ``tasks`` (indices, (m,)) alone, shape (m, *shape)."""
        own_total = self.own_total if tasks is None else self.own_total[tasks]
        return self.shared_total + own_total

    def held_out(self, tasks: np.ndarray | None = None) -> np.ndarray:
        """Every task's total without each fold, shape (n_folds, n_tasks, *shape); or
        those of the ``tasks`` (indices, (m,)) alone, shape (n_folds, m, *shape)."""
        own_total, own = (
            (self.own_total, self.own) if tasks is None
            else (self.own_total[tasks], self.own[:, tasks])
        )
        return (self.shared_total - self.shared)[:, None] + (own_total - own)


class TaskHistory:
    """Signals seen so far and each task's labels and per-fold class statistics.

    Parameters
    ----------
    n_tasks, n_classes, n_features : int
    n_folds : int, default 10
    class_scatters : bool, default False
        Also keep every task's per-class scatter matrices (the Student-t decoder).
    keeps_frame_labels : bool, default False
        Also keep every task's frame label weights of the signals since the last switch,
        before any ambiguous label was split (`resplit_own_labels` needs them).
    eigen_period : int or None, default None
        Also keep the training sets' scatters decomposed, each decomposed again every
        ``eigen_period`` signals in turn (`decoding.scatter_eigen`;
        `refresh_period` balances the cost), for the pooled
        LDA with a fixed shrinkage; None: the decoders decompose the scatters.
    """

    def __init__(
        self,
        n_tasks: int,
        n_classes: int,
        n_features: int,
        n_folds: int = DEFAULT_FOLDS,
        class_scatters: bool = False,
        keeps_frame_labels: bool = False,
        eigen_period: int | None = None,
    ) -> None:
        if n_folds < 2:
            raise ValueError(f"n_folds must be >= 2; got {n_folds}")
        self.n_tasks, self.n_classes, self.n_features, self.n_folds = (
            n_tasks,
            n_classes,
            n_features,
            n_folds,
        )
        self.n_signals = 0
        self._signals = np.empty((64, n_features))
        # Label weights: rows before the last switch are shared, later ones per task.
        self._shared_weights = np.empty((64, n_classes))
        self._own_weights = np.empty((n_tasks, 64, n_classes))
        self._own_frame_weights = np.empty((n_tasks, 64, n_classes)) if keeps_frame_labels else None
        self._n_shared = 0
        # Tasks whose labels agree on every signal since the last switch share one
        # labelling (and so one set of decoders): each task's labelling, and one task of
        # each labelling.
        self._labelling, self._representatives = _one_labelling(n_tasks)
        self._scatter = np.zeros((n_folds, n_features, n_features))
        self._set_scatters: np.ndarray | None = None  # cache of _training_scatters()
        self._signal_sum = np.zeros((n_folds, n_features))
        self._fold_size = np.zeros(n_folds)
        self._counts = FoldSums(n_tasks, n_folds, (n_classes,))
        self._sums = FoldSums(n_tasks, n_folds, (n_classes, n_features))
        self._scatters = (
            FoldSums(n_tasks, n_folds, (n_classes, n_features, n_features))
            if class_scatters
            else None
        )
        self._eigen = (
            RollingScatterEigen(n_folds + 1, n_features, eigen_period)
            if eigen_period is not None
            else None
        )

    @property
    def signals(self) -> np.ndarray:
        """Signals in arrival order, shape (n_signals, n_features), float64."""
        return self._signals[: self.n_signals]

    def task_label_weights(self, task: int) -> np.ndarray:
        """``task``'s label weights of every signal, shape (n_signals, n_classes)."""
        return np.concatenate(
            [self._shared_weights[: self._n_shared], self._own_weights[task, : self._n_own]]
        )

    @property
    def label_weights(self) -> np.ndarray:
        """Every task's label weights, shape (n_tasks, n_signals, n_classes) (a copy)."""
        shared = np.broadcast_to(
            self._shared_weights[: self._n_shared], (self.n_tasks, self._n_shared, self.n_classes)
        )
        return np.concatenate([shared, self._own_weights[:, : self._n_own]], axis=1)

    @property
    def labellings(self) -> tuple[np.ndarray, np.ndarray]:
        """The distinct labellings of the history: every task's (n_tasks,), an index into
        the second array, which holds one task of each labelling (n_labellings,).

        Tasks whose label weights agree exactly on every signal have the same statistics,
        so the same decoders, predictions and confusion: they are fitted once. Right after
        a target switch every task has the adopted labels (one labelling); each signal
        splits the labellings by the label it gets."""
        return self._labelling, self._representatives

    def _split_labellings(self, *rows: np.ndarray) -> None:
        """Split the labellings by every task's new ``rows`` (n_tasks, m) each."""
        key = np.column_stack([self._labelling, *rows])
        self._labelling, self._representatives = _group_rows(key)

    @property
    def n_adopted(self) -> int:
        """Signals before the last target switch, whose labels every task adopted."""
        return self._n_shared

    @property
    def _n_own(self) -> int:
        return self.n_signals - self._n_shared

    def add(
        self,
        signal: np.ndarray,
        weights: np.ndarray,
        frame_weights: np.ndarray | None = None,
        weight: float = 1.0,
    ) -> None:
        """Append ``signal`` (n_features,) with every task's label weights (n_tasks, K)
        and, if the history keeps them, the frame's weights they were split from (the
        same shape; default ``weights``).

        ``weight`` (> 0): how much the signal counts in the shared statistics (its fold's
        scatter ``w x x^T``, sum ``w x`` and size ``w``; the decomposed scatters get ``sqrt(w)
        x``): a pseudo-observation of an earlier session (`calibration_free.prior`),
        whose label weights the caller scales by ``w`` too, so that the signal's unit of
        weight is ``w`` in every statistic. 1: a signal observed live (the same numbers as
        without the argument).
        """
        if self.n_signals == len(self._signals):
            self._signals = np.concatenate([self._signals, np.empty_like(self._signals)])
        if self._n_own == self._own_weights.shape[1]:
            self._own_weights = _doubled(self._own_weights)
            if self._own_frame_weights is not None:
                self._own_frame_weights = _doubled(self._own_frame_weights)
        index = self.n_signals
        self._signals[index] = signal
        self._own_weights[:, self._n_own] = weights
        if self._own_frame_weights is not None:
            self._own_frame_weights[:, self._n_own] = (
                weights if frame_weights is None else frame_weights
            )
        fold = index % self.n_folds
        live = weight == 1.0
        outer = np.outer(signal, signal)
        self._scatter[fold] += outer if live else weight * outer  # symmetric either way
        self._set_scatters = None
        self._signal_sum[fold] += signal if live else weight * signal
        self._fold_size[fold] += weight
        if self._eigen is not None:
            members = np.arange(self.n_folds + 1) != fold
            root = signal if live else np.sqrt(weight) * signal
            self._eigen.add(root, members, self._training_scatters())
        self._split_labellings(weights, *(() if frame_weights is None else (frame_weights,)))
        self._counts.add(fold, weights)
        self._sums.add(fold, weights[:, :, None] * signal)
        if self._scatters is not None:
            self._scatters.add(fold, np.multiply.outer(weights, np.outer(signal, signal)))
        self.n_signals += 1

    def relabel(self, task: int) -> None:
        """Give every task the labels of ``task`` on the whole history (method.md §5).

        Without copying any per-task statistic: ``task``'s part since the last switch
        joins the shared part, and every task's own part restarts.
        """
        own = self._own_weights[task, : self._n_own]
        end = self._n_shared + len(own)
        if end > len(self._shared_weights):
            grown = np.empty((2 * end, self.n_classes))
            grown[: self._n_shared] = self._shared_weights[: self._n_shared]
            self._shared_weights = grown
        self._shared_weights[self._n_shared : end] = own
        self._n_shared = end
        for sums in (self._counts, self._sums, self._scatters):
            if sums is not None:
                sums.adopt(task)
        self._labelling, self._representatives = _one_labelling(self.n_tasks)

    def resplit_own_labels(self, proba: np.ndarray) -> None:
        """Split again every ambiguous label since the last switch by ``proba``.

        A frame label that allows several classes but not all (guidance: two optimal
        directions) is shared among them in proportion to ``proba`` (n_tasks, n_signals -
        n_adopted, K), each task's latest out-of-fold class probabilities of the signals
        since the switch (`TaskModels.held_out_proba` from `n_adopted`): one EM step
        on which of the allowed classes the user chose, where the split made when each
        signal arrived used the decoder of that time. The tasks' statistics since the
        switch are rebuilt from the new weights. Needs ``keeps_frame_labels``.
        """
        if self._own_frame_weights is None:
            raise RuntimeError("this history keeps no frame labels to split again")
        n_own = self._n_own
        frame = self._own_frame_weights[:, :n_own]
        support = (frame > 0).sum(axis=-1, keepdims=True)
        ambiguous = (support > 1) & (support < self.n_classes)
        if not np.any(ambiguous):
            return
        if proba.shape != frame.shape:
            raise ValueError(
                f"proba must have shape {frame.shape} (tasks, signals since the switch, "
                f"classes); got {proba.shape}"
            )
        shared = frame * proba
        total = shared.sum(axis=-1, keepdims=True)
        resplit = np.where(total > 0, shared / np.where(total > 0, total, 1.0), frame)
        weights = np.where(ambiguous, resplit, frame)
        self._own_weights[:, :n_own] = weights
        signals = self._signals[self._n_shared : self.n_signals]
        folds = np.arange(self._n_shared, self.n_signals) % self.n_folds
        counts = np.zeros(self._counts.own.shape)
        sums = np.zeros(self._sums.own.shape)
        scatters = None if self._scatters is None else np.zeros(self._scatters.own.shape)
        for fold in range(self.n_folds):
            members = folds == fold
            fold_weights, fold_signals = weights[:, members], signals[members]
            counts[fold] = fold_weights.sum(axis=1)
            sums[fold] = np.einsum("tik,id->tkd", fold_weights, fold_signals)
            if scatters is not None:
                scatters[fold] = np.einsum(
                    "tik,id,ie->tkde", fold_weights, fold_signals, fold_signals, optimize=True
                )
        self._counts.replace_own(counts)
        self._sums.replace_own(sums)
        if self._scatters is not None and scatters is not None:
            self._scatters.replace_own(scatters)
        # Tasks of one labelling get the same new weights from the same probabilities;
        # grouped again from the weights themselves, whatever ``proba`` was.
        self._labelling, self._representatives = _one_labelling(self.n_tasks)
        self._split_labellings(weights.reshape(self.n_tasks, -1), frame.reshape(self.n_tasks, -1))

    def pooled_statistics(
        self, with_folds: bool = True, tasks: np.ndarray | None = None
    ) -> PooledStatistics:
        """The pooled statistics of every fold's training set (all signals but that
        fold's), then of the whole history: batch shape (n_folds + 1, n_tasks); without
        the folds, of the whole history only: batch shape (1, n_tasks). With ``tasks``
        (indices, (m,)), of those tasks' labellings alone: a task axis of m."""

        def training_sets(sums: FoldSums) -> np.ndarray:
            whole = sums.total(tasks)[None]
            if not with_folds:
                return whole
            return np.concatenate([sums.held_out(tasks), whole])

        def shared(per_fold: np.ndarray) -> np.ndarray:
            return self._training_sets(per_fold) if with_folds else per_fold.sum(axis=0)[None]

        scatter = self._training_scatters() if with_folds else shared(self._scatter)
        eigen = None
        if self._eigen is not None:
            eigen = self._eigen.current()
            if not with_folds:
                eigen = eigen.select(slice(-1, None))
        return PooledStatistics(
            scatter=scatter,
            n_signals=shared(self._fold_size),
            signal_sum=shared(self._signal_sum),
            counts=training_sets(self._counts),
            sums=training_sets(self._sums),
            eigen=eigen,
        )

    def _training_scatters(self) -> np.ndarray:
        """Every training set's scatter, (n_folds + 1, d, d), summed once per signal (the
        rolling eigendecompositions and the decoders' fit share it)."""
        if self._set_scatters is None:
            self._set_scatters = self._training_sets(self._scatter)
        return self._set_scatters

    @staticmethod
    def _training_sets(per_fold: np.ndarray) -> np.ndarray:
        """A shared per-fold statistic (n_folds, ...) summed over every fold's training
        set, then over the whole history: (n_folds + 1, ...)."""
        total = per_fold.sum(axis=0)
        return np.concatenate([total - per_fold, total[None]])

    def class_statistics(
        self, with_folds: bool = True, tasks: np.ndarray | None = None
    ) -> tuple[ClassStatistics, ClassStatistics | None]:
        """Per-class statistics of the whole history (n_tasks, ...) and of each fold's
        training set (n_folds, n_tasks, ...; None without ``with_folds``); with ``tasks``
        (indices, (m,)), of those tasks' labellings alone (a task axis of m). Needs
        ``class_scatters``."""
        if self._scatters is None:
            raise RuntimeError("this history keeps no per-class scatter matrices")
        parts = (self._counts, self._sums, self._scatters)
        whole = ClassStatistics(*(part.total(tasks) for part in parts))
        if not with_folds:
            return whole, None
        return whole, ClassStatistics(*(part.held_out(tasks) for part in parts))

    def class_means(self) -> np.ndarray:
        """Every task's class means on the whole history, shape (n_tasks, n_classes,
        n_features); a class without signals gets the mean of all the signals."""
        counts, sums = self._counts.total(), self._sums.total()
        filled = counts > 0
        means = sums / np.where(filled, counts, 1.0)[..., None]
        overall = self.signals.mean(axis=0) if self.n_signals else np.zeros(self.n_features)
        return np.where(filled[..., None], means, overall)

    def label_confusion_counts(
        self, by_fold: np.ndarray, tasks: np.ndarray | None = None
    ) -> np.ndarray:
        """``sum_i w_i(t) p_i(t)^T`` for every task: (n_tasks, K, K); or for the ``tasks``
        (indices, (m,)) alone: (m, K, K).

        ``by_fold`` (n_folds, per_fold, n_tasks or m, K): class probabilities of every signal in
        the layout of `cross_validated_proba` (signal ``i`` at ``[i % n_folds, i //
        n_folds]``; the padding beyond the last signal is ignored). Row ``k`` of the result
        is the predictions summed over the signals with task ``t``'s label weight
        ``w_ik(t)``. The labels shared by every task (those adopted at target switches) take
        one matrix product per fold, whatever the number of tasks; only the signals since
        the last switch are gathered per task.
        """
        n_folds, per_fold, n_tasks, n_classes = by_fold.shape
        n_shared = self._n_shared
        shared = np.zeros((per_fold * n_folds, n_classes))
        shared[:n_shared] = self._shared_weights[:n_shared]
        shared = shared.reshape(per_fold, n_folds, n_classes).transpose(1, 2, 0)  # (F, K, j)
        flat = by_fold.reshape(n_folds, per_fold, n_tasks * n_classes)
        counts = np.matmul(shared, flat).sum(axis=0)  # (K, T * K)
        counts = counts.reshape(n_classes, n_tasks, n_classes).transpose(1, 0, 2)
        if self._n_own:
            predicted = signals_from(by_fold, n_shared, self.n_signals)  # (n_own, T, K)
            own = self._own_weights[:, : self._n_own]
            own = own if tasks is None else own[tasks]
            counts = counts + np.einsum("tik,itl->tkl", own, predicted)
        return counts

    def cross_validated_proba(self, fold_decoders: BatchedDecoders) -> np.ndarray:
        """Out-of-fold class probabilities by fold: (n_folds, per_fold, n_tasks, K).

        ``fold_decoders`` has batch shape (n_folds, n_tasks). Signal ``i`` is in fold
        ``i % n_folds`` at position ``i // n_folds``, so the signals, zero-padded to a
        multiple of ``n_folds``, reshape to (n_folds, per_fold, n_features) and every
        fold's decoders score their own fold in one batched call; the padding's rows are
        not predictions. `in_signal_order` gives the (n_tasks, n_signals, K) view.
        """
        n_signals, n_folds = self.n_signals, self.n_folds
        per_fold = -(-n_signals // n_folds)
        padded = np.zeros((per_fold * n_folds, self.n_features))
        padded[:n_signals] = self._signals[:n_signals]
        by_fold = np.ascontiguousarray(
            padded.reshape(per_fold, n_folds, self.n_features).swapaxes(0, 1)
        )
        proba = fold_decoders.proba(by_fold[:, None])  # (n_folds, T, per_fold, K)
        return proba.swapaxes(1, 2)  # a view of the decoders' (n_folds, per_fold, T, K)


def _one_labelling(n_tasks: int) -> tuple[np.ndarray, np.ndarray]:
    """Every task in labelling 0, task 0 standing for it (see `TaskHistory.labellings`)."""
    return np.zeros(n_tasks, dtype=np.intp), np.zeros(1, dtype=np.intp)


def _group_rows(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``key`` (n, m), n >= 1, compared by value (0.0 equals -0.0):
    every row's group (n,), the groups numbered in the rows' lexicographic order, and the
    first row of each group (n_groups,). What ``np.unique(key, axis=0, return_index=True,
    return_inverse=True)`` gives, from one stable lexicographic sort of the rows instead
    of a sort of structured records (6-10x faster on these arrays)."""
    order = np.lexsort(key.T[::-1])
    ordered = key[order]
    starts = np.empty(len(key), dtype=bool)
    starts[0] = True
    np.any(ordered[1:] != ordered[:-1], axis=1, out=starts[1:])
    groups = np.empty(len(key), dtype=np.intp)
    groups[order] = np.cumsum(starts) - 1
    return groups, order[starts]


def _doubled(rows: np.ndarray) -> np.ndarray:
    """``rows`` (n_tasks, capacity, K) with twice the capacity (the new rows unset)."""
    return np.concatenate([rows, np.empty_like(rows)], axis=1)


def signals_from(by_fold: np.ndarray, first: int, n_signals: int) -> np.ndarray:
    """Probabilities by fold (`TaskHistory.cross_validated_proba`) of signals
    ``first`` to ``n_signals - 1``, in signal order: (n, n_tasks, K) (a copy)."""
    index = np.arange(first, n_signals)
    n_folds = by_fold.shape[0]
    return by_fold[index % n_folds, index // n_folds]


def in_signal_order(by_fold: np.ndarray, n_signals: int, task: int | None = None) -> np.ndarray:
    """Probabilities by fold (`TaskHistory.cross_validated_proba`) in signal order:
    (n_tasks, n_signals, K), or (n_signals, K) for one ``task`` (a copy)."""
    n_tasks, n_classes = by_fold.shape[2:]
    if task is not None:
        return by_fold[:, :, task].swapaxes(0, 1).reshape(-1, n_classes)[:n_signals]
    in_order = by_fold.transpose(2, 1, 0, 3).reshape(n_tasks, -1, n_classes)
    return in_order[:, :n_signals]


def balanced_accuracy(proba: np.ndarray, label_weights: np.ndarray) -> float | None:
    """Balanced accuracy of out-of-fold class probabilities ``proba`` (n_signals, K)
    against ``label_weights`` (n_signals, K), possibly soft.

    Every signal's predicted class is the argmax of its probabilities (ties to the lower
    class); a class's recall is the weight of its signals predicted as it over its total
    weight; the result is the mean recall over the classes that have signals, or None
    while fewer than two have.
    """
    totals = label_weights.sum(axis=0)
    present = totals > 0
    if present.sum() < 2:
        return None
    predicted = proba.argmax(axis=1)
    hits = label_weights[np.arange(len(predicted)), predicted]
    correct = np.bincount(predicted, weights=hits, minlength=len(totals))
    return float(np.mean(correct[present] / totals[present]))


DECODERS: tuple[str, ...] = ("lda", "student_t", "gaussian", "categorical")


@dataclass(frozen=True)
class DecoderFit:
    """How every task's decoders are fitted on a `TaskHistory`.

    Attributes
    ----------
    kind : {"lda", "student_t", "gaussian", "categorical"}
        Pooled-covariance shrinkage LDA on the shared statistics
        (`decoding.lda`); the Student-t predictive (`decoding.student_t`) or
        a plain Gaussian per class (QDA, `decoding.gaussian`), both on per-class
        statistics; or button frequencies of symbolic signals
        (`decoding.categorical`), on the class counts and sums alone.
    shrinkage : float
        Covariance shrinkage (not used by "categorical").
    student_t_counts : {"class", "total"}, default "class"
        The count in the Student-t predictive (`decoding.student_t.fit_student_t`):
        each class's own, or the training set's total (the thesis code's).
    """

    kind: str
    shrinkage: float
    student_t_counts: str = "class"

    def __post_init__(self) -> None:
        check_option("decoder", self.kind, DECODERS)
        check_option("student_t_counts", self.student_t_counts, STUDENT_T_COUNTS)

    @property
    def class_scatters(self) -> bool:
        """Whether the history must keep per-class scatter matrices."""
        return self.kind in ("student_t", "gaussian")

    @property
    def rolling_eigen(self) -> bool:
        """Whether the decoders use decomposed scatters refreshed in turn (the pooled LDA
        with a fixed positive shrinkage)."""
        shrinkage = self.shrinkage
        return self.kind == "lda" and not isinstance(shrinkage, str) and shrinkage > 0

    def __call__(
        self, history: TaskHistory, with_folds: bool = True, tasks: np.ndarray | None = None
    ) -> tuple[BatchedDecoders, BatchedDecoders | None]:
        """Every task's full decoder (batch (n_tasks,)) and fold decoders (batch
        (n_folds, n_tasks); None without ``with_folds``: no cross-validation fit); with
        ``tasks`` (indices, (m,)), those tasks' alone (a task axis of m)."""
        if self.class_scatters:
            whole, training = history.class_statistics(with_folds, tasks)
            folds = self._fit_classes(training) if training is not None else None
            return self._fit_classes(whole), folds
        statistics = history.pooled_statistics(with_folds, tasks)
        if self.kind == "categorical":
            decoders: BatchedDecoders = fit_categorical(statistics.counts, statistics.sums)
        else:
            decoders = fit_pooled_lda(statistics, self.shrinkage)
        return decoders.select(-1), decoders.select(slice(0, -1)) if with_folds else None

    def _fit_classes(self, statistics: ClassStatistics) -> BatchedDecoders:
        if self.kind == "student_t":
            return fit_student_t(statistics, self.shrinkage, self.student_t_counts)
        return fit_gaussian(statistics, self.shrinkage)


def decoder_fit(decoder: str, shrinkage: float, student_t_counts: str = "class") -> DecoderFit:
    """The fitting of decoders of kind ``decoder`` (one of `DECODERS`)."""
    return DecoderFit(decoder, shrinkage, student_t_counts)


@dataclass(frozen=True)
class TaskModels:
    """Every task's decoder on the whole history, with its cross-validated confusion
    when it was fitted with one.

    Tasks that share a labelling (`TaskHistory.labellings`) share their decoders:
    the models hold one per labelling, and every per-task result is that labelling's.

    Attributes
    ----------
    decoders : BatchedDecoders, batch shape (n_labellings,)
    labelling : ndarray, shape (n_tasks,), int
        Every task's labelling: its decoder is ``decoders.select(labelling[task])``.
    confusion : ndarray, shape (n_labellings, n_classes, n_classes), or None
        ``p(true label i | predicted j)`` from k-fold cross-validation; None when fitted
        without cross-validation.
    cv_by_fold : ndarray, shape (n_folds, per_fold, n_labellings, n_classes), or None
        The out-of-fold class probabilities the confusion matrices were built from, in
        the layout of `TaskHistory.cross_validated_proba` (`cv_proba`: every
        task's, in signal order).
    n_signals : int
        Signals the models were fitted on.
    """

    decoders: BatchedDecoders
    labelling: np.ndarray
    confusion: np.ndarray | None = None
    cv_by_fold: np.ndarray | None = None
    n_signals: int = 0

    @property
    def cv_proba(self) -> np.ndarray | None:
        """Every task's out-of-fold class probabilities, (n_tasks, n_signals, n_classes)
        (a copy), or None without cross-validation."""
        if self.cv_by_fold is None:
            return None
        return in_signal_order(self.cv_by_fold, self.n_signals)[self.labelling]

    @classmethod
    def fit(
        cls,
        history: TaskHistory,
        fit: DecoderFit,
        smoothing: float,
        balanced: bool = True,
        cross_validate: bool = True,
    ) -> TaskModels:
        """Fit every labelling's decoders and (with ``cross_validate``) their k-fold
        confusion matrices on ``history``.

        ``smoothing`` and ``balanced``: see `confusion_matrices`.
        """
        labelling, representatives = history.labellings
        decoders, fold_decoders = fit(history, cross_validate, representatives)
        if fold_decoders is None:
            return cls(decoders, labelling)
        return cls.cross_validated(history, decoders, fold_decoders, smoothing, balanced)

    @classmethod
    def cross_validated(
        cls,
        history: TaskHistory,
        decoders: BatchedDecoders,
        fold_decoders: BatchedDecoders,
        smoothing: float,
        balanced: bool = True,
    ) -> TaskModels:
        """The models of the history's labellings' fitted ``decoders`` (batch
        (n_labellings,)) with the confusion of their ``fold_decoders`` (batch (n_folds,
        n_labellings))."""
        labelling, representatives = history.labellings
        by_fold = history.cross_validated_proba(fold_decoders)
        counts = history.label_confusion_counts(by_fold, representatives)
        confusion = confusion_matrices(counts, decoders.present, smoothing, balanced)
        return cls(decoders, labelling, confusion, by_fold, history.n_signals)

    def balanced_accuracy(self, task: int, label_weights: np.ndarray) -> float | None:
        """Cross-validated balanced accuracy of ``task``'s decoder
        (`balanced_accuracy`)."""
        if self.cv_by_fold is None:
            raise RuntimeError("these models were fitted without cross-validation")
        proba = in_signal_order(self.cv_by_fold, self.n_signals, int(self.labelling[task]))
        return balanced_accuracy(proba, label_weights)

    @property
    def informative(self) -> np.ndarray:
        """Tasks whose decoder has enough data in every class, shape (n_tasks,), bool."""
        return self.decoders.informative[self.labelling]

    def corrected_proba(self, signals: np.ndarray) -> np.ndarray:
        """``q = C p`` for signals (n, d): (n_tasks, n, K); needs the confusion.

        A task's decoder may not know every class yet (too few signals of it). Under equal
        class priors a new signal belongs to a known class with probability
        ``n_known / K``: the known classes share that mass as ``q`` says, and every unknown
        class gets ``1 / K``. A decoder that cannot tell its classes apart thus gives 1/K
        everywhere, like an uninformative one, whatever the number of classes it knows.
        """
        if self.confusion is None:
            raise RuntimeError("these models were fitted without cross-validation")
        return self._per_task(corrected_proba(self.confusion, self.decoders.proba(signals)))

    def proba(self, signals: np.ndarray) -> np.ndarray:
        """The decoders' own class probabilities ``p`` of signals (n, d): (n_tasks, n, K),
        with unknown classes treated as in `corrected_proba`."""
        return self._per_task(self.decoders.proba(signals))

    def held_out_proba(self, first: int = 0) -> np.ndarray:
        """Every task's out-of-fold class probabilities of the signals it was fitted on
        from signal ``first`` on, (n_tasks, n_signals - first, K), unknown classes treated
        as in `corrected_proba`; needs the cross-validation."""
        if self.cv_by_fold is None:
            raise RuntimeError("these models were fitted without cross-validation")
        rows = signals_from(self.cv_by_fold, first, self.n_signals)
        return self._per_task(rows.swapaxes(0, 1))

    def held_out_corrected_proba(self, task: int) -> np.ndarray:
        """``task``'s out-of-fold ``q = C p`` of every signal it was fitted on, (n_signals,
        K), unknown classes treated as in `corrected_proba`; needs the
        cross-validation."""
        if self.cv_by_fold is None or self.confusion is None:
            raise RuntimeError("these models were fitted without cross-validation")
        labelling = self.labelling[task : task + 1]
        rows = in_signal_order(self.cv_by_fold, self.n_signals, int(labelling[0]))
        corrected = corrected_proba(self.confusion[labelling], rows[None])
        return self._with_unknown_classes(corrected, labelling)[0]

    def _per_task(self, q: np.ndarray) -> np.ndarray:
        """Every labelling's probabilities ``q`` (n_labellings, n, K) as every task's
        (n_tasks, n, K), unknown classes treated as in `corrected_proba`."""
        return self._with_unknown_classes(q, slice(None))[self.labelling]

    def _with_unknown_classes(self, q: np.ndarray, labellings: slice | np.ndarray) -> np.ndarray:
        """Probabilities ``q`` (n_labellings, n, K) of the labellings ``labellings`` with
        the classes their decoders do not know given ``1 / K`` (see
        `corrected_proba`)."""
        n_classes = q.shape[-1]
        known = (self.decoders.present & self.decoders.informative[:, None])[labellings]
        share = known.sum(axis=1)[:, None, None] / n_classes
        return np.where(known[:, None, :], q * share, 1.0 / n_classes)
