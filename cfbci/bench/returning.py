"""``cfbci bench returning``: a returning user's second session, from scratch and from the
recording of the first (`calibration_free.prior`).

**Days.** Day 1 and day 2 are two disjoint halves of the data, stratified by label:

* a dataset file (``--dataset``): for user ``u``, each class's signals permuted by a
  generator seeded with ``u`` and halved (``--split stratified``, the default); or, with
  ``--split order``, the first and second halves of each class in the file's (recording)
  order, the same for every user;
* synthetic ErrP data (``--synthetic errp``): two draws of the same synthetic subject, day
  ``d``'s epochs (600 per class, `acquisition.synthetic.generate_errp_epochs` at
  ``--synthetic-accuracy``) from ``SeedSequence([u, d])``. Subjects differ in the latency of
  their outcome responses: subject ``u``'s are delayed by a draw of N(0, 40 ms) (clipped to
  +-100 ms; `SUBJECT_LATENCY_SD`) from ``SeedSequence([u, 0])``
  (`acquisition.synthetic.ResponseDrift`). A day-to-day drift ``D`` (``--drift``,
  default 0.2) makes the drift arm's day 2 ``100 D`` ms later and ``1 - D`` times the
  amplitude.

**Sessions.** User ``u`` (``--first-seed`` to ``--first-seed + --seeds - 1``) has a day-1
session of seed ``u`` on day 1, recorded in the service's layout (`DayOneTape`:
``/config``, ``/epoch``, ``/features``, ``/move``, ``/state`` with ``/belief``, ``/event``;
synthetic epochs raw, as the live source sends them, dataset signals as feature vectors; no
``/truth``), then day-2 sessions on day 2 of seed ``u + DAY2_SEED_OFFSET`` (day 1's seed
would give day 2 the same start and first target), one per arm:

* ``scratch``: no prior;
* ``prior``: the day-1 recording of the same user, read by `replay.prior.read_prior`;
* ``complemented``: that prior with its labels reversed (labels adopted wrongly);
* synthetic data only: ``other_subject``, the day-1 recording of the next user (the last
  user's: the first's), and ``drift``: day 2 drifted, with the day-1 prior;
  ``drift_scratch``, from scratch on that drifted day 2, is the drift arm's reference;
  on request (``--arms``), ``population``: the other users' day-1 recordings as one weak
  prior (`population_prior`).

**Figures.** Per arm, the ``summary`` of ``cfbci simulate --json``
(`cfbci.offline.simulation.summarise`), and: ``paired``, the per-seed differences against the
arm's reference (``scratch``; ``drift_scratch`` for ``drift``) of the first target's step (a
session without a target counts ``steps + 1``), the correct and the wrong targets, each
with its mean and 95 % t-interval and its median; ``fallbacks``, the prior check's decisions
(`calibration_free.prior.PriorCheck`): sessions that fell back and at which steps
(step 0: refused by the power premise), sessions that trusted the prior and when, sessions
still testing at the end, and sessions whose day 1 gave no prior (``no_prior``: it declared
fewer than two targets; day 2 runs from scratch). On a small dataset (``s4.mat``: 900
signals a day) one epoch recurs several times in a 500-step session, and its copies (in
today's signals and in the prior) can fall on both sides of the learner's cross-validation:
the figures compare arms, they are not absolute performance.
"""

from __future__ import annotations

import functools
import time
from collections import Counter
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from scipy import stats

from acquisition.labelled import LabelledEpochs, LabelledFeatures
from acquisition.loaders import N_CLASSES, features_from_epochs, load_labelled
from acquisition.sources import DEFAULT_SYNTHETIC_ACCURACY, SYNTHETIC_EPOCHS_PER_CLASS, DataSpec
from acquisition.synthetic import ResponseDrift, generate_errp_epochs
from calibration_free.config import LearnerConfig
from calibration_free.prior import FeatureSpace, Prior, ReturningLearner
from cfbci.offline.parallel import Scheduler, run_parallel
from cfbci.offline.simulation import SessionConfig, SessionResult, run_session, summarise
from cfbci.service.recordings import record_beliefs
from replay.prior import NoLabelledSignals, epochs_space, read_prior
from replay.recording import SessionRecorder
from session.core import Step
from session.tasks import TaskSession

