"""Learning a puddle-world task from unlabelled mixed feedback + guidance signals (§2).

Every ``update_every`` steps the learner relabels the whole history under each of the 660
tasks with the mixed frame, fits every task's 6-class shrinkage LDA at once (the shared
statistics of `decoding.lda.fit_pooled_lda`) and scores each task by batch matching
without cross-validation (the likelihood ch. 4 used for speech):
``log L_t = sum_i log sum_l p(l | s_i, a_i, t) p_t(l | e_i)``; the task probabilities are
``L_t / sum_u L_u`` (the normalised likelihood). Between updates the decoders and task
probabilities stay those of the last update.

Exploration strategies (before the first update, actions are uniform):

* ``random``: uniform actions;
* ``epsilon-greedy``: an optimal action of the most likely task, a uniform one with
  probability ``epsilon``;
* ``myopic``: the action of largest uncertainty at the current state;
* ``planning``: at every update, 100 uniform states ``x_k`` get the uncertainty
  ``u_k = max_a U(x_k, a)``; the reward map ``R(x) = sum_k u_k exp(-|x - x_k|^2 / (2 *
  0.01))`` is solved by value iteration (discount 0.95) on the world's discretisation, and
  the agent acts epsilon-greedily on it.

``U(x, a)`` is the meaning-space measure of ch. 5: over up to 20 signals of the history,
the weighted variance across tasks of the expected match ``sum_l p(l | x, a, t) p_t(l | e)``.
Random draws come from the learner's generator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp, softmax

from calibration_free.puddle import PuddleWorld, mixed_frame
from calibration_free.world import value_iteration
from decoding.lda import fit_pooled_lda
from decoding.statistics import PooledStatistics
from decoding.validation import check_at_least, check_option, check_range

EXPLORATIONS = ("random", "epsilon-greedy", "myopic", "planning")


@dataclass(frozen=True)
class PuddleConfig:
    """Settings of the puddle-world learner.

    Attributes
    ----------
    exploration : {"random", "epsilon-greedy", "myopic", "planning"}
    mixing : float
        Weight of feedback in the mixed frame (the teacher's, known to the learner).
    alpha : float
        The learner's frame noise (0.1: the teacher's mistake rate).
    update_every : int
        Steps between likelihood updates.
    epsilon : float
        Exploration rate of ``epsilon-greedy`` and ``planning``.
    shrinkage : float
    n_map_states, n_map_signals : int
        Sampled states of the uncertainty map, history signals the uncertainty averages.
    kernel_variance : float
        Variance of each state's Gaussian bump in the reward map.
    map_discount : float
    """

    exploration: str = "planning"
    mixing: float = 0.5
    alpha: float = 0.1
    update_every: int = 15
    epsilon: float = 0.1
    shrinkage: float = 0.5
    n_map_states: int = 100
    n_map_signals: int = 20
    kernel_variance: float = 0.01
    map_discount: float = 0.95

    def __post_init__(self) -> None:
        check_option("exploration", self.exploration, EXPLORATIONS)
        for name in ("mixing", "alpha"):  # 0 or 1 leaves labels no weight: -inf likelihoods
            check_range(name, getattr(self, name), 0.0, 1.0, inclusive=False)
        for name in ("epsilon", "shrinkage"):
            check_range(name, getattr(self, name), 0.0, 1.0)
        for name in ("update_every", "n_map_states", "n_map_signals"):
            check_at_least(name, getattr(self, name), 1)
        check_at_least("kernel_variance", self.kernel_variance, 0, strict=True)
        check_range("map_discount", self.map_discount, 0.0, 1.0)
        if self.map_discount == 1:
            raise ValueError(f"map_discount must be in [0, 1); got {self.map_discount!r}")


class PuddleLearner:
    """Chooses actions and scores the 660 tasks (see the module docstring).

    Attributes
    ----------
    probabilities : ndarray, shape (660,)
        Normalised likelihood of every task after the last update (uniform before).
    """

    def __init__(
        self, world: PuddleWorld, config: PuddleConfig, rng: np.random.Generator
    ) -> None:
        self.world, self.config, self.rng = world, config, rng
        self.probabilities = np.full(world.n_tasks, 1.0 / world.n_tasks)
        self._states: list[np.ndarray] = []
        self._actions: list[int] = []
        self._signals: list[np.ndarray] = []
        self._decoders = None
        self._plan: np.ndarray | None = None  # (n_cells, 4) action values of the map

    def propose(self, state: np.ndarray) -> int:
        """The next action at ``state``, shape (2,)."""
        config, rng = self.config, self.rng
        if self._decoders is None or config.exploration == "random":
            return int(rng.integers(self.world.n_actions))
        if config.exploration == "myopic":
            return int(np.argmax(self._uncertainty(state[None])[0]))
        if rng.random() < config.epsilon:
            return int(rng.integers(self.world.n_actions))
        if config.exploration == "planning":
            values = self._plan[self.world.cell(state)]
            return int(rng.choice(np.flatnonzero(values >= values.max() - 1e-12)))
        best = int(np.argmax(self.probabilities))
        return int(rng.choice(np.flatnonzero(self.world.optimal_at(state[None])[best, 0])))

    def observe(self, state: np.ndarray, action: int, signal: np.ndarray) -> None:
        """Add the signal answering ``action`` taken at ``state``; update on schedule."""
        self._states.append(np.asarray(state, dtype=float))
        self._actions.append(int(action))
        self._signals.append(np.asarray(signal, dtype=float))
        if len(self._signals) % self.config.update_every == 0:
            self._update()

    def _update(self) -> None:
        states, signals = np.array(self._states), np.array(self._signals)
        labels = mixed_frame(
            self.world.optimal_at(states), np.array(self._actions), self.config.mixing,
            self.config.alpha,
        )  # (T, n, 6)
        statistics = PooledStatistics(
            scatter=signals.T @ signals,
            n_signals=np.asarray(len(signals)),
            signal_sum=signals.sum(axis=0),
            counts=labels.sum(axis=1),
            sums=np.swapaxes(labels, 1, 2) @ signals,
        )
        self._decoders = fit_pooled_lda(statistics, self.config.shrinkage)
        log_proba = self._decoders.log_proba(signals)  # (T, n, 6)
        with np.errstate(divide="ignore"):
            log_match = logsumexp(log_proba + np.log(labels), axis=2)
        self.probabilities = softmax(log_match.sum(axis=1))
        if self.config.exploration == "planning":
            self._plan = self._planned_values()

    def _uncertainty(self, states: np.ndarray) -> np.ndarray:
        """``U(x, a)`` at states (P, 2): (P, 4)."""
        signals = np.array(self._signals)
        chosen = self.rng.choice(
            len(signals), size=min(self.config.n_map_signals, len(signals)), replace=False
        )
        proba = np.exp(self._decoders.log_proba(signals[chosen]))  # (T, S, 6)
        optimal = self.world.optimal_at(states)  # (T, P, 4)
        uncertainty = np.empty((len(states), self.world.n_actions))
        for action in range(self.world.n_actions):
            frame = mixed_frame(
                optimal, np.full(len(states), action), self.config.mixing, self.config.alpha
            )  # (T, P, 6)
            expected = frame @ np.swapaxes(proba, 1, 2)  # (T, P, S)
            mean = np.tensordot(self.probabilities, expected, axes=1)
            spread = np.tensordot(self.probabilities, (expected - mean) ** 2, axes=1)
            uncertainty[:, action] = spread.sum(axis=1)
        return uncertainty

    def _planned_values(self) -> np.ndarray:
        """Action values of the kernel-smoothed uncertainty map on the discretisation."""
        config, world = self.config, self.world
        samples = self.rng.uniform(size=(config.n_map_states, 2))
        heights = self._uncertainty(samples).max(axis=1)
        reward = kernel_map(world.cell_centres, samples, heights, config.kernel_variance)
        targets = world.transitions
        return value_iteration(reward[targets], targets, discount=config.map_discount)


def kernel_map(
    points: np.ndarray, samples: np.ndarray, heights: np.ndarray, variance: float
) -> np.ndarray:
    """``R(x) = sum_k u_k exp(-|x - x_k|^2 / (2 variance))`` at ``points`` (P, 2), for
    samples (K, 2) of heights (K,): (P,). Each bump is unnormalised (height ``u_k``)."""
    distances = ((points[:, None, :] - samples[None]) ** 2).sum(axis=2)
    return np.exp(-0.5 * distances / variance) @ heights
