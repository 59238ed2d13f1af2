"""The simulated teacher of the puddle world: feedback or guidance, with mistakes (§2).

For every action the teacher gives feedback with probability ``mixing`` (correct when the
action is optimal for its task at the state), otherwise guidance (an optimal direction,
uniformly among ties); with probability ``mistake_rate`` the answer is wrong (the other
feedback label, or a uniform non-optimal direction). It answers with a signal of the
dataset class standing for that label: class ``k`` is label ``k`` of
`calibration_free.puddle.MIXED_LABELS` (correct, incorrect, north, south, east,
west), unknown to the learner. Random draws, in order, from the teacher's generator: the
task, then per action the feedback-or-guidance coin, the mistake coin, the direction
(guidance only), and pool shuffles when a pool is (re)filled.

The signals themselves (`gaussian_signals`, on the session's data stream) are six
classes of the Gaussian generator, 20-D, nominal accuracy 0.95, as many per class as the
ErrP synthetic pools: the offline sessions (`cfbci.offline.puddle`) and the live source
(`acquisition.simulated_source`) draw them here.
"""

from __future__ import annotations

import numpy as np

from acquisition.gaussian import generate_gaussian_features
from acquisition.labelled import LabelledFeatures
from acquisition.signal_pools import SignalPools
from acquisition.sources import SYNTHETIC_EPOCHS_PER_CLASS
from calibration_free.puddle import MIXED_LABELS, PuddleWorld

#: The Gaussian stand-in for the thesis's speech features: six words, 20-D.
SIGNAL_DIMS, SIGNAL_ACCURACY = 20, 0.95


def gaussian_signals(rng: np.random.Generator) -> LabelledFeatures:
    """A puddle session's six-class signals (class ``k`` stands for label ``k`` of
    `calibration_free.puddle.MIXED_LABELS`)."""
    return generate_gaussian_features(
        SYNTHETIC_EPOCHS_PER_CLASS, len(MIXED_LABELS), SIGNAL_DIMS, SIGNAL_ACCURACY, rng
    )


class MixedTeacher:
    """A teacher with a hidden puddle-world task.

    Parameters
    ----------
    world : PuddleWorld
    labels : ndarray of int, shape (n_signals,)
        Dataset classes 0..5.
    rng : Generator
    mixing : float, default 0.5
    mistake_rate : float, default 0.1

    Attributes
    ----------
    task : int
    """

    def __init__(
        self,
        world: PuddleWorld,
        labels: np.ndarray,
        rng: np.random.Generator,
        mixing: float = 0.5,
        mistake_rate: float = 0.1,
    ) -> None:
        self.world, self.rng, self.mixing, self.mistake_rate = world, rng, mixing, mistake_rate
        self.task = int(rng.integers(world.n_tasks))
        self._pools = SignalPools(labels, len(MIXED_LABELS), rng)

    def label(self, state: np.ndarray, action: int) -> int:
        """The label (index into MIXED_LABELS) of the teacher's answer."""
        optimal = self.world.optimal_at(np.asarray(state)[None])[self.task, 0]
        feedback = self.rng.random() < self.mixing
        mistake = self.rng.random() < self.mistake_rate
        if feedback:
            return int(optimal[action] == mistake)  # 0 correct, 1 incorrect
        directions = np.flatnonzero(optimal != mistake)
        if len(directions) == 0:  # every direction optimal: a mistake is impossible
            directions = np.arange(len(optimal))
        return 2 + int(self.rng.choice(directions))

    def answer(self, state: np.ndarray, action: int) -> tuple[int, int]:
        """(index of the signal in the dataset, its label)."""
        label = self.label(state, action)
        return self._pools.draw(label), label