#: Day 2's session seed is the user's plus this.
DAY2_SEED_OFFSET = 1_000_000
#: Standard deviation of the synthetic subjects' response latencies, s, and its clip.
SUBJECT_LATENCY_SD = 0.04
SUBJECT_LATENCY_CLIP = 0.1
DEFAULT_DRIFT = 0.2
#: The arms, in order; the synthetic ones run on synthetic data only.
ARMS = ("scratch", "prior", "complemented")
SYNTHETIC_ARMS = ("other_subject", "drift_scratch", "drift")
#: Each arm's reference for the paired differences.
REFERENCE = {"drift": "drift_scratch"}
#: Per-seed figures compared between arms.
PAIRED = ("first_target_step", "correct_targets", "wrong_targets")


@dataclass(frozen=True)
class ReturningData:
    """Where the two days' signals come from (module docstring).

    Attributes
    ----------
    path : Path or None
        A dataset file; None: synthetic ErrP data.
    accuracy : float
        The synthetic data's nominal balanced accuracy.
    drift : float
        The drift arm's day-to-day drift ``D`` (synthetic).
    split : {"stratified", "order"}
        How a dataset file is halved.
    """

    path: Path | None = None
    accuracy: float = DEFAULT_SYNTHETIC_ACCURACY
    drift: float = DEFAULT_DRIFT
    split: str = "stratified"

    def __post_init__(self) -> None:
        if self.split not in ("stratified", "order"):
            raise ValueError(f"split must be 'stratified' or 'order'; got {self.split!r}")
        if self.path is None and not 0.0 <= self.drift < 1.0:
            raise ValueError(f"--drift must be in [0, 1); got {self.drift}")

    @property
    def arms(self) -> tuple[str, ...]:
        """The arms run by default (``population`` on request only)."""
        return ARMS if self.path is not None else ARMS + SYNTHETIC_ARMS

    def chosen_arms(self, names: list[str] | None) -> tuple[str, ...]:
        """The arms ``names`` (default `arms`) with their references, in order.

        Raises
        ------
        ValueError
            On an arm unknown or not for these data.
        """
        known = self.arms + (() if self.path is not None else ("population",))
        unknown = sorted(set(names or ()) - set(known))
        if unknown:
            raise ValueError(f"--arms {unknown}: not arms of these data; they are {list(known)}")
        chosen = set(names or self.arms)
        chosen |= {REFERENCE.get(arm, "scratch") for arm in chosen}
        return tuple(arm for arm in known if arm in chosen)

    def describe(self) -> str:
        if self.path is not None:
            return f"{self.path} ({self.split} halves)"
        return (f"synthetic ErrP subjects (nominal balanced accuracy {self.accuracy:g}), drift "
                f"{self.day_drift().describe()}")

    def day_drift(self) -> ResponseDrift:
        """The drift arm's drift from day 1 to day 2."""
        return ResponseDrift(1.0 - self.drift, 0.1 * self.drift)

    def subject(self, user: int) -> ResponseDrift:
        """Synthetic subject ``user``'s responses (their latency)."""
        rng = np.random.default_rng(np.random.SeedSequence([user, 0]))
        latency = np.clip(rng.normal(0.0, SUBJECT_LATENCY_SD), -SUBJECT_LATENCY_CLIP,
                          SUBJECT_LATENCY_CLIP)
        return ResponseDrift(1.0, float(latency))

    def day(self, user: int, day: int, drifted: bool = False) -> LabelledEpochs | LabelledFeatures:
        """User ``user``'s signals of day ``day`` (1 or 2); ``drifted``: with the day drift
        (synthetic day 2)."""
        if self.path is None:
            drift = self.subject(user).then(self.day_drift()) if drifted else self.subject(user)
            epochs = generate_errp_epochs(
                SYNTHETIC_EPOCHS_PER_CLASS, SYNTHETIC_EPOCHS_PER_CLASS, accuracy=self.accuracy,
                seed=np.random.SeedSequence([user, day]), drift=drift,
            )
            return replace(epochs, epochs=epochs.epochs.astype(np.float32))
        data = _load(self.path)
        halves = []
        for label in range(data.n_classes):
            members = np.flatnonzero(data.labels == label)
            if self.split == "stratified":
                members = np.random.default_rng(user).permutation(members)
            halves.append(np.array_split(members, 2)[day - 1])
        chosen = np.sort(np.concatenate(halves))
        return replace(
            data, features=data.features[chosen], labels=data.labels[chosen],
            source=f"{data.source} (day {day} of {self.split} halves, user {user})",
        )


