"""The returning user's prior: its algebra (pseudo-observations equal live signals), the
recordings it is read from (adopted labels only, never the truth, no task information), its
feature space, and the learner that checks it against the blank learner."""

from __future__ import annotations

import copy
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conformance import TaskTeacher, check_learner

from acquisition.gaussian import generate_gaussian_features
from acquisition.labelled import LabelledFeatures
from acquisition.loaders import features_from_epochs
from acquisition.synthetic import ResponseDrift, generate_errp_epochs
from calibration_free.config import LearnerConfig
from calibration_free.frames import Frame
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.prior import (
    FeatureSpace,
    Prior,
    PriorSession,
    ReturningLearner,
    adopted_labels,
    power_premise,
)
from calibration_free.streams import session_streams
from calibration_free.world import GridWorld
from cfbci.bench.returning import DayOneTape, recorded_config
from cfbci.cli import main
from cfbci.offline.simulation import SessionConfig, run_session
from replay.prior import read_prior, read_prior_session
from replay.recording import SessionRecorder, decode_array, read_recording
from replay.rerun import Rerun, recorded_signals
from session.sessions import task_learner

#: Small, fast settings; the power prior off: Gaussian signals know no ErrP power premise.
SMALL = {"n_folds": 5, "n_planning_signals": 5, "power_prior": False}
GAUSSIAN = {"n_classes": 2, "n_dims": 4, "accuracy": 0.85}


def gaussian(seed: int, n_per_class: int = 300) -> LabelledFeatures:
    """Two-class Gaussian signals, float32 values."""
    data = generate_gaussian_features(n_per_class, seed=seed, **GAUSSIAN)
    return replace(data, features=data.features.astype(np.float32).astype(np.float64))


def record_day(path: Path, seed: int, steps: int, data: LabelledFeatures, grid: int = 3) -> None:
    """A simulated session recorded as the service records one (the bench's tape)."""
    config = SessionConfig(steps=steps, grid=grid, learner=LearnerConfig(**SMALL))
    fields = recorded_config(seed, config, data, "gaussian test signals")
    with SessionRecorder(path, f"day-{seed}", fields) as recorder:
        run_session(seed, config, data, on_move=DayOneTape(recorder, fields, data))


