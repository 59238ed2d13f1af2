"""Plain references for the per-task decoders and matching update.

* `EqualPriorLDA`: scikit-learn's ``LinearDiscriminantAnalysis(solver="lsqr",
  shrinkage=...)`` (empirical priors, so its covariance is the pooled within-class one)
  with the documented prior correction ``log(1/K) - log(prior_k)`` added to its scores:
  the learner's decoder for hard labels.
* `weighted_lda_log_proba`: the same formulas written out with numpy for any class
  weights (soft labels, and signals a task gives no label, whose rest weight makes a
  class of their own in the covariance).
* `reference_log_match`: per task, the full decoder and ``cross_val_predict`` with
  ``KFold`` for the confusion. The learner assigns signal ``i`` to fold ``i % k``;
  ordering the history by (fold, arrival) turns those folds into ``KFold``'s contiguous
  blocks of the same sizes.
"""

import numpy as np
from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
from sklearn.model_selection import KFold, cross_val_predict


class EqualPriorLDA(LinearDiscriminantAnalysis):
    """scikit-learn's pooled-covariance LDA, deciding under equal class priors."""

    def predict_proba(self, X):
        scores = self.decision_function(X)
        if scores.ndim == 1:  # binary: the log-odds of class 1
            log_odds = scores - np.log(self.priors_[1] / self.priors_[0])
            scores = np.c_[np.zeros(len(scores)), log_odds]
        else:
            scores = scores - np.log(self.priors_)
        scores = scores - scores.max(axis=1, keepdims=True)
        proba = np.exp(scores)
        return proba / proba.sum(axis=1, keepdims=True)

    def predict(self, X):
        return self.classes_[np.argmax(self.predict_proba(X), axis=1)]


def lda(shrinkage: float) -> EqualPriorLDA:
    return EqualPriorLDA(solver="lsqr", shrinkage=shrinkage)


def weighted_lda_log_proba(
    X: np.ndarray, weights: np.ndarray, shrinkage: float, signals: np.ndarray
) -> np.ndarray:
    """log p(k | signal) (n, K) of the pooled LDA trained on ``X`` (N, d) with class
    weights ``weights`` (N, K) (rows summing to at most 1); absent classes -inf, an
    uninformative decoder log(1/K)."""
    n, d = X.shape
    n_classes = weights.shape[1]
    all_weights = np.c_[weights, 1.0 - weights.sum(axis=1)]
    within = np.zeros((d, d))
    means = np.zeros((n_classes, d))
    for k in range(n_classes + 1):
        w = all_weights[:, k]
        if w.sum() <= 1e-9:
            continue
        mean = w @ X / w.sum()
        centred = X - mean
        within += (w[:, None] * centred).T @ centred
        if k < n_classes:
            means[k] = mean
    covariance = within / n
    covariance = (1 - shrinkage) * covariance + shrinkage * np.trace(covariance) / d * np.eye(d)
    present = weights.sum(axis=0) >= 2
    if present.sum() < 2:
        return np.full((len(signals), n_classes), -np.log(n_classes))
    coef = np.linalg.solve(covariance, means.T)
    scores = signals @ coef - 0.5 * np.sum(means.T * coef, axis=0) - np.log(present.sum())
    scores = np.where(present, scores, -np.inf)
    top = scores.max(axis=1, keepdims=True)
    return scores - top - np.log(np.exp(scores - top).sum(axis=1, keepdims=True))


def weighted_cross_validated_proba(
    X: np.ndarray, weights: np.ndarray, shrinkage: float, n_folds: int = 10
) -> np.ndarray:
    """Out-of-fold probabilities (N, K), signal i in fold i % n_folds."""
    folds = np.arange(len(X)) % n_folds
    out = np.empty(weights.shape)
    for f in range(n_folds):
        train, test = folds != f, folds == f
        out[test] = np.exp(weighted_lda_log_proba(X[train], weights[train], shrinkage, X[test]))
    return out


def confusion(weights, cv_proba, smoothing=1.0, balanced=True):
    counts = weights.T @ cv_proba + smoothing
    if balanced:
        counts = counts / counts.sum(axis=1, keepdims=True)
    return counts / counts.sum(axis=0, keepdims=True)


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
    """log m_t for every task, from scikit-learn.

    history (n, d), labels (n_tasks, n) hard labels, signal (d,), expected (n_tasks, K).
    """
    n = len(history)
    order = np.lexsort((np.arange(n), np.arange(n) % n_folds))
    out = []
    for task_labels, task_expected in zip(labels, expected, strict=True):
        p = lda(shrinkage).fit(history, task_labels).predict_proba(signal[None])[0]
        cv = np.empty((n, n_classes))
        cv[order] = cross_val_predict(
            lda(shrinkage),
            history[order],
            task_labels[order],
            cv=KFold(n_folds),
            method="predict_proba",
        )
        matrix = confusion(np.eye(n_classes)[task_labels], cv, smoothing, balanced)
        out.append(np.log(task_expected @ (matrix @ p)))
    return np.array(out)
