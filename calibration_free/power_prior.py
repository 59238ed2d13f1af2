"""The ErrP power prior: epochs after errors carry more power (feedback frame only).

method.md's prior breaks the symmetry between hypotheses whose label sets are nearly
complementary (opposite corners): a decoder fitted on a task's labels is as good as one
fitted on the complementary labels, so only a premise about the signals themselves tells
the two apart. Two forms of the same premise, one interface:

- :class:`MeanPowerRatio` (``"ratio"``, method.md's): ``log(P_error(t) / P_correct(t))``,
  the log ratio of each class's mean power ``||e||^2`` under task t's label weights,
  recomputed from the whole history; bounded (about 0.3-0.5 on ErrP data), so it weighs
  as much after 500 signals as after 20.
- :class:`LogPowerEvidence` (``"evidence"``): the premise as evidence that grows with the
  data. Each signal's log power ``z = log ||e||^2`` is modelled as Gaussian with one mean
  per class and a shared variance; under task t's label weights, the profile likelihood
  ratio of "errors have the higher mean log power" against "the lower" is
  ``sign(m_error - m_correct) * (n / 2) * log(S_total / S_within)`` (the one-way analysis
  of variance's statistic in log form; ``S`` sums of squares of ``z``). A labelling and its
  complement get opposite values, so the complement of the user's task loses what the
  task gains. Being a log ratio of powers, it does not depend on the signals' units.

Both keep per-task class sums of the label weights ``w_ik`` (with eps) and adopt one
task's sums for every task at a target switch, as the decoders' statistics do.
"""

from __future__ import annotations

import numpy as np

#: The forms of the power prior (``LearnerConfig.power_prior_kind``).
POWER_PRIOR_KINDS = ("ratio", "evidence")

CORRECT, ERROR = 0, 1


class PowerPrior:
    """Per-task class sums of the label weights, and the scores of one form of the prior.

    Parameters
    ----------
    n_tasks : int
    n_classes : int
        2 (correct, error): the prior is for the feedback frame.
    """

    def __init__(self, n_tasks: int, n_classes: int = 2) -> None:
        self._weights = np.zeros((n_tasks, n_classes))

    def add(self, expected: np.ndarray, x: np.ndarray) -> None:
        """Count one signal ``x`` (n_features,) with every task's label distribution
        ``expected`` (n_tasks, n_classes)."""
        self._weights += expected

    def adopt(self, task: int) -> None:
        """Give every task ``task``'s sums (a target switch adopts its labels)."""
        self._weights[:] = self._weights[task]

    def scores(self) -> np.ndarray:
        """The prior's log score of every task, shape (n_tasks,)."""
        raise NotImplementedError


class MeanPowerRatio(PowerPrior):
    """method.md's ``log(P_error / P_correct)``; 0 while either class has no weight."""

    def __init__(self, n_tasks: int, n_classes: int = 2) -> None:
        super().__init__(n_tasks, n_classes)
        self._power_sums = np.zeros((n_tasks, n_classes))

    def add(self, expected: np.ndarray, x: np.ndarray) -> None:
        super().add(expected, x)
        self._power_sums += expected * float(x @ x)

    def adopt(self, task: int) -> None:
        super().adopt(task)
        self._power_sums[:] = self._power_sums[task]

    def scores(self) -> np.ndarray:
        return power_log_ratio(self._power_sums, self._weights)


class LogPowerEvidence(PowerPrior):
    """The signed profile likelihood ratio of the log powers' class order (module doc).

    0 for every task until three signals with distinct powers have arrived. A signal of
    zero power counts with the smallest positive double's log (it cannot occur with EEG).
    """

    def __init__(self, n_tasks: int, n_classes: int = 2) -> None:
        super().__init__(n_tasks, n_classes)
        self._log_power_sums = np.zeros((n_tasks, n_classes))
        self._moments = np.zeros(3)  # count, sum and sum of squares of z, shared by all

    def add(self, expected: np.ndarray, x: np.ndarray) -> None:
        super().add(expected, x)
        z = float(np.log(max(float(x @ x), np.finfo(float).tiny)))
        self._log_power_sums += expected * z
        self._moments += (1.0, z, z * z)

    def adopt(self, task: int) -> None:
        super().adopt(task)
        self._log_power_sums[:] = self._log_power_sums[task]

    def scores(self) -> np.ndarray:
        count, total, squares = self._moments
        scatter = squares - total * total / count if count else 0.0
        if count < 3 or not scatter > 0:
            return np.zeros(len(self._weights))
        defined = np.all(self._weights > 0, axis=1)
        weights = np.where(defined[:, None], self._weights, 1.0)
        means = self._log_power_sums / weights
        between = np.where(defined, (self._log_power_sums * means).sum(axis=1), 0.0)
        between -= np.where(defined, total * total / count, 0.0)
        within = np.clip(scatter - between, scatter * 1e-12, scatter)
        gain = 0.5 * count * np.log(scatter / within)
        return np.sign(means[:, ERROR] - means[:, CORRECT]) * gain


def power_log_ratio(power_sums: np.ndarray, weight_sums: np.ndarray) -> np.ndarray:
    """The power prior ``log(P_error / P_correct)`` of every task (feedback frame).

    Parameters
    ----------
    power_sums : ndarray, shape (n_tasks, 2)
        ``sum_i w_ik ||e_i||^2`` for k = correct, error.
    weight_sums : ndarray, shape (n_tasks, 2)
        ``sum_i w_ik``.

    Returns
    -------
    ndarray, shape (n_tasks,)
        0 for a task while either class has no weight yet.
    """
    defined = np.all(weight_sums > 0, axis=1) & np.all(power_sums > 0, axis=1)
    safe_weights = np.where(weight_sums > 0, weight_sums, 1.0)
    safe_power = np.where(power_sums > 0, power_sums, 1.0)
    mean_power = safe_power / safe_weights
    return np.where(defined, np.log(mean_power[:, ERROR] / mean_power[:, CORRECT]), 0.0)


def make_power_prior(kind: str, n_tasks: int, n_classes: int = 2) -> PowerPrior:
    """The power prior of ``kind`` (one of :data:`POWER_PRIOR_KINDS`)."""
    if kind == "ratio":
        return MeanPowerRatio(n_tasks, n_classes)
    if kind == "evidence":
        return LogPowerEvidence(n_tasks, n_classes)
    raise ValueError(f"power_prior_kind must be one of {POWER_PRIOR_KINDS}; got {kind!r}")
