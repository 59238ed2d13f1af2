"""Choosing the next action while not confident: the planners (method.md §6,
method-extensions §1(a)7 and §6.3), behind one interface, `Planner`.

`PLANNERS`: ``"uncertainty"`` (meaning-space uncertainty, value iteration),
``"information"`` (the expected information of the next answer about the task, value
iteration),
``"signal"`` (signal-space uncertainty from the class means, value iteration),
``"greedy"`` (an optimal action towards the most likely task), ``"epsilon-greedy"``
(with probability ``epsilon`` a uniform action, else greedy) and ``"random"``. The learner
takes uniform actions during its warm-up whatever the planner, and walks greedily to its
task once confident.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from scipy.special import xlogy

from calibration_free.frames import Frame
from calibration_free.signal_space import signal_space_uncertainty
from calibration_free.ties import near_best
from calibration_free.world import World, optimal_action_values
from decoding.validation import check_option, check_range

PLANNERS: tuple[str, ...] = (
    "uncertainty", "information", "greedy", "random", "signal", "epsilon-greedy"
)
DEFAULT_DISCOUNT = 0.9
DEFAULT_EPSILON = 0.1
#: Indicator elements the uncertainty planner builds at a time (bounds its temporaries).
_CHUNK_ELEMENTS = 1 << 22
#: Bytes of row indicators the uncertainty planner keeps from one step to the next: built
#: once when they fit (6.4 MB at 20 x 20 in feedback), else chunk by chunk at every step.
KEPT_INDICATOR_BYTES = 64 << 20


def random_action(world: World, rng: np.random.Generator) -> int:
    """An action drawn uniformly among all actions (the grid's ``goal`` included)."""
    return int(rng.integers(world.n_actions))


def greedy_action(world: World, state: int, task: int, rng: np.random.Generator) -> int:
    """An optimal action towards ``task``, ties drawn at random; in the task's state, the
    world's declaration action (the grid's ``goal``) where it has one."""
    if state == world.task_states[task]:
        declaration = world.declaration_action(state)
        if declaration is not None:
            return declaration
    return int(rng.choice(np.flatnonzero(world.optimal[task, state])))


@dataclass(frozen=True)
class PlanningInputs:
    """What a planner may use of the learner's state; the costly parts are computed only
    when a planner asks for them.

    Attributes
    ----------
    best_task : int
        The most likely task.
    task_weights : ndarray, shape (n_tasks,)
        Non-negative task weights summing to 1 (``LearnerConfig.planning_weights``).
    state_bonus : ndarray, shape (n_states,), or None
        Bonus of being in every state, added to an uncertainty reward scaled to a maximum
        of 1: the learner's novelty bonus and its pull toward the likely goals (None:
        neither).
    predicted_samples : callable () -> ndarray (n_tasks, n_signals, n_classes) or None
        Every task's prediction (the likelihood's, see
        `calibration_free.task_likelihoods.TaskLikelihood.predict`) of past signals
        sampled for this step; None before any decoder. Draws the sample from the
        learner's rng.
    class_means : callable () -> ndarray (n_tasks, n_classes, n_features) or None
        Every task decoder's class means; None before any signal.
    """

    best_task: int
    task_weights: np.ndarray
    state_bonus: np.ndarray | None
    predicted_samples: Callable[[], np.ndarray | None]
    class_means: Callable[[], np.ndarray | None]


class Planner(ABC):
    """Chooses an action from a state (the interface of every planner).

    Parameters
    ----------
    frame : Frame
        The interaction frame (and through it the world) the tasks are judged in.
    """

    def __init__(self, frame: Frame) -> None:
        self.frame = frame
        self.world = frame.world

    @abstractmethod
    def action(self, state: int, inputs: PlanningInputs, rng: np.random.Generator) -> int:
        """The action to take from ``state``."""


class RandomPlanner(Planner):
    """A uniform action."""

    def action(self, state: int, inputs: PlanningInputs, rng: np.random.Generator) -> int:
        return random_action(self.world, rng)


class GreedyPlanner(Planner):
    """An optimal action towards the most likely task."""

    def action(self, state: int, inputs: PlanningInputs, rng: np.random.Generator) -> int:
        return greedy_action(self.world, state, inputs.best_task, rng)


class EpsilonGreedyPlanner(Planner):
    """With probability ``epsilon`` a uniform action, else greedy on the most likely task.

    One uniform draw from the rng decides, then the action's own draw.
    """

    def __init__(self, frame: Frame, epsilon: float = DEFAULT_EPSILON) -> None:
        super().__init__(frame)
        self.epsilon = check_range("epsilon", epsilon, 0.0, 1.0)

    def action(self, state: int, inputs: PlanningInputs, rng: np.random.Generator) -> int:
        if rng.random() < self.epsilon:
            return random_action(self.world, rng)
        return greedy_action(self.world, state, inputs.best_task, rng)


class RewardPlanner(Planner):
    """Value iteration on an uncertainty reward, then the best action (ties at random).

    Subclasses provide `reward`. Before it can be computed (no decoder yet) the
    action is uniform.

    Parameters
    ----------
    frame : Frame
    discount : float, default 0.9
        Discount of the value iteration.
    """

    def __init__(self, frame: Frame, discount: float = DEFAULT_DISCOUNT) -> None:
        super().__init__(frame)
        self.discount = discount

    @abstractmethod
    def reward(self, inputs: PlanningInputs) -> np.ndarray | None:
        """Uncertainty of every (state, action), shape (n_states, n_actions), or None."""

    def action(self, state: int, inputs: PlanningInputs, rng: np.random.Generator) -> int:
        """The best action from ``state`` under the reward plus ``inputs.state_bonus``."""
        reward = self.reward(inputs)
        if reward is None:
            return random_action(self.world, rng)
        if inputs.state_bonus is not None:
            scale = max(reward.max(), np.finfo(float).tiny)
            reward = reward / scale + inputs.state_bonus[:, None]
        q = optimal_action_values(reward, self.world.transitions, self.discount)[state]
        return int(rng.choice(np.flatnonzero(near_best(q))))


class UncertaintyPlanner(RewardPlanner):
    """Rewards state-actions whose expected signal would best tell hypotheses apart.

    For sampled past signals ``e`` and every (s, a, t), the expected match is
    ``m_t(s, a, e) = sum_l p(l | s, a, t) q_t(e)_l``. The reward of (s, a) is the
    variance of ``m_t`` across tasks, weighted by the task weights, summed over the
    signals; value iteration on that reward gives the action to take.

    The frame has few distinct label rows ``D_r`` (`Frame`),
    so ``m_t(s, a, e) = M[t, e, r]`` with ``M = q D^T`` and ``r`` the row of (t, s, a).
    Both moments over tasks are then sums over the rows of ``(weights x M)`` times the
    indicator of row ``r`` (T x columns): per step ``(n_rows - 1)`` products of an
    ``(n_signals + 1, T)`` matrix with an indicator of the frame's uint8 row table, kept
    from step to step where it is small (up to 64 MB: 6.4 MB at 20 x 20) and built chunk by
    chunk at every step otherwise; exactly the old formula up to rounding. Where the
    frame's labels do not depend on the action (guidance) the columns are states, not
    (state, action) pairs.

    Parameters
    ----------
    frame : Frame
        The interaction frame (and through it the world) the tasks are judged in.
    discount : float, default 0.9
        Discount of the value iteration.
    """

    def __init__(self, frame: Frame, discount: float = DEFAULT_DISCOUNT) -> None:
        super().__init__(frame, discount)
        self._kept_indicators: list[tuple[int, int, list[np.ndarray]]] | None = None

    def reward(self, inputs: PlanningInputs) -> np.ndarray | None:
        predicted = inputs.predicted_samples()
        return None if predicted is None else self.rewards(predicted, inputs.task_weights)

    def rewards(self, corrected: np.ndarray, task_weights: np.ndarray) -> np.ndarray:
        """Uncertainty of every state-action.

        Parameters
        ----------
        corrected : ndarray, shape (n_tasks, n_signals, n_classes)
            ``q_t(e)`` of the sampled signals.
        task_weights : ndarray, shape (n_tasks,)
            Non-negative, summing to 1.

        Returns
        -------
        ndarray, shape (n_states, n_actions)
        """
        index = self.frame.row_index
        n_tasks, n_states, n_kinds = index.shape
        columns = index.reshape(n_tasks, n_states * n_kinds)
        matches = corrected @ self.frame.distribution_rows.T  # (T, n, R)
        per_signal, summed = self._task_terms(matches, task_weights)
        # Per task and row: [a term per signal e, a term summed over them], (T, n + 1, R).
        moments = np.concatenate([per_signal, summed[:, None]], axis=1)
        # Row 0 everywhere, plus what each other row changes where it applies.
        base = moments[:, :, 0].sum(axis=0)
        offsets = np.ascontiguousarray(  # (R - 1, n + 1, T), contiguous for BLAS
            (moments[:, :, 1:] - moments[:, :, :1]).transpose(2, 1, 0)
        )
        reward = np.empty(columns.shape[1])
        for start, stop, indicators in self._row_indicators(columns, len(offsets) + 1):
            totals = np.repeat(base[:, None], stop - start, axis=1)
            for offset, indicator in zip(offsets, indicators, strict=True):
                totals += offset @ indicator
            reward[start:stop] = self._combine(totals[:-1], totals[-1])
        reward = np.maximum(reward, 0.0).reshape(n_states, n_kinds)
        return np.broadcast_to(reward, (n_states, self.world.n_actions)).copy()

    def _row_indicators(
        self, columns: np.ndarray, n_rows: int
    ) -> Iterable[tuple[int, int, list[np.ndarray]]]:
        """Chunks of the columns of the frame's row table ``columns`` (T, C): ``(start,
        stop, [float indicator (T, stop - start) of row r, for r = 1 .. n_rows - 1])``. The
        table never changes: the indicators are kept if they fit in
        `KEPT_INDICATOR_BYTES`, else built again at each call, a chunk at a time."""
        if self._kept_indicators is not None:
            return self._kept_indicators
        n_tasks, n_columns = columns.shape
        chunk = max(1, _CHUNK_ELEMENTS // n_tasks)
        chunks = (
            (start, min(start + chunk, n_columns), [
                (columns[:, start : start + chunk] == row).astype(float)
                for row in range(1, n_rows)
            ])
            for start in range(0, n_columns, chunk)
        )
        if columns.size * (n_rows - 1) * 8 > KEPT_INDICATOR_BYTES:
            return chunks
        self._kept_indicators = list(chunks)
        return self._kept_indicators

    @staticmethod
    def _task_terms(matches: np.ndarray, task_weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per task, signal and label row: ``w m`` (T, n, R); and ``sum_e w m^2`` (T, R)."""
        weighted = matches * task_weights[:, None, None]
        return weighted, np.einsum("tnr,tnr->tr", weighted, matches)

    @staticmethod
    def _combine(per_signal: np.ndarray, summed: np.ndarray) -> np.ndarray:
        """The reward of every column from the task sums of `_task_terms`, (n, C) and
        (C,): the weighted variance ``sum_e (sum_t w m^2 - (sum_t w m)^2)``."""
        return summed - np.sum(per_signal**2, axis=0)


class InformationPlanner(UncertaintyPlanner):
    """Rewards state-actions by the expected information their answer gives about the task.

    The mutual information between the task and the next signal, ``I(s, a) = sum_t w_t
    KL(p(e | t, s, a) || sum_u w_u p(e | u, s, a))``, estimated on the sampled past
    signals ``e`` (drawn from the signals' marginal): under equal class priors ``p(e | t,
    s, a)`` is proportional to the expected match ``m_t(s, a, e)``, so the self-normalised
    ``m~_t(e) = m_t(e) / sum_e' m_t(e')`` gives ``I = sum_e (sum_t w m~ log m~ - M log M)``
    with ``M(e) = sum_t w_t m~_t(e)``. The decoder's uncertainty is in it through the
    confusion-corrected ``q``: a decoder that cannot tell classes apart gives every
    signal the same match, and no information. Same row-indicator sums and value
    iteration as `UncertaintyPlanner` (whose weighted variance is this quantity's
    second-order approximation, without the division by ``M``).
    """

    @staticmethod
    def _task_terms(matches: np.ndarray, task_weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``w m~`` (T, n, R) and ``sum_e w m~ log m~`` (T, R)."""
        totals = matches.sum(axis=1, keepdims=True)
        normalised = matches / np.where(totals > 0, totals, 1.0)
        weighted = normalised * task_weights[:, None, None]
        return weighted, np.sum(xlogy(weighted, normalised), axis=1)

    @staticmethod
    def _combine(per_signal: np.ndarray, summed: np.ndarray) -> np.ndarray:
        return summed - np.sum(xlogy(per_signal, per_signal), axis=0)


class SignalPlanner(RewardPlanner):
    """Rewards state-actions where the hypotheses expect far-apart signals (the code's
    ``'signal_trace'``, method-extensions §1(a)7).

    For every (s, a) and task t, the frame's most probable label ``l*_t(s, a)`` (ties to
    the lower class) and the mean of that class in task t's decoder give the signal t
    expects; the reward is the weighted spread of those means,
    ``U(s, a) = sum_t w_t ||mu_t(s, a) - mu_bar(s, a)||^2``
    (`calibration_free.signal_space.signal_space_uncertainty`).

    Parameters
    ----------
    frame : Frame
    discount : float, default 0.9
        Discount of the value iteration (the thesis: 0.95).
    """

    def reward(self, inputs: PlanningInputs) -> np.ndarray | None:
        means = inputs.class_means()
        return None if means is None else self.rewards(means, inputs.task_weights)

    def rewards(self, class_means: np.ndarray, task_weights: np.ndarray) -> np.ndarray:
        """Uncertainty of every state-action, shape (n_states, n_actions).

        ``class_means`` (n_tasks, n_classes, n_features), ``task_weights`` (n_tasks,)
        non-negative summing to 1.
        """
        most_probable_row = np.argmax(self.frame.distribution_rows, axis=1).astype(np.uint8)
        labels = most_probable_row[self.frame.row_index]  # (n_tasks, n_states, A or 1)
        uncertainty = signal_space_uncertainty(class_means, labels, task_weights)
        return np.broadcast_to(uncertainty, (self.world.n_states, self.world.n_actions)).copy()


def make_planner(
    kind: str, frame: Frame, discount: float = DEFAULT_DISCOUNT, epsilon: float = DEFAULT_EPSILON
) -> Planner:
    """The planner of kind ``kind`` (one of `PLANNERS`)."""
    check_option("planner", kind, PLANNERS)
    if kind == "uncertainty":
        return UncertaintyPlanner(frame, discount)
    if kind == "information":
        return InformationPlanner(frame, discount)
    if kind == "signal":
        return SignalPlanner(frame, discount)
    if kind == "epsilon-greedy":
        return EpsilonGreedyPlanner(frame, epsilon)
    return GreedyPlanner(frame) if kind == "greedy" else RandomPlanner(frame)
