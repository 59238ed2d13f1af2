"""Interaction frames: what a user's signal means for a (state, action) under each task.

A frame gives, for every task ``t``, state ``s`` and action ``a``:

* the frame's own label as a distribution over the ``n_classes`` classes (the *label
  weights*: one-hot for the feedback frame; uniform over the optimal guidance actions for
  the guidance frame). Decoders are trained with these weights, except where the label is
  uniform over all classes (guidance, at the task's state itself when no guidance action
  is optimal there): those signals teach nothing about any class and get weight 0.
* the label the learner *expects* from a user who errs with rate ``eps`` (the *label
  distribution*): ``1 - eps`` on the frame's label(s), ``eps`` spread over the other
  classes. This is ``p(l | s, a, t)`` of the matching pseudo-likelihood.

Feedback frame (ErrP): class 0 = correct, 1 = error; an action is correct under ``t`` iff
it is optimal (`calibration_free.world.World.optimal`).

Guidance frame: class ``k`` is the guidance action ``world.guidance_actions[k]`` (the
grid's move directions up, down, left, right) the user wants *from the state where the
action is taken*, whatever that action was; uniform over the optimal ones when several are
optimal, and over all of them where none is (the grid's task cell itself).

Storage is compact: a frame has only a few distinct label rows (feedback: 2; guidance: one
per set of optimal guidance actions, at most ``2 ** n_classes``), kept once in
`Frame.weight_rows` and `Frame.distribution_rows`, and a table
`Frame.row_index` of which row applies where: ``(n_tasks, n_states, n_actions)``
uint8 for feedback (a view of the world's optimality table), ``(n_tasks, n_states, 1)`` for
guidance, whose label does not depend on the action. The table is built on first use.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from calibration_free.world import World
from decoding.validation import check_option, check_range

FRAMES: tuple[str, ...] = ("feedback", "guidance")
CORRECT, ERROR = 0, 1


def _expected_rows(weights: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """(training weights, expected distribution) of label rows ``weights`` (R, K).

    ``1 - eps`` on the support, ``eps`` spread over the other classes; a row supported on
    every class is kept as it is and trains nothing (weight 0).
    """
    support = weights > 0
    n_other = (~support).sum(axis=-1, keepdims=True)
    spread = np.where(~support, eps / np.maximum(n_other, 1), 0.0)
    distribution = np.where(n_other > 0, (1.0 - eps) * weights + spread, weights)
    return np.where(n_other > 0, weights, 0.0), distribution


@dataclass(frozen=True, eq=False)
class Frame:
    """An interaction frame on a world, with the learner's assumed user error rate.

    Parameters
    ----------
    world : World
    kind : {"feedback", "guidance"}
    eps : float, default 0.1
        Assumed probability that the user's label is not the frame's (method.md §2).

    Attributes
    ----------
    n_classes : int
        2 (feedback: correct, error) or ``len(world.guidance_actions)`` (guidance).
    weight_rows, distribution_rows : ndarray, shape (n_rows, n_classes)
        The distinct label rows: training weights and expected label distribution.
    row_index : ndarray, shape (n_tasks, n_states, n_actions or 1), uint8
        Which row applies to task t, state s and action a (last axis 1: every action).
    """

    world: World
    kind: str = "feedback"
    eps: float = 0.1

    def __post_init__(self) -> None:
        check_option("frame", self.kind, FRAMES)
        check_range("eps", self.eps, 0.0, 0.5, inclusive=True)
        if self.kind == "guidance" and not 2 <= len(self.world.guidance_actions) <= 8:
            raise ValueError(
                f"the guidance frame needs 2 to 8 guidance actions; the {self.world.name} "
                f"world has {len(self.world.guidance_actions)}"
            )

    @property
    def n_classes(self) -> int:
        return 2 if self.kind == "feedback" else len(self.world.guidance_actions)

    def class_names(self) -> tuple[str, ...]:
        """Names of the classes, in class order."""
        if self.kind == "feedback":
            return ("correct", "error")
        return tuple(self.world.action_names[a] for a in self.world.guidance_actions)

    @cached_property
    def _tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        optimal = self.world.optimal
        if self.kind == "feedback":
            # Row 0: error, row 1: correct, so that the index is the optimality table.
            labels = np.array([[0.0, 1.0], [1.0, 0.0]])
            index = optimal.view(np.uint8)
        else:
            guided = optimal[:, :, list(self.world.guidance_actions)]
            bits = (guided.astype(np.uint8) << np.arange(guided.shape[-1], dtype=np.uint8))
            table = bits.sum(axis=-1, dtype=np.uint8)  # the set of optimal actions, as bits
            masks = np.flatnonzero(np.bincount(table.ravel(), minlength=256))
            row_of_mask = np.zeros(256, dtype=np.uint8)
            row_of_mask[masks] = np.arange(len(masks))
            index = row_of_mask[table][:, :, None]
            labels = (masks[:, None] >> np.arange(self.n_classes) & 1).astype(float)
            labels[masks == 0] = 1.0
            labels /= labels.sum(axis=-1, keepdims=True)
        weights, distribution = _expected_rows(labels, self.eps)
        return weights, distribution, index

    @cached_property
    def has_ambiguous_labels(self) -> bool:
        """Whether some label allows several classes but not all (guidance where two
        actions are optimal); builds the tables."""
        support = (self.weight_rows > 0).sum(axis=1)
        return bool(np.any((support > 1) & (support < self.n_classes)))

    @property
    def weight_rows(self) -> np.ndarray:
        return self._tables[0]

    @property
    def distribution_rows(self) -> np.ndarray:
        return self._tables[1]

    @property
    def row_index(self) -> np.ndarray:
        return self._tables[2]

    def rows_at(self, state: int, action: int) -> np.ndarray:
        """Every task's label row at (state, action), shape (n_tasks,)."""
        index = self.row_index
        return index[:, state, action if index.shape[-1] > 1 else 0]

    def weights_at(self, state: int, action: int) -> np.ndarray:
        """Every task's training weights at (state, action), shape (n_tasks, n_classes)."""
        return self.weight_rows[self.rows_at(state, action)]

    def distribution_at(self, state: int, action: int) -> np.ndarray:
        """Every task's ``p(l | s, a, t)``, shape (n_tasks, n_classes)."""
        return self.distribution_rows[self.rows_at(state, action)]

    def _dense(self, rows: np.ndarray) -> np.ndarray:
        index = self.row_index
        shape = (*index.shape[:2], self.world.n_actions)
        return rows[np.broadcast_to(index, shape)]

    @property
    def label_weights(self) -> np.ndarray:
        """Dense training weights, shape (n_tasks, n_states, n_actions, n_classes).

        Built on every call (``T S A K`` floats): for small worlds and checks only; the
        learner uses `weights_at`.
        """
        return self._dense(self.weight_rows)

    @property
    def label_distribution(self) -> np.ndarray:
        """Dense ``p(l | s, a, t)``, shape (n_tasks, n_states, n_actions, n_classes).

        Built on every call: for small worlds and checks only (see `label_weights`).
        """
        return self._dense(self.distribution_rows)
