"""Interaction frames: what a user's signal means for a (state, action) under each task.

A frame gives, for every task ``t``, state ``s`` and action ``a``:

* ``label_weights[t, s, a, k]`` — the frame's own label as a distribution over the
  ``n_classes`` classes (one-hot for the feedback frame; uniform over the optimal move
  directions for the guidance frame). Decoders are trained with these weights, except
  where the label is uniform over all classes (guidance, at the task cell itself): those
  signals teach nothing about any class and get weight 0.
* ``label_distribution[t, s, a, k]`` — the label the learner *expects* from a user who
  errs with rate ``eps``: ``1 - eps`` on the frame's label(s), ``eps`` spread over the
  other classes. This is ``p(l | s, a, t)`` of the matching pseudo-likelihood.

Feedback frame (ErrP): class 0 = correct, 1 = error; an action is correct under ``t`` iff
it is optimal (see :class:`~calibration_free.world.GridWorld`).

Guidance frame: class ``k`` is the move direction ``MOVES[k]`` (up, down, left, right) the
user wants *from the state where the action is taken*, whatever that action was; uniform
over the optimal directions when several are optimal, and over all four at the task cell
itself, where no move is optimal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration_free.world import MOVES, GridWorld
from decoding.validation import check_option, check_range

FRAMES: tuple[str, ...] = ("feedback", "guidance")
CORRECT, ERROR = 0, 1


@dataclass(frozen=True)
class Frame:
    """An interaction frame on a world, with the learner's assumed user error rate.

    Parameters
    ----------
    world : GridWorld
    kind : {"feedback", "guidance"}
    eps : float, default 0.1
        Assumed probability that the user's label is not the frame's (method.md §2).

    Attributes
    ----------
    n_classes : int
        2 (feedback: correct, error) or 4 (guidance: up, down, left, right).
    label_weights : ndarray, shape (n_tasks, n_states, n_actions, n_classes)
    label_distribution : ndarray, shape (n_tasks, n_states, n_actions, n_classes)
    """

    world: GridWorld
    kind: str = "feedback"
    eps: float = 0.1
    label_weights: np.ndarray = field(init=False, repr=False)
    label_distribution: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        check_option("frame", self.kind, FRAMES)
        check_range("eps", self.eps, 0.0, 0.5, inclusive=True)
        optimal = self.world.optimal
        if self.kind == "feedback":
            weights = np.stack([optimal, ~optimal], axis=-1).astype(float)
        else:
            moves = optimal[:, :, : len(MOVES)].astype(float)
            at_task = moves.sum(axis=-1, keepdims=True) == 0
            moves = np.where(at_task, 1.0, moves)
            moves /= moves.sum(axis=-1, keepdims=True)
            # The label depends on the state only: broadcast over the actions taken there.
            weights = np.repeat(moves[:, :, None, :], self.world.n_actions, axis=2)
        support = weights > 0
        n_other = (~support).sum(axis=-1, keepdims=True)
        spread = np.where(~support, self.eps / np.maximum(n_other, 1), 0.0)
        distribution = np.where(n_other > 0, (1.0 - self.eps) * weights + spread, weights)
        # A label uniform over every class says nothing about what any class looks like:
        # such signals do not train the decoders (weight 0), though they are still matched.
        weights = np.where(n_other > 0, weights, 0.0)
        object.__setattr__(self, "label_weights", weights)
        object.__setattr__(self, "label_distribution", distribution)

    @property
    def n_classes(self) -> int:
        return self.label_weights.shape[-1]

    def class_names(self) -> tuple[str, ...]:
        """Names of the classes, in class order."""
        return ("correct", "error") if self.kind == "feedback" else MOVES
