"""The calibrated baseline of method.md §7, behind the same interface as the learner.

A calibration phase of ``n_calibration`` actions with the target known to the device:
each action is, with probability ``correct_ratio`` (0.8), an optimal action for the
calibration target (``goal`` at the target itself) and otherwise a non-optimal one. The
device labels these signals itself from the known target. One decoder (the configured
kind) is then trained on them, its k-fold confusion estimated once, and from then on the
task posterior is a Bayesian filter with that fixed decoder: the same matching update
(always confusion-corrected: ``likelihood`` is not used), confidence rule, planner and
target-reached rule as the learner, without task relabelling and without the power
prior. Its steps to the first target include the calibration.
"""

from __future__ import annotations

import numpy as np

from calibration_free.config import LearnerConfig
from calibration_free.learner import Proposal, TaskLearner
from calibration_free.likelihood import match
from calibration_free.task_decoders import DecoderFit, TaskHistory, TaskModels
from calibration_free.world import World
from decoding.validation import check_range

DEFAULT_CALIBRATION_TRIALS = 400
DEFAULT_CORRECT_RATIO = 0.8


class CalibratedBaseline(TaskLearner):
    """Calibrate a decoder on a known target, then filter tasks with it fixed.

    Parameters
    ----------
    world : World
    calibration_target : int
        The cell the user is told to aim at during calibration (known to the device).
    n_calibration : int, default 400
        Calibration actions.
    config : LearnerConfig, optional
        Decoder, frame, confidence and planner settings (``power_prior`` is not used).
    rng : numpy Generator or seed, optional
    correct_ratio : float, default 0.8
        Share of correct actions during calibration.
    """

    def __init__(
        self,
        world: World,
        calibration_target: int,
        n_calibration: int = DEFAULT_CALIBRATION_TRIALS,
        config: LearnerConfig | None = None,
        rng: np.random.Generator | int | None = None,
        correct_ratio: float = DEFAULT_CORRECT_RATIO,
    ) -> None:
        super().__init__(world, config, rng)
        check_range("n_calibration", n_calibration, 1, 1_000_000)
        check_range("correct_ratio", correct_ratio, 0.0, 1.0)
        self.calibration_target = self._check_state(calibration_target)
        self.n_calibration = int(n_calibration)
        self.correct_ratio = correct_ratio
        self.log_likelihood = np.zeros(world.n_tasks)
        self._history: TaskHistory | None = None
        self._models: TaskModels | None = None

    @property
    def _fit(self) -> DecoderFit:
        """The calibrated decoder's fit: with ``shrinkage``, as its calibration labels are
        known, not guessed (``first_target_shrinkage`` is the learner's)."""
        return self._fits[1]

    @property
    def calibrating(self) -> bool:
        """True while the calibration actions are not all done."""
        return self.n_signals < self.n_calibration

    def propose(self, state: int) -> Proposal:
        """A calibration action (80/20) while calibrating, afterwards as the learner."""
        if not self.calibrating:
            return super().propose(state)
        state = self._check_state(state)
        optimal = self.world.optimal[self.calibration_target, state]
        pick_correct = self.rng.random() < self.correct_ratio
        candidates = np.flatnonzero(optimal if pick_correct else ~optimal)
        self._pending_target = None
        return Proposal(int(self.rng.choice(candidates)), False)

    def observe(self, state: int, action: int, signal: np.ndarray) -> None:
        """Store a calibration signal, or update the task filter with the fixed decoder."""
        x = self._check_input(state, action, signal)
        self._visits[state] += 1
        self.n_signals += 1
        if self._models is None:
            if self._history is None:
                self._history = TaskHistory(
                    1, self.frame.n_classes, x.shape[0], self.config.n_folds,
                    class_scatters=self._fit.class_scatters,
                )
            weights = self.frame.weights_at(state, action)[self.calibration_target]
            self._history.add(x, weights[None])
            if not self.calibrating:
                self._choose_shrinkage(self._history, 0)
                self._models = TaskModels.fit(
                    self._history,
                    self._fit,
                    self.config.confusion_smoothing,
                    self.config.balanced_confusion,
                )
            return
        corrected = self._models.corrected_proba(x[None])[0, 0]
        expected = self.frame.distribution_at(state, action)
        self.log_likelihood += np.log(match(expected, np.broadcast_to(corrected, expected.shape)))
        if self._take_target_reached(state, action) is not None:
            self.log_likelihood[:] = 0.0

    def _predicted_samples(self) -> np.ndarray | None:
        if self._models is None or self._history is None:
            return None
        signals = self._history.signals[self._sample_indices(self._history.n_signals)]
        corrected = self._models.corrected_proba(signals)
        return np.broadcast_to(corrected, (self.world.n_tasks, *corrected.shape[1:]))

    def _class_means(self) -> np.ndarray | None:
        """The calibrated decoder's class means, the same for every task."""
        if self._models is None or self._history is None:
            return None
        means = self._history.class_means()
        return np.broadcast_to(means, (self.world.n_tasks, *means.shape[1:]))