@pytest.fixture(scope="module")
def day_one(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("prior") / "day1.mcap"
    record_day(path, seed=3, steps=160, data=gaussian(1))
    return path


def feed(learner: CalibrationFreeLearner, steps: list[tuple[int, int, np.ndarray]]) -> None:
    for state, action, signal in steps:
        learner.observe(state, action, signal.astype(np.float32))


def random_steps(world: GridWorld, data: LabelledFeatures, n: int, seed: int) -> list:
    rng = np.random.default_rng(seed)
    return [
        (int(rng.integers(world.n_states)), int(rng.integers(world.n_actions)),
         data.features[int(rng.integers(len(data.features)))])
        for _ in range(n)
    ]


def assert_same_statistics(first: CalibrationFreeLearner, second: CalibrationFreeLearner) -> None:
    a, b = first.history.pooled_statistics(), second.history.pooled_statistics()
    for name in ("scatter", "n_signals", "signal_sum", "counts", "sums"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.eigen is not None and b.eigen is not None
    for name in ("basis", "eigenvalues", "pending"):
        assert np.array_equal(getattr(a.eigen, name), getattr(b.eigen, name)), name


@pytest.mark.parametrize("decoder", ["lda", "student_t"])
def test_a_prior_is_the_same_signals_fed_live(decoder: str) -> None:
    """A learner that observed signals and adopted a task's labels at a target, and one
    started from those signals and labels as a prior (weight 1): the same statistics, bit
    for bit, then the same proposals and beliefs on the same next signals."""
    world, data = GridWorld(3), gaussian(2)
    config = LearnerConfig(decoder=decoder, shrinkage=0.5 if decoder == "student_t" else None,
                           **SMALL)
    live = CalibrationFreeLearner(world, config, np.random.default_rng(0))
    feed(live, random_steps(world, data, 120, seed=1))
    target = 4  # goal at the target's cell, declared: its labels adopted by every task
    live.follow_declaration(target)
    feed(live, [(target, world.declaration_action(target), data.features[0])])
    assert live.n_targets == 1 and live.history.n_adopted == 121
    informed = CalibrationFreeLearner(world, config, copy.deepcopy(live.rng))
    informed.adopt_prior(
        live.history.signals.astype(np.float32), live.history.task_label_weights(target),
        np.ones(live.history.n_signals),
    )
    if decoder == "lda":
        assert_same_statistics(live, informed)
    else:
        for a, b in zip(live.history.class_statistics()[0].__dict__.values(),
                        informed.history.class_statistics()[0].__dict__.values(), strict=True):
            assert np.array_equal(a, b)
    assert informed.shrinkage_in_use == live.shrinkage_in_use
    for state, _, signal in random_steps(world, data, 25, seed=2):
        proposals = live.propose(state), informed.propose(state)
        assert proposals[0] == proposals[1]
        feed(live, [(state, proposals[0].action, signal)])
        feed(informed, [(state, proposals[1].action, signal)])
        assert np.array_equal(live.beliefs().confidence, informed.beliefs().confidence)
    assert informed.n_signals == 25 and live.evidence_temperature == informed.evidence_temperature


def test_weighted_pseudo_observations() -> None:
    """Pseudo-observations of weight w count w times in every statistic (the whole
    history's scatter, sum, size, class counts and sums), against direct weighted sums."""
    world, data = GridWorld(3), gaussian(3, n_per_class=40)
    labels = np.eye(2)[data.labels]
    weights = np.random.default_rng(0).uniform(0.1, 2.0, len(labels))
    learner = CalibrationFreeLearner(world, LearnerConfig(**SMALL), np.random.default_rng(0))
    learner.adopt_prior(data.features.astype(np.float32), labels, weights)
    whole = learner.history.pooled_statistics(with_folds=False)
    x = data.features
    np.testing.assert_allclose(whole.scatter[0], (weights[:, None] * x).T @ x, rtol=1e-12)
    np.testing.assert_allclose(whole.signal_sum[0], weights @ x, rtol=1e-12)
    np.testing.assert_allclose(whole.n_signals[0], weights.sum(), rtol=1e-12)
    expected_counts = weights @ labels
    np.testing.assert_allclose(whole.counts[0], np.broadcast_to(expected_counts, (9, 2)))
    np.testing.assert_allclose(whole.sums[0][3], (weights[:, None] * labels).T @ x)


def test_pseudo_observations_count_distinct_epochs_by_recency() -> None:
    """Copies of an epoch share its weight; an older session weighs ``recency`` times the
    next; an epoch of both sessions counts once, at its most recent session's weight."""
    space = FeatureSpace(2, "feedback", 2)
    a, b, c = np.float32([[1, 0]]), np.float32([[0, 1]]), np.float32([[1, 1]])
    recent = PriorSession(np.concatenate([a, a, a, b]), np.eye(2)[[0, 0, 1, 1]], "recent")
    older = PriorSession(np.concatenate([b, c]), np.eye(2)[[1, 0]], "older")
    prior = Prior((recent, older), space, recency=0.5, weight=2.0)
    signals, labels, weights = prior.pseudo_observations()
    assert signals.shape == (6, 2) and labels.shape == (6, 2)
    by_vector = {}
    for signal, weight in zip(signals, weights, strict=True):
        by_vector[signal.tobytes()] = by_vector.get(signal.tobytes(), 0.0) + weight
    assert by_vector[a.tobytes()] == pytest.approx(2.0)  # three copies, one epoch
    assert by_vector[b.tobytes()] == pytest.approx(2.0)  # in both: the recent weight
    assert by_vector[c.tobytes()] == pytest.approx(1.0)  # older only: half
    assert prior.effective_size == pytest.approx(5.0)


def test_adopted_labels_are_the_declared_tasks_segments() -> None:
    """Each declared target's segment under its task; not the first segment nor the last,
    open one."""
    world = GridWorld(3)
    frame = Frame(world, "feedback")
    moves = [(s % 9, s % 5) for s in range(12)]
    indices, labels = adopted_labels(frame, moves, {2: 7, 6: 1, 9: 5})
    assert indices.tolist() == [3, 4, 5, 6, 7, 8, 9]
    expected = [frame.weights_at(*moves[i])[1 if i <= 6 else 5] for i in indices]
    assert np.array_equal(labels, expected)


def test_a_recording_gives_the_learners_adopted_labels_and_never_its_truth(
    day_one: Path, tmp_path: Path
) -> None:
    """The prior of a recording is its learner's signals with the labels the learner
    adopted (as the re-run's learner holds them at its last target), whatever its /truth
    says: a copy whose truth labels are all flipped gives the same prior."""
    session, space, _ = read_prior_session(day_one)
    recording = read_recording(day_one)
    assert recording.messages["/truth"] == []  # the tape records no truth: add one
    flipped = tmp_path / "truth.mcap"
    with SessionRecorder(flipped, recording.session, recording.config) as recorder:
        for topic, messages in recording.messages.items():
            if topic in ("/config", "/log"):
                continue
            for log_time, message in messages:
                if topic in ("/epoch", "/features"):
                    header = {k: v for k, v in message.items() if k not in ("data", "shape",
                                                                            "dtype")}
                    recorder.record_array(topic, header, decode_array(message), log_time)
                else:
                    recorder.record(topic, message, log_time)
                if topic == "/move":
                    truth = {"seq": message["seq"], "t_ns": 0, "step": message["step"],
                             "target": 0, "label": 1}
                    recorder.record("/truth", truth, log_time)
    again, _, _ = read_prior_session(flipped)
    assert np.array_equal(session.signals, again.signals)
    assert np.array_equal(session.labels, again.labels)
    # The labels are those the learner itself adopted: re-run it to its last target.
    moves = [m for _, m in recording.messages["/move"]]
    last = max(m["step"] for m in moves if m["target_reached"])
    first = min(m["step"] for m in moves if m["target_reached"])
    rerun = Rerun(recording.config)
    for signal in recorded_signals(recording)[:last]:
        rerun.observe(signal)
    learner = rerun.session.learner
    adopted = learner.history.task_label_weights(0)[:last]
    assert learner.history.n_adopted == last
    assert np.array_equal(session.labels, adopted[first:][adopted[first:].sum(axis=1) > 0])
    assert space == FeatureSpace(4, "feedback", 2)


def _mirrored(path: Path, out: Path) -> None:
    """The recording with every state, target and move mirrored left to right on its grid:
    the same signals and the same labels under other targets."""
    recording = read_recording(path)
    side = recording.config["grid"]
    world = GridWorld(side)

    def mirror(state: int) -> int:
        row, col = divmod(state, side)
        return row * side + side - 1 - col

    swap = {"left": "right", "right": "left"}
    with SessionRecorder(out, recording.session, recording.config) as recorder:
        for topic, messages in recording.messages.items():
            if topic in ("/config", "/log", "/belief"):
                continue
            for log_time, message in messages:
                if topic in ("/epoch", "/features"):
                    header = {k: v for k, v in message.items()
                              if k not in ("data", "shape", "dtype")}
                    recorder.record_array(topic, header, decode_array(message), log_time)
                    continue
                if topic == "/move":
                    message = {**message, "from_state": mirror(message["from_state"]),
                               "to_state": mirror(message["to_state"]),
                               "action": swap.get(message["action"], message["action"])}
                if topic == "/state":
                    message = {**message, "best_task": mirror(message["best_task"])}
                recorder.record(topic, message, log_time)
    assert world.n_states == side * side


def test_day_two_does_not_inherit_day_one_targets(day_one: Path, tmp_path: Path) -> None:
    """A prior carries no task information: day 1 mirrored (other targets, the same signals
    and labels) gives the same prior, and day 2's proposals are those of day 1's."""
    mirrored = tmp_path / "mirrored.mcap"
    _mirrored(day_one, mirrored)
    targets = [m["from_state"] for _, m in read_recording(day_one).messages["/move"]
               if m["target_reached"]]
    mirror_targets = [m["from_state"] for _, m in read_recording(mirrored).messages["/move"]
                      if m["target_reached"]]
    assert targets != mirror_targets
    first, second = read_prior([day_one]), read_prior([mirrored])
    assert np.array_equal(first.sessions[0].signals, second.sessions[0].signals)
    assert np.array_equal(first.sessions[0].labels, second.sessions[0].labels)
    world, config = GridWorld(3), LearnerConfig(**SMALL)
    learners = [task_learner(world, config, session_streams(9)[2], prior=p)
                for p in (first, second)]
    teachers = [TaskTeacher(world, "feedback", 9) for _ in learners]
    states = [teacher.start() for teacher in teachers]
    for _ in range(30):
        proposals = [learner.propose(state) for learner, state in zip(learners, states,
                                                                     strict=True)]
        assert proposals[0] == proposals[1]
        answers = [t.answer(s, p) for t, s, p in zip(teachers, states, proposals, strict=True)]
        for learner, state, proposal, (signal, _) in zip(learners, states, proposals, answers,
                                                          strict=True):
            learner.observe(state, proposal.action, np.float32(signal))
        states = [next_state for _, next_state in answers]


def test_the_returning_learner_passes_the_learner_conformance_checks(day_one: Path) -> None:
    """Label-free interface (the prior is its construction's only extra input), decisions
    from the signals alone, determinism, well-formed beliefs, malformed signals rejected."""
    prior = read_prior([day_one])
    world, config = GridWorld(3), LearnerConfig(**SMALL)
    check_learner(
        lambda seed: ReturningLearner(world, config, session_streams(seed)[2], prior),
        lambda seed: TaskTeacher(world, "feedback", seed),
        steps=16,
    )


def test_a_mismatched_prior_is_refused(day_one: Path, tmp_path: Path, capsys) -> None:
    """A prior of 4-feature signals for sessions of 5 features: refused, saying what
    differs (the command exits 2 with the message)."""
    prior = read_prior([day_one])
    with pytest.raises(ValueError, match=r"n_features: 4 vs 5"):
        prior.check_space(FeatureSpace(5, "feedback", 2))
    with pytest.raises(ValueError, match=r"frame: 'feedback' vs 'guidance'.*n_classes: 2 vs 4"):
        prior.check_space(FeatureSpace(4, "guidance", 4))
    epochs = FeatureSpace(4, "feedback", 2, 256.0, -0.2, ("Fz", "Cz"), (("window", (0.2, 0.8)),))
    with pytest.raises(ValueError, match=r"sfreq: None vs 256.0; tmin: None vs -0.2"):
        prior.check_space(epochs)
    code = main(["simulate", "--synthetic", "gaussian", "--dims", "5", "--seeds", "1",
                 "--steps", "5", "--jobs", "1", "--prior", str(day_one)])
    assert code == 2
    assert "n_features: 4 vs 5" in capsys.readouterr().err


def test_simulate_with_a_prior(day_one: Path, tmp_path: Path) -> None:
    """``cfbci simulate --prior``: the sessions start from it (the report's config says
    which), and a report without a prior has no such key."""
    out = tmp_path / "with.json"
    args = ["simulate", "--synthetic", "gaussian", "--dims", "4", "--grid", "3", "--seeds",
            "1", "--steps", "40", "--jobs", "1", "--set", "power_prior=false"]
    assert main([*args, "--json", str(out), "--prior", str(day_one)]) == 0
    report = json.loads(out.read_text())
    assert report["config"]["prior"]["sources"] == [str(day_one)]
    assert report["config"]["prior"]["effective_size"] > 50
    assert main([*args, "--json", str(tmp_path / "without.json")]) == 0
    assert "prior" not in json.loads((tmp_path / "without.json").read_text())["config"]


def another_user(seed: int) -> LabelledFeatures:
    """Gaussian signals of another user: the classes apart along other directions."""
    data = gaussian(seed)
    return replace(data, features=data.features[:, ::-1] * np.array([1.0, -1.0, 1.0, -1.0]))


def test_the_users_own_prior_speeds_day_two_and_another_users_costs_nothing(
    day_one: Path, tmp_path: Path
) -> None:
    """Day 2 of a Gaussian user on a 5 x 5 grid: with the user's day-1 prior, never
    abandoned, the first target comes sooner than from scratch; with another user's prior
    (the classes along other directions), never trusted and further from it by the check's
    statistic, the session finds as many correct targets as from scratch; either at most
    one more wrong target than from scratch (the informed learner declares only what the
    blank learner's best task corroborates)."""
    other = tmp_path / "other.mcap"
    record_day(other, seed=3, steps=160, data=another_user(1))
    config = SessionConfig(steps=150, grid=5, learner=LearnerConfig(**SMALL))
    scratch = run_session(11, config, gaussian(4))
    outcomes = {}
    for name, path in (("own", day_one), ("other", other)):
        learners: list[ReturningLearner] = []
        result = run_session(
            11, replace(config, prior=read_prior([path])), gaussian(4),
            on_move=lambda session, _, kept=learners: kept.append(session.learner),
        )
        outcomes[name] = (learners[0].decision, result)
    (own, with_own), (foreign, with_other) = outcomes["own"], outcomes["other"]
    assert own.outcome != "fallen back" and foreign.outcome != "trusted"
    assert min(foreign.statistic) < min(own.statistic)
    assert with_own.first_target_step is not None and scratch.first_target_step is not None
    assert with_own.first_target_step < scratch.first_target_step
    assert with_other.correct_targets >= scratch.correct_targets
    for result in (with_own, with_other):
        assert result.wrong_targets <= scratch.wrong_targets + 1


def test_the_power_premise_refuses_a_complemented_errp_prior() -> None:
    """ErrP labels agree with the power premise (errors carry more power), their complement
    contradicts it by as much: a complemented ErrP prior is abandoned before any signal."""
    data = features_from_epochs(generate_errp_epochs(150, 150, accuracy=0.7, seed=5))
    signals = data.features.astype(np.float32)
    labels = np.eye(2)[data.labels]
    premise = power_premise(signals, labels, np.ones(len(labels)))
    assert premise > 5
    assert power_premise(signals, labels[:, ::-1], np.ones(len(labels))) == -premise
    space = FeatureSpace(signals.shape[1], "feedback", 2)
    prior = Prior((PriorSession(signals, labels, "errp"),), space)
    world, config = GridWorld(3), LearnerConfig(n_folds=5, n_planning_signals=5)
    right = ReturningLearner(world, config, np.random.default_rng(0), prior)
    wrong = ReturningLearner(world, config, np.random.default_rng(0), prior.complemented())
    assert right.decision.outcome == "testing"
    assert (wrong.decision.outcome, wrong.decision.step) == ("fallen back", 0)
    assert wrong.informed is None and not wrong.acting.prior_adopted
    # Abandoned before the first signal, it costs nothing: the session is the one from
    # scratch, step for step.
    session = SessionConfig(steps=60, grid=3, learner=config)
    plain = replace(data, features=signals.astype(np.float64))
    assert run_session(5, replace(session, prior=prior.complemented()), plain) == run_session(
        5, session, plain)


def test_the_generators_drift() -> None:
    """No drift changes nothing; a latency drift delays the error-minus-correct wave by it,
    an amplitude drift scales it."""
    plain = generate_errp_epochs(200, 200, accuracy=0.9, seed=1)
    assert np.array_equal(
        plain.epochs, generate_errp_epochs(200, 200, accuracy=0.9, seed=1,
                                           drift=ResponseDrift()).epochs)
    assert plain.source == generate_errp_epochs(20, 20, accuracy=0.9, seed=1).source
    late = generate_errp_epochs(200, 200, accuracy=0.9, seed=1, drift=ResponseDrift(0.5, 0.04))
    assert np.array_equal(plain.labels, late.labels)
    fcz = list(plain.ch_names).index("FCz")

    def wave(data):  # the error-minus-correct mean at FCz
        return (data.epochs[data.labels == 1, fcz].mean(axis=0)
                - data.epochs[data.labels == 0, fcz].mean(axis=0))

    times = plain.tmin + np.arange(plain.epochs.shape[-1]) / plain.sfreq
    window = (times > 0.15) & (times < 0.35)  # the error negativity at 250 ms
    trough = times[window][np.argmin(wave(plain)[window])]
    shifted = times[(times > 0.19) & (times < 0.39)]
    late_trough = shifted[np.argmin(wave(late)[(times > 0.19) & (times < 0.39)])]
    assert late_trough - trough == pytest.approx(0.04, abs=0.008)
    ratio = np.ptp(wave(late)) / np.ptp(wave(plain))
    assert 0.4 < ratio < 0.65
    assert "drift amplitude x0.5, latency +40 ms" in late.source


def test_the_informed_learner_declares_only_corroborated_targets(
    day_one: Path, tmp_path: Path
) -> None:
    """While the prior is tested, every target the informed learner declares is one the
    blank learner's posterior corroborates (at least half its best task's), with the user's
    own prior and with another user's; the informed learner does declare some."""
    other = tmp_path / "other.mcap"
    record_day(other, seed=3, steps=160, data=another_user(1))
    config = SessionConfig(steps=150, grid=5, learner=LearnerConfig(**SMALL))
    informed_declarations = 0
    for path in (day_one, other):
        seen: list[bool] = []  # corroborated, at each declaration of the informed learner

        def check(session, step, seen=seen) -> None:
            learner = session.learner
            if step.move is None or not step.move["target_reached"]:
                return
            if learner.blank is not None and learner.acting is learner.informed:
                seen.append(learner.corroborated)

        run_session(11, replace(config, prior=read_prior([path])), gaussian(4), on_move=check)
        assert all(seen)
        informed_declarations += len(seen)
    assert informed_declarations > 0


def test_the_power_premise_counts_copies_by_their_weights() -> None:
    """Copies of an epoch sharing its weight (a small data set's recurring epochs) give
    the premise of the distinct epochs: every part of the statistic is weighted alike."""
    data = features_from_epochs(generate_errp_epochs(150, 150, accuracy=0.7, seed=5))
    signals, labels = data.features.astype(np.float32), np.eye(2)[data.labels]
    once = power_premise(signals, labels, np.ones(len(labels)))
    twice = power_premise(np.concatenate([signals, signals]), np.concatenate([labels, labels]),
                          np.full(2 * len(labels), 0.5))
    assert once > 5
    assert twice == pytest.approx(once, rel=1e-9)