@functools.lru_cache(maxsize=2)
def _load(path: Path) -> LabelledFeatures:
    """A dataset file, loaded once per process."""
    return load_labelled(path)


def as_features(data: LabelledEpochs | LabelledFeatures) -> LabelledFeatures:
    """The learner's feature vectors of a day's signals."""
    return features_from_epochs(data) if isinstance(data, LabelledEpochs) else data


def data_space(data: LabelledEpochs | LabelledFeatures, frame: str) -> FeatureSpace:
    """The feature space of signals a session is simulated on (``frame``'s classes)."""
    n_features = as_features(data).features.shape[1]
    if isinstance(data, LabelledEpochs):
        return epochs_space(n_features, frame, N_CLASSES[frame], data.sfreq, data.tmin,
                            data.ch_names)
    return FeatureSpace(n_features, frame, N_CLASSES[frame])


def spec_space(data: DataSpec, frame: str) -> FeatureSpace:
    """The feature space of ``cfbci simulate``'s sessions on ``data``: a dataset file's
    signals (raw epochs of a recording that holds them), synthetic ErrP epochs (of the
    generator's sampling and channels), or Gaussian signals."""
    if data.path is not None:
        return data_space(data.load_signals(frame), frame)
    if data.synthetic == "gaussian":
        return FeatureSpace(data.dims, frame, N_CLASSES[frame])
    return data_space(generate_errp_epochs(1, 1, seed=0), frame)


def simulation_prior(paths: list[Path], data: DataSpec, frame: str) -> Prior:
    """The prior of ``cfbci simulate --prior``: the recordings read, checked against the
    feature space of the sessions' data.

    Raises
    ------
    FileNotFoundError, ValueError
        On a recording that cannot be read as a prior, or a prior of another feature space
        (the message says what differs).
    """
    prior = read_prior(paths)
    prior.check_space(spec_space(data, frame))
    return prior


class DayOneTape:
    """Records a simulated session to an MCAP file as the service records a live one
    (`cfbci.service.running`): config, then per step the epoch and its features, the
    move, the state with the belief, and the target events; a `run_session`
    ``on_move`` hook.

    Parameters
    ----------
    recorder : SessionRecorder
    config : dict
        The recorded config's fields.
    data : LabelledEpochs or LabelledFeatures
        The signals the user answers with (the epoch of a learner's signal is found by its
        feature vector).
    """

    def __init__(
        self, recorder: SessionRecorder, config: dict[str, Any],
        data: LabelledEpochs | LabelledFeatures,
    ) -> None:
        self.recorder, self.config = recorder, config
        features = np.asarray(as_features(data).features, dtype=np.float32)
        self._index = {row.tobytes(): i for i, row in enumerate(features)}
        self._payloads = data.epochs if isinstance(data, LabelledEpochs) else features
        self._sent: Counter[str] = Counter()  # messages per kind: the next one's seq
        self._event("session_started", f"session {recorder.path.stem!r} started")

    def _stamp(self, kind: str) -> dict[str, int]:
        """``seq`` (per kind, from 0, as each sender numbers its messages) and ``t_ns``."""
        self._sent[kind] += 1
        return {"seq": self._sent[kind] - 1, "t_ns": time.monotonic_ns()}

    def _event(self, event: str, text: str) -> None:
        stamp = self._stamp("event")
        message = {**stamp, "event": event, "message": text, "config_t_ns": None}
        self.recorder.record("/event", message, stamp["t_ns"])
        self.recorder.record_log(2, f"{event}: {text}", stamp["t_ns"])

    def __call__(self, session: TaskSession, step: Step) -> None:
        if session.n_signals:
            self._epoch(session)
        if step.move is not None:
            stamp = self._stamp("move")
            self.recorder.record("/move", {**stamp, **step.move}, stamp["t_ns"])
        state, stamp = session.state(), self._stamp("state")
        confidence = np.asarray(state.confidence, dtype=np.float32)
        message = {**stamp, **state.fields, "confidence": [float(x) for x in confidence]}
        self.recorder.record("/state", message, stamp["t_ns"])
        record_beliefs(self.recorder, self.config, session, state, stamp["t_ns"])
        for text in step.events:
            self._event("target_reached", text)
        if step.move is None:
            self._event("session_ended", f"session ended after {session.step} steps")

    def _epoch(self, session: TaskSession) -> None:
        signal = np.asarray(session.learner.history.signals[-1], dtype=np.float32)
        payload = np.asarray(self._payloads[self._index[signal.tobytes()]], dtype=np.float32)
        step = session.n_signals
        epoch = {"step": step, "signal": self.config["signal"]}
        if "ch_names" in self.config:
            epoch["ch_names"] = self.config["ch_names"]
        stamp = self._stamp("epoch")  # its features are recorded under the epoch's seq
        self.recorder.record_array(
            "/epoch", {**stamp, "units": "uV", **epoch}, payload, stamp["t_ns"])
        self.recorder.record_array("/features", {**stamp, "step": step}, signal, stamp["t_ns"])


