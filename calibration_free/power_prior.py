"""The ErrP power prior: epochs after errors carry more power (feedback frame only).

method.md's prior breaks the symmetry between hypotheses whose label sets are nearly
complementary (opposite corners): a decoder fitted on a task's labels is as good as one
fitted on the complementary labels, so only a premise about the signals themselves tells
the two apart. Forms of the same premise behind one interface (`PowerPrior`):

- `MeanPowerRatio` (``"ratio"``, method.md's): ``log(P_error(t) / P_correct(t))``,
  the log ratio of each class's mean power ``||e||^2`` under task t's label weights,
  recomputed from the whole history; bounded (about 0.3-0.5 on ErrP data), so it weighs
  as much after 500 signals as after 20.
- `LogPowerEvidence` (``"evidence"``): the premise as evidence that grows with the
  data. Each signal's log power ``z = log ||e||^2`` is modelled as Gaussian with one mean
  per class and a shared variance; under task t's label weights, the profile likelihood
  ratio of "errors have the higher mean log power" against "the lower" is
  ``sign(m_error - m_correct) * (n / 2) * log(S_total / S_within)`` (the one-way analysis
  of variance's statistic in log form; ``S`` sums of squares of ``z``). A labelling and its
  complement get opposite values, so the complement of the user's task loses what the
  task gains. Being a log ratio of powers, it does not depend on the signals' units.
- `EvidenceThenRatio` (``"evidence_then_ratio"``, the default): the evidence until
  the first target, where no label is adopted yet and a task and its complement are the
  confusion that locks a session in; the ratio from the first target on, where the
  adopted labels have settled the mapping and the evidence, added uncalibrated to the
  calibrated segments' evidence, cost wrong targets on the tuning data (README, "The
  power prior as evidence").

The first two keep per-task class sums of the label weights ``w_ik`` (with eps) and adopt
one task's sums for every task at a target switch, as the decoders' statistics do.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from decoding.validation import check_option

#: The forms of the power prior (``LearnerConfig.power_prior_kind``).
POWER_PRIOR_KINDS = ("ratio", "evidence", "evidence_then_ratio")

CORRECT, ERROR = 0, 1


class PowerPrior(ABC):
    """One form of the prior: fed every signal's power with every task's label
    distribution, told of target switches, read as a log score per task."""

    @abstractmethod
    def add(self, expected: np.ndarray, power: float) -> None:
        """Count one signal of power ``||x||^2`` (its features' units squared) with every
        task's label distribution ``expected`` (n_tasks, n_classes: correct, error)."""

    @abstractmethod
    def adopt(self, task: int) -> None:
        """A target switch: every task takes ``task``'s sums (its labels are adopted)."""

    @abstractmethod
    def scores(self) -> np.ndarray:
        """The prior's log score of every task, shape (n_tasks,)."""


class _ClassSums(PowerPrior, ABC):
    """Per task and class, the label weights' sum and the weighted sum of a value of each
    signal (its power, or its log power)."""

    def __init__(self, n_tasks: int, n_classes: int = 2) -> None:
        self._weights = np.zeros((n_tasks, n_classes))
        self._sums = np.zeros((n_tasks, n_classes))

    def _accumulate(self, expected: np.ndarray, value: float) -> None:
        self._weights += expected
        self._sums += expected * value

    def adopt(self, task: int) -> None:
        self._weights[:] = self._weights[task]
        self._sums[:] = self._sums[task]


class MeanPowerRatio(_ClassSums):
    """method.md's ``log(P_error / P_correct)``; 0 while either class has no weight."""

    def add(self, expected: np.ndarray, power: float) -> None:
        self._accumulate(expected, power)

    def scores(self) -> np.ndarray:
        return power_log_ratio(self._sums, self._weights)


class LogPowerEvidence(_ClassSums):
    """The signed profile likelihood ratio of the log powers' class order (module doc).

    0 for every task until three signals with distinct powers have arrived, and for a task
    while either class has no weight. A signal of zero power counts with the smallest
    positive double's log (it cannot occur with EEG).
    """

    def __init__(self, n_tasks: int, n_classes: int = 2) -> None:
        super().__init__(n_tasks, n_classes)
        self._moments = np.zeros(3)  # count, sum and sum of squares of z, shared by all

    def add(self, expected: np.ndarray, power: float) -> None:
        z = float(np.log(max(power, np.finfo(float).tiny)))
        self._accumulate(expected, z)
        self._moments += (1.0, z, z * z)

    def scores(self) -> np.ndarray:
        count, total, squares = self._moments
        scatter = squares - total * total / count if count else 0.0
        if count < 3 or not scatter > 0:
            return np.zeros(len(self._weights))
        defined = np.all(self._weights > 0, axis=1)
        weights = np.where(defined[:, None], self._weights, 1.0)
        means = self._sums / weights
        between = np.where(defined, (self._sums * means).sum(axis=1) - total * total / count, 0.0)
        within = np.clip(scatter - between, scatter * 1e-12, scatter)
        gain = 0.5 * count * np.log(scatter / within)
        return np.sign(means[:, ERROR] - means[:, CORRECT]) * gain


class EvidenceThenRatio(PowerPrior):
    """`LogPowerEvidence` until the first target switch, `MeanPowerRatio`
    from then on (the ratio kept from the first signal, so that it has the whole history;
    the evidence, never read again after the switch, no longer fed)."""

    def __init__(self, n_tasks: int, n_classes: int = 2) -> None:
        self._evidence = LogPowerEvidence(n_tasks, n_classes)
        self._ratio = MeanPowerRatio(n_tasks, n_classes)
        self._switched = False

    def add(self, expected: np.ndarray, power: float) -> None:
        self._ratio.add(expected, power)
        if not self._switched:
            self._evidence.add(expected, power)

    def adopt(self, task: int) -> None:
        self._ratio.adopt(task)
        self._switched = True

    def scores(self) -> np.ndarray:
        return (self._ratio if self._switched else self._evidence).scores()


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
    """The power prior of ``kind`` (one of `POWER_PRIOR_KINDS`)."""
    check_option("power_prior_kind", kind, POWER_PRIOR_KINDS)
    return _FORMS[kind](n_tasks, n_classes)


_FORMS: dict[str, type[PowerPrior]] = {
    "ratio": MeanPowerRatio,
    "evidence": LogPowerEvidence,
    "evidence_then_ratio": EvidenceThenRatio,
}
