"""The simulated user: holds a hidden target and answers every device action with a signal.

For every action the user decides the label its brain would produce under the current
target and the interaction frame, then answers with a recorded (or synthetic) signal of
that label, drawn without replacement from that label's pool; an empty pool is refilled
with a fresh shuffle. The target is a task of the world (the grid's: a cell). After every
target the device declares reached, correct or not, the user picks a new target uniformly
among the other tasks.

Feedback frame: label 0 (correct) if the action is optimal for the target, else 1 (error).
Guidance frame: the label is the guidance action the user wants from the current state:
dataset class ``k`` stands for ``world.guidance_actions[k]`` — on the grid ``MOVES[k]``,
0 up, 1 down, 2 left, 3 right (for ``move_finger.mat``, ``Y`` = 1..4 in that order). The
choice is uniform among the optimal guidance actions, and among all of them where none is
optimal (the grid's target cell itself). The learner never knows this mapping.

With ``error_rate`` > 0 the user gives a wrong label with that probability: the other
class for feedback, a uniformly drawn non-optimal guidance action for guidance.

Random draws, in order, from the user's generator: the agent's start state (none in a
world with a fixed start, e.g. the line world's middle), the first target, then for every
action one uniform draw for the error coin, the guidance choice (guidance only), and pool
shuffles when a pool is (re)filled.
"""

from __future__ import annotations

import numpy as np

from acquisition.signal_pools import SignalPools
from calibration_free.frames import CORRECT, ERROR, FRAMES
from calibration_free.world import World
from decoding.validation import check_option, check_range


class SimulatedUser:
    """A user with a hidden target, answering actions with indices into a labelled pool.

    Parameters
    ----------
    world : World
    frame : {"feedback", "guidance"}
    labels : ndarray, shape (n_signals,), int
        Class of every signal of the dataset the user answers from.
    rng : numpy Generator
    error_rate : float, default 0.0
        Probability that the user's label is not the frame's.

    Attributes
    ----------
    start_state : int
        The state the agent starts in (`World.start_state`: uniform on the grid).
    target : int
        The current hidden target (a task index; on the grid, a cell).
    """

    def __init__(
        self,
        world: World,
        frame: str,
        labels: np.ndarray,
        rng: np.random.Generator,
        error_rate: float = 0.0,
    ) -> None:
        check_option("frame", frame, FRAMES)
        check_range("user error rate", error_rate, 0.0, 1.0)
        self.world, self.frame, self.rng, self.error_rate = world, frame, rng, error_rate
        labels = np.asarray(labels)
        self._guidance = np.array(world.guidance_actions)
        n_classes = 2 if frame == "feedback" else len(self._guidance)
        self._pools = SignalPools(labels, n_classes, rng, f" for the {frame} frame")
        self.start_state = world.start_state(rng)
        self.target = int(rng.integers(world.n_tasks))

    def label(self, state: int, action: int) -> int:
        """The class the user's brain produces for ``action`` taken in ``state``."""
        wrong = self.rng.random() < self.error_rate
        optimal = self.world.optimal[self.target, state]
        if self.frame == "feedback":
            is_error = (not optimal[action]) != wrong
            return ERROR if is_error else CORRECT
        n_classes = len(self._guidance)
        directions = np.flatnonzero(optimal[self._guidance])
        if len(directions) == 0:
            directions = np.arange(n_classes)
        if wrong and len(directions) < n_classes:
            directions = np.setdiff1d(np.arange(n_classes), directions)
        return int(self.rng.choice(directions))

    def answer(self, state: int, action: int) -> tuple[int, int]:
        """(index of the signal in the dataset, its class) for ``action`` taken in ``state``."""
        label = self.label(state, action)
        return self._pools.draw(label), label

    def new_target(self) -> int:
        """Pick the next target uniformly among the tasks other than the current one."""
        others = np.delete(np.arange(self.world.n_tasks), self.target)
        self.target = int(self.rng.choice(others))
        return self.target

