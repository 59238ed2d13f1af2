"""Calibrated evidence after a target: the temperature's fit, and the learner's use of it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.special import softmax
from test_learner import WORLD

from calibration_free.config import LearnerConfig
from calibration_free.evidence_temperature import TEMPERATURE_BOUNDS, fit_temperature
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.likelihood import label_log_matches, normalised_likelihood
from calibration_free.world import GOAL
from session.config import learner_settings, recorded_config


def labels_drawn_at(temperature: float, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random predictions' label log matches (eps 0.1) and one-hot labels drawn from
    ``softmax(temperature * log m)``: labels for which ``temperature`` is calibrated."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(0.05, 0.95, size=n)
    log_matches = label_log_matches(np.column_stack([q, 1.0 - q]), eps=0.1)
    probabilities = softmax(temperature * log_matches, axis=1)
    drawn = (rng.random(n) < probabilities[:, 1]).astype(int)
    return log_matches, np.eye(2)[drawn]


def test_the_label_matches_are_tempered_by_eps() -> None:
    log_matches = label_log_matches(np.array([[0.8, 0.2], [0.5, 0.5]]), eps=0.1)
    expected = np.log([[0.9 * 0.8 + 0.1 * 0.2, 0.9 * 0.2 + 0.1 * 0.8], [0.5, 0.5]])
    np.testing.assert_allclose(log_matches, expected, rtol=1e-12)


@pytest.mark.parametrize("temperature", [1.0, 2.5, 4.0])
def test_the_fit_recovers_the_temperature_the_labels_were_drawn_at(temperature: float) -> None:
    log_matches, labels = labels_drawn_at(temperature, n=20_000, seed=3)
    assert fit_temperature(log_matches, labels) == pytest.approx(temperature, rel=0.06)


def test_labels_unrelated_to_the_matches_give_the_lowest_temperature() -> None:
    log_matches, _ = labels_drawn_at(2.0, n=5_000, seed=4)
    unrelated = np.eye(2)[np.random.default_rng(5).integers(2, size=5_000)]
    assert fit_temperature(log_matches, unrelated) < 0.3
    assert fit_temperature(log_matches, unrelated) >= TEMPERATURE_BOUNDS[0]


def test_labels_of_another_shape_are_refused() -> None:
    with pytest.raises(ValueError, match=r"log matches \(3, 2\) and label weights \(2, 2\)"):
        fit_temperature(np.zeros((3, 2)), np.eye(2))


def weak_signal(label: int, rng: np.random.Generator) -> np.ndarray:
    """Two classes one standard deviation apart in 4 dimensions: evidence to calibrate."""
    return (rng.normal(size=4) + 1.0 * label).astype(np.float32)


def session_steps(seed: int = 0) -> list[tuple[int, int, np.ndarray, int | None]]:
    """(state, action, signal, declared task or None): 60 random actions toward target 5,
    a walk to it and ``goal`` there, then 40 random actions toward target 10."""
    rng = np.random.default_rng(seed)
    steps, state = [], 0

    def act(action: int, target: int, declares: int | None = None) -> None:
        nonlocal state
        label = 0 if WORLD.optimal[target, state, action] else 1
        steps.append((state, action, weak_signal(label, rng), declares))
        state = WORLD.step(state, action)

    for _ in range(60):
        act(int(rng.integers(WORLD.n_actions)), target=5)
    while state != WORLD.task_states[5]:
        act(int(np.flatnonzero(WORLD.optimal[5, state])[0]), target=5)
    act(GOAL, target=5, declares=5)
    for _ in range(40):
        act(int(rng.integers(WORLD.n_actions)), target=10)
    return steps


def replay(config: LearnerConfig) -> tuple[CalibrationFreeLearner, list[tuple]]:
    """A learner fed `session_steps` open-loop; per step after the target, (its
    log-likelihood, the decision rule's confidence of the best task)."""
    learner = CalibrationFreeLearner(WORLD, config, rng=0)
    after_target = []
    for state, action, signal, declares in session_steps():
        if declares is not None:
            learner.follow_declaration(declares)
        learner.observe(state, action, signal)
        if learner.n_targets:
            beliefs = learner.beliefs()
            after_target.append(
                (learner.log_likelihood.copy(), beliefs.confidence[beliefs.best_task])
            )
    return learner, after_target


def test_after_a_target_the_evidence_is_the_tempered_evidence_times_the_temperature() -> None:
    tempered = LearnerConfig(calibrated_evidence=False, power_prior=False)
    plain, plain_steps = replay(tempered)
    calibrated, calibrated_steps = replay(replace(tempered, calibrated_evidence=None,
                                                  calibration_signals=50))
    assert plain.n_targets == calibrated.n_targets == 1
    assert plain.evidence_temperature == 1.0
    temperature = calibrated.evidence_temperature
    assert temperature > 1.2, "one-SD classes: the tempered evidence is too weak"
    # The decoders do not depend on the temperature: only the evidence is scaled.
    for (log_plain, _), (log_calibrated, confidence) in zip(
        plain_steps, calibrated_steps, strict=True
    ):
        np.testing.assert_allclose(log_calibrated, temperature * log_plain, rtol=1e-9, atol=1e-12)
        # The decision rule is the normalised likelihood.
        assert confidence == pytest.approx(normalised_likelihood(log_calibrated).max())
    # The temperature is the one that calibrates the adopted labels' out-of-fold matches.
    history = calibrated.history
    n_adopted = history.n_adopted
    learner = CalibrationFreeLearner(WORLD, tempered, rng=0)
    for state, action, signal, declares in session_steps()[:n_adopted]:
        if declares is not None:
            learner.follow_declaration(declares)
        learner.observe(state, action, signal)
    models = learner._current_models()
    corrected = models.held_out_corrected_proba(0)
    labels = learner.history.task_label_weights(0)
    assert temperature == fit_temperature(label_log_matches(corrected, 0.1), labels)


def test_a_target_on_fewer_signals_than_the_calibration_needs_keeps_the_tempered_rule() -> None:
    config = LearnerConfig(power_prior=False, calibration_signals=500)
    learner, after_target = replay(config)
    assert learner.n_targets == 1 and learner.evidence_temperature == 1.0
    log_likelihood, confidence = after_target[-1]
    best = int(np.argmax(log_likelihood))
    others = np.delete(log_likelihood, best)
    pairwise = 1.0 / (1.0 + np.exp(others.max() - log_likelihood[best]))
    assert confidence == pytest.approx(pairwise)


def test_the_held_out_corrected_probabilities_are_the_confusion_times_the_held_out_ones() -> None:
    learner, _ = replay(LearnerConfig(power_prior=False))
    models = learner._current_models()
    raw = models.held_out_proba(0)
    for task in (0, 5, 10):
        confusion = models.confusion[models.labelling[task]]
        np.testing.assert_allclose(
            models.held_out_corrected_proba(task), raw[task] @ confusion.T, rtol=1e-12
        )


def test_calibrated_evidence_is_feedbacks_default_and_is_recorded_resolved() -> None:
    assert LearnerConfig().uses_calibrated_evidence
    assert LearnerConfig().to_dict()["calibrated_evidence"] is True
    for config in (
        LearnerConfig(frame="guidance"),
        LearnerConfig(likelihood="simple"),
        LearnerConfig(declare_targets=False),
    ):
        assert not config.uses_calibrated_evidence
        assert config.to_dict()["calibrated_evidence"] is False
    # A recording from before the setting ran without it.
    settings = LearnerConfig().to_dict()
    del settings["calibrated_evidence"]
    old = recorded_config({"learner": settings, "frame": "feedback"})["learner"]
    assert not learner_settings(old, "feedback").uses_calibrated_evidence


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"calibrated_evidence": True, "frame": "guidance"},
         "calibrated_evidence needs frame 'feedback'"),
        ({"calibrated_evidence": True, "likelihood": "batch"}, "likelihood 'batch'"),
        ({"calibrated_evidence": 1}, "calibrated_evidence must be true, false or null"),
        ({"calibrated_beta": 1.0}, "calibrated_beta"),
        ({"calibration_signals": 0}, "calibration_signals"),
    ],
)
def test_settings_that_cannot_calibrate_are_refused(values: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LearnerConfig(**values)
