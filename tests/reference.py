"""A plain reference for the per-task matching update, built from scikit-learn.

For every task: ``LinearDiscriminantAnalysis(solver="lsqr")`` fitted on the whole history
for the new signal's probabilities, and ``cross_val_predict`` with ``KFold`` for the
confusion matrix. The learner assigns signal ``i`` to fold ``i % k``; ordering the history
by (fold, arrival) turns those folds into ``KFold``'s contiguous blocks of the same sizes.
"""

import numpy as np
from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
from sklearn.model_selection import KFold, cross_val_predict


def lda(n_classes: int, shrinkage: float) -> LinearDiscriminantAnalysis:
    return LinearDiscriminantAnalysis(
        solver="lsqr", shrinkage=shrinkage, priors=np.full(n_classes, 1.0 / n_classes)
    )


def reference_log_match(
    history: np.ndarray,
    labels: np.ndarray,
    signal: np.ndarray,
    expected: np.ndarray,
    *,
    n_classes: int = 2,
    shrinkage: float = 0.5,
    n_folds: int = 10,
    smoothing: float = 1.0,
    balanced: bool = True,
) -> np.ndarray:
    """log m_t for every task.

    history (n, d), labels (n_tasks, n) hard labels, signal (d,), expected (n_tasks, K).
    """
    n = len(history)
    order = np.lexsort((np.arange(n), np.arange(n) % n_folds))
    out = []
    for task_labels, task_expected in zip(labels, expected, strict=True):
        p = lda(n_classes, shrinkage).fit(history, task_labels).predict_proba(signal[None])[0]
        cv = np.empty((n, n_classes))
        cv[order] = cross_val_predict(
            lda(n_classes, shrinkage),
            history[order],
            task_labels[order],
            cv=KFold(n_folds),
            method="predict_proba",
        )
        counts = np.eye(n_classes)[task_labels].T @ cv + smoothing
        if balanced:
            counts = counts / counts.sum(axis=1, keepdims=True)
        confusion = counts / counts.sum(axis=0, keepdims=True)
        out.append(np.log(task_expected @ (confusion @ p)))
    return np.array(out)
