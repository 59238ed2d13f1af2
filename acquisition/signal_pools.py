"""Per-class pools of a dataset's signals, drawn without replacement and refilled."""

from __future__ import annotations

import numpy as np


class SignalPools:
    """Indices of each class's signals, drawn without replacement; an empty pool is refilled
    with a fresh shuffle of its class (one ``rng.permutation`` call per refill).

    Parameters
    ----------
    labels : ndarray of int, shape (n_signals,)
        Class of every signal of the dataset.
    n_classes : int
        Classes that must have signals (0..n_classes-1).
    rng : Generator
    purpose : str, optional
        Ends the error message of a missing class (e.g. " for the guidance frame").
    """

    def __init__(
        self, labels: np.ndarray, n_classes: int, rng: np.random.Generator, purpose: str = ""
    ) -> None:
        labels = np.asarray(labels)
        self._members = [np.flatnonzero(labels == k) for k in range(n_classes)]
        empty = [k for k, members in enumerate(self._members) if len(members) == 0]
        if empty:
            raise ValueError(f"the dataset has no signal of class(es) {empty}{purpose}")
        self._queues: list[list[int]] = [[] for _ in range(n_classes)]
        self.rng = rng

    def draw(self, label: int) -> int:
        """The index of the next signal of class ``label``."""
        queue = self._queues[label]
        if not queue:
            queue.extend(self.rng.permutation(self._members[label]).tolist()[::-1])
        return queue.pop()