def recorded_config(
    seed: int, config: SessionConfig, data: LabelledEpochs | LabelledFeatures, describe: str
) -> dict[str, Any]:
    """The config fields the service would record for a session (docs/protocol.md)."""
    fields: dict[str, Any] = {
        "seed": seed, "world": config.world, "grid": config.grid,
        "frame": config.learner.frame, "steps": config.steps,
        "learner": config.learner.to_dict(), "dataset": {"description": describe},
    }
    if isinstance(data, LabelledEpochs):
        return fields | {"signal": "epochs", "sfreq": data.sfreq, "tmin": data.tmin,
                         "ch_names": list(data.ch_names)}
    return fields | {"signal": "features"}


@dataclass(frozen=True)
class DayJob:
    """One session of the bench (a job of `cfbci.offline.parallel.run_parallel`).

    Attributes
    ----------
    data : ReturningData
    user : int
    arm : str
        "day1", or a day-2 arm.
    steps : int
    recordings : tuple of str
        "day1": where the user's day 1 is recorded; an arm with a prior: the recordings it
        is read from; else none.
    prior_weight : float
        The prior's weight (`calibration_free.prior.Prior.weight`).
    """

    data: ReturningData
    user: int
    arm: str
    steps: int
    recordings: tuple[str, ...] = ()
    prior_weight: float = 1.0


def run_day(job: DayJob) -> tuple[SessionResult, dict[str, Any] | None]:
    """Run one session of the bench: its result and the prior check's decision
    (`decision_of`)."""
    config = SessionConfig(steps=job.steps, learner=LearnerConfig())
    if job.arm == "day1":
        signals = job.data.day(job.user, 1)
        fields = recorded_config(job.user, config, signals, job.data.describe())
        with SessionRecorder(job.recordings[0], f"day1-{job.user}", fields) as recorder:
            tape = DayOneTape(recorder, fields, signals)
            result = run_session(job.user, config, as_features(signals), on_move=tape)
        return result, None
    signals = job.data.day(job.user, 2, drifted=job.arm in ("drift", "drift_scratch"))
    empty = None  # a day 1 that declared fewer than two targets gives no prior
    if job.recordings:
        try:
            prior = (population_prior(job.recordings, job.user, job.prior_weight)
                     if job.arm == "population" else read_prior(job.recordings,
                                                                weight=job.prior_weight))
        except NoLabelledSignals:
            empty = {"outcome": "no prior", "step": None, "premise": None}
        else:
            prior.check_space(data_space(signals, config.learner.frame))
            config = replace(
                config, prior=prior.complemented() if job.arm == "complemented" else prior)
    learners: list[Any] = []
    result = run_session(
        job.user + DAY2_SEED_OFFSET, config, as_features(signals),
        on_move=lambda session, _: learners.append(session.learner) if not learners else None,
    )
    return result, empty or decision_of(learners[0])


