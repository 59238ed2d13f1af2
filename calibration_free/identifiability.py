"""Which task hypotheses no signal can tell apart (method-extensions.md §7.1 and §5).

Under an unknown signal-to-meaning mapping, tasks ``t`` and ``u`` cannot be separated if
some permutation ``sigma`` of the frame's classes makes their expected labels equal
everywhere: ``p_u(sigma(l) | s, a) = p_t(l | s, a)`` for every state, action and class.
``sigma`` = identity: the two are *identical*; any other permutation: *symmetric* (for
feedback, the swap correct <-> error: every action optimal for one is wrong for the other,
as G1 and G2 at the two ends of a line world without no-move). Whatever signals the user
produces, a decoder trained on ``t``'s labels is then a decoder of ``u``'s labels with its
classes renamed, and the matching likelihoods are equal.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from calibration_free.frames import Frame

#: Frames with more classes than this are checked for identical pairs only.
MAX_PERMUTED_CLASSES = 6


@dataclass(frozen=True)
class Confusable:
    """Two tasks that no signal can tell apart.

    Attributes
    ----------
    task, other : int
        The two tasks (``task < other``).
    permutation : tuple of int
        ``permutation[k]`` is the class of ``other`` that class ``k`` of ``task`` reads as.
    """

    task: int
    other: int
    permutation: tuple[int, ...]

    @property
    def kind(self) -> str:
        """"identical" (identity permutation) or "symmetric"."""
        identity = self.permutation == tuple(range(len(self.permutation)))
        return "identical" if identity else "symmetric"


def confusable_pairs(frame: Frame) -> list[Confusable]:
    """Every pair of tasks of ``frame``'s world that no signal can tell apart.

    Each pair is listed once, with the first permutation (in lexicographic order, so the
    identity first) under which the two tasks' expected labels agree at every (state,
    action). Cost: one pass over the frame's row table per permutation of the classes
    (``K!``; frames with more than `MAX_PERMUTED_CLASSES` classes are checked for
    identical pairs only).

    Returns
    -------
    list of Confusable
        Sorted by (task, other).
    """
    rows = np.round(frame.distribution_rows, 12)
    n_tasks = frame.world.n_tasks
    index = frame.row_index.reshape(n_tasks, -1)
    n_classes = rows.shape[1]
    permutations = (
        itertools.permutations(range(n_classes))
        if n_classes <= MAX_PERMUTED_CLASSES
        else [tuple(range(n_classes))]
    )
    by_row = {tuple(row): r for r, row in enumerate(rows)}
    found: dict[tuple[int, int], tuple[int, ...]] = {}
    tasks_with: dict[bytes, list[int]] = {}  # the tasks having each row sequence
    for u in range(n_tasks):
        tasks_with.setdefault(index[u].tobytes(), []).append(u)
    for sigma in permutations:
        # The row task u must have where task t has row r: rows[r] with its classes renamed.
        renamed = np.full(len(rows), -1)
        for r, row in enumerate(rows):
            image = np.empty(n_classes)
            image[list(sigma)] = row
            renamed[r] = by_row.get(tuple(image), -1)
        for t in range(n_tasks):
            mapped = renamed[index[t]]
            if np.any(mapped < 0):
                continue
            for u in tasks_with.get(mapped.astype(index.dtype).tobytes(), []):
                if u != t:
                    pair = (min(t, u), max(t, u))
                    found.setdefault(pair, sigma if t < u else _inverse(sigma))
    return [Confusable(t, u, found[(t, u)]) for t, u in sorted(found)]


def _inverse(permutation: tuple[int, ...]) -> tuple[int, ...]:
    inverse = [0] * len(permutation)
    for k, image in enumerate(permutation):
        inverse[image] = k
    return tuple(inverse)
