"""The simulated teacher of the continuous-goal world: a hidden goal point, cardinal answers.

The goal is uniform in ``[0, 1]^2``. At every probe point the teacher draws a direction from
the cardinal frame of its goal with its own noise (0 by default: the thesis code's), and
answers with a signal of the dataset class standing for that direction, drawn without
replacement (`acquisition.signal_pools.SignalPools`). Dataset class
``class_order[k]`` stands for direction ``k`` of `calibration_free.cardinal.DIRECTIONS`
(default: class k), a mapping the learner never knows.

Random draws, in order, from the teacher's generator: the goal (two uniforms), then per
probe one categorical draw of the direction and the pool shuffles when a pool is (re)filled.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from acquisition.signal_pools import SignalPools
from calibration_free.cardinal import DIRECTIONS, cardinal_guidance


class CardinalTeacher:
    """A teacher with a hidden goal answering probe points with dataset signal indices.

    Parameters
    ----------
    labels : ndarray of int, shape (n_signals,)
        Dataset classes 0..3.
    rng : Generator
    alpha : float, default 0
        The teacher's frame noise.
    class_order : sequence of int, optional
        ``class_order[k]`` is the dataset class of direction k.

    Attributes
    ----------
    goal : ndarray, shape (2,)
    """

    def __init__(
        self,
        labels: np.ndarray,
        rng: np.random.Generator,
        alpha: float = 0.0,
        class_order: Sequence[int] | None = None,
    ) -> None:
        n = len(DIRECTIONS)
        self.class_order = np.arange(n) if class_order is None else np.asarray(class_order)
        if sorted(self.class_order.tolist()) != list(range(n)):
            raise ValueError(f"class_order must be a permutation of 0..{n - 1}; got {class_order}")
        self.rng, self.alpha = rng, alpha
        self.goal = rng.uniform(size=2)
        self._pools = SignalPools(labels, n, rng)

    def answer(self, point: np.ndarray) -> tuple[int, int]:
        """(index of the signal in the dataset, its direction) for a probe at ``point``."""
        distribution = cardinal_guidance(np.asarray(point)[None], self.goal[None], self.alpha)
        direction = int(self.rng.choice(len(DIRECTIONS), p=distribution[0, 0]))
        return self._pools.draw(int(self.class_order[direction])), direction
