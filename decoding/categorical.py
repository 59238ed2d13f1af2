"""A categorical decoder for symbolic signals (method-extensions §5: two buttons).

A symbolic signal says which of ``n_symbols`` buttons the user pressed, as a one-hot vector
(``[1, 0]`` for the first button of two). Each class's model is the frequency of every
button among that class's signals: the class's weighted sum of the signals divided by its
weight, ``f_k = s_k / n_k``, with no smoothing (the proof's maximum-likelihood button
model). A signal's class probabilities are the normalised likelihoods under equal priors,
``p(k | e) = (e . f_k) / sum_j (e . f_j)`` (for a one-hot ``e``, the frequency of the
pressed button); a button that no class has seen gives no information (uniform). A class
with no weight takes no part (probability 0); while fewer than two classes take part the
decoder gives no information (uniform).

It needs only the classes' weighted counts and sums, no scatter matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from decoding.statistics import EMPTY_WEIGHT, BatchedDecoders


@dataclass(frozen=True)
class CategoricalDecoders(BatchedDecoders):
    """A batch of per-class button-frequency decoders.

    Attributes
    ----------
    frequencies : ndarray, shape (*B, n_classes, n_symbols)
        Each class's button frequencies (rows sum to 1; 0 for absent classes).
    present : ndarray, shape (*B, n_classes), bool
        Classes with signals.
    """

    frequencies: np.ndarray
    present: np.ndarray

    def _known_log_proba(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=float)
        if np.any(X < 0):
            raise ValueError(
                "the categorical decoder takes symbolic signals (one-hot button presses, "
                "entries >= 0); got a negative entry"
            )
        likelihood = X @ np.swapaxes(self.frequencies, -1, -2)  # (*B, n, K)
        total = likelihood.sum(axis=-1, keepdims=True)
        seen = total > 0
        with np.errstate(divide="ignore"):
            log_proba = np.log(likelihood) - np.log(np.where(seen, total, 1.0))
        return np.where(seen, log_proba, -np.log(likelihood.shape[-1]))


def fit_categorical(counts: np.ndarray, sums: np.ndarray) -> CategoricalDecoders:
    """Button-frequency decoders from class weights and weighted signal sums.

    Parameters
    ----------
    counts : ndarray, shape (*B, n_classes)
        Each class's summed signal weights.
    sums : ndarray, shape (*B, n_classes, n_symbols)
        Each class's weighted sum of the (one-hot) signals: its button counts.
    """
    present = counts > EMPTY_WEIGHT
    frequencies = sums / np.where(present, counts, 1.0)[..., None]
    return CategoricalDecoders(
        frequencies=np.where(present[..., None], frequencies, 0.0), present=present
    )