def population_prior(paths: tuple[str, ...], user: int, weight: float = 1.0) -> Prior:
    """Other users' recordings as one weak prior: no recency among them, and each one's
    labelled signals thinned to a ``1 / len(paths)`` share (drawn with the user's seed), so
    that together they weigh about one session (times ``weight``)."""
    prior = read_prior(paths, recency=1.0, weight=weight)
    rng = np.random.default_rng(user)
    sessions = []
    for session in prior.sessions:
        kept = np.sort(rng.choice(len(session.signals), max(1, len(session.signals) // len(paths)),
                                  replace=False))
        sessions.append(replace(session, signals=session.signals[kept],
                                labels=session.labels[kept]))
    return replace(prior, sessions=tuple(sessions))


def decision_of(learner: Any) -> dict[str, Any] | None:
    """The prior check's decision of a session's learner (None without a prior)."""
    if not isinstance(learner, ReturningLearner):
        return None
    decision = learner.decision
    return {"outcome": decision.outcome, "step": decision.step, "premise": decision.premise}


def paired(results: list[SessionResult], reference: list[SessionResult]) -> dict[str, Any]:
    """Per-seed differences (arm minus reference) of `PAIRED`, each with its mean,
    95 % t-interval and median."""
    out: dict[str, Any] = {}
    for key in PAIRED:
        def value(result: SessionResult, key: str = key) -> float:
            figure = getattr(result, key)
            return result.steps + 1 if figure is None else figure

        differences = np.array(
            [value(a) - value(b) for a, b in zip(results, reference, strict=True)])
        mean = float(differences.mean())
        if len(differences) > 1 and differences.std(ddof=1) > 0:
            half = stats.t.ppf(0.975, len(differences) - 1) * stats.sem(differences)
            interval = [mean - float(half), mean + float(half)]
        else:
            interval = [mean, mean]
        out[key] = {"mean": mean, "interval_95": interval, "median": float(np.median(differences)),
                    "differences": differences.tolist()}
    return out


def fallbacks(decisions: list[dict[str, Any]]) -> dict[str, Any]:
    """The prior check's decisions over an arm's sessions (`decision_of`)."""
    by = {outcome: sorted(d["step"] for d in decisions if d["outcome"] == outcome)
          for outcome in ("fallen back", "trusted")}
    return {
        "sessions": len(decisions),
        "fell_back": len(by["fallen back"]), "fell_back_at": by["fallen back"],
        "trusted": len(by["trusted"]), "trusted_at": by["trusted"],
        "testing": sum(d["outcome"] == "testing" for d in decisions),
        "no_prior": sum(d["outcome"] == "no prior" for d in decisions),
        "refused_by_power_premise": sum(d["step"] == 0 for d in decisions
                                        if d["outcome"] == "fallen back"),
    }


def bench_returning(
    data: ReturningData, users: list[int], steps: int, directory: Path,
    scheduler: Scheduler, console: Console, arms: tuple[str, ...] | None = None,
    prior_weight: float = 1.0,
) -> dict[str, Any]:
    """Run the day-1 sessions (recorded to ``directory``), then the day-2 sessions of
    ``arms`` (default `ReturningData.chosen_arms`'s); the JSON report (module
    docstring)."""
    arms = arms or data.chosen_arms(None)
    recordings = {user: str(directory / f"day1-{user}.mcap") for user in users}
    jobs = [DayJob(data, user, "day1", steps, (recordings[user],)) for user in users]
    day1 = run_parallel(run_day, jobs, scheduler=scheduler, description="day 1",
                        console=console)
    others = dict(zip(users, users[1:] + users[:1], strict=True))
    priors = {
        "prior": lambda user: (recordings[user],),
        "complemented": lambda user: (recordings[user],),
        "drift": lambda user: (recordings[user],),
        "other_subject": lambda user: (recordings[others[user]],),
        "population": lambda user: tuple(recordings[u] for u in users if u != user),
    }
    jobs = [
        DayJob(data, user, arm, steps, priors[arm](user) if arm in priors else (), prior_weight)
        for arm in arms for user in users
    ]
    done = run_parallel(run_day, jobs, scheduler=scheduler, description="day 2",
                        console=console)
    per_arm = {arm: done[i * len(users):(i + 1) * len(users)] for i, arm in enumerate(arms)}
    summaries = {}
    for arm, outcomes in per_arm.items():
        results = [result for result, _ in outcomes]
        decisions = [decision for _, decision in outcomes if decision is not None]
        summaries[arm] = summarise(results) | {"fallbacks": fallbacks(decisions)}
        if arm not in ("scratch", "drift_scratch"):
            reference = [result for result, _ in per_arm[REFERENCE.get(arm, "scratch")]]
            summaries[arm]["paired"] = paired(results, reference)
    return {
        "config": {
            "data": data.describe(), "dataset": None if data.path is None else str(data.path),
            "synthetic_accuracy": None if data.path is not None else data.accuracy,
            "drift": None if data.path is not None else asdict(data.day_drift()),
            "split": data.split if data.path is not None else None,
            "users": users, "steps": steps, "day2_seed_offset": DAY2_SEED_OFFSET,
            "prior_weight": prior_weight,
            "recordings": str(directory),
        },
        "day1": summarise([result for result, _ in day1]),
        "arms": summaries,
        "sessions": {
            arm: [asdict(result) | {"decision": decision} for result, decision in outcomes]
            for arm, outcomes in per_arm.items()
        },
    }


