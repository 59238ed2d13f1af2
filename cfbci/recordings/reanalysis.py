"""``cfbci replay FILE.mcap --option key=value``: open-loop re-analysis of a recording.

The recorded history (the device's states, actions and the user's epochs, in order) is
re-scored by learners with other settings, to compare settings on identical data.

Open loop
    A re-scoring learner never chooses an action: it observes the recorded
    ``(from_state, action, signal)`` of every step, in order (raw epochs go through the ErrP
    feature extractor as in the service, `replay.rerun.recorded_signals`). Where the
    recorded device declared a target (a ``move`` with ``target_reached``), the user then
    picked a new target, so every re-scoring learner switches task *at the same steps, to
    the same declared cells* (`calibration_free.learner.TaskLearner.follow_declaration`):
    the history's segments are the recording's, whatever the re-scoring learner believed.
    ``observe`` draws nothing from the learner's random stream, so with the recording's own
    settings the re-scored beliefs equal the recorded ``/state`` messages exactly; that is
    checked and reported.

Steps
    Step ``k`` (1-based) is the recording's ``k``-th move; the beliefs *of step k* are those
    the move of step ``k`` was chosen from, after ``k - 1`` epochs (the ``k``-th ``/state``),
    as in ``cfbci simulate --trace`` and `replay.metrics`. The user's target at step
    ``k`` is the ``/truth`` target of step ``k``, or, in a session with a person, the
    operator's last mark at or before it (`replay.metrics.session_truth`). A learner *is
    confident at step k* when its beliefs of step ``k`` are (its best task's confidence
    exceeds ``beta``): it would then walk to its best task instead of exploring. The final
    beliefs, after the last epoch, are compared with the recording but belong to no step.

Segments
    Segment ``j`` runs from the step after the ``(j-1)``-th recorded declaration (step 1 for
    the first) to the ``j``-th declaration included; the last runs to the last step. Per
    setting and segment the report gives the first step at which the learner is confident,
    on which cell, and whether that cell is the user's target at that step.

Settings that only choose actions (`ACTING`: the planner's) change nothing open-loop;
the report says so when they are all an alternative changes.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration_free.config import LearnerConfig
from calibration_free.prior import Prior
from replay.metrics import session_truth
from replay.recorded_prior import recorded_prior
from replay.recording import Recording, read_recording
from replay.rerun import recorded_signals
from session.config import config_world, learner_settings
from session.plane import is_plane
from session.sessions import open_loop

#: Name of the recording's own settings in the report.
OWN = "own settings"
#: Name of the recorded ``/state`` beliefs in the per-step report.
RECORDED = "recorded"
#: Learner settings that only choose actions: without effect on open-loop beliefs.
ACTING = frozenset(
    ("planner", "planning_weights", "novelty_bonus", "n_planning_signals", "discount",
     "warmup_steps")
)


@dataclass(frozen=True)
class Trajectory:
    """Beliefs after 0, 1, ..., n epochs; row ``i`` is the beliefs of step ``i + 1``.

    Attributes
    ----------
    confidence : ndarray, shape (n_rows, n_tasks), float32
        Confidence of every task, as the ``state`` message carries it.
    best_task : ndarray, shape (n_rows,), int
    confident : ndarray, shape (n_rows,), bool
    """

    confidence: np.ndarray
    best_task: np.ndarray
    confident: np.ndarray

    def __len__(self) -> int:
        return len(self.best_task)


@dataclass(frozen=True)
class RecordedHistory:
    """What a re-scoring learner observes, and what the recording says about it.

    Attributes
    ----------
    config : dict
        The recorded session configuration.
    states, actions : ndarray, shape (n_steps,), int
        The state and action (index into the world's actions) of every recorded move
        answered by an epoch.
    declared : ndarray, shape (n_steps,), bool
        The move declared a target reached (the world's declaration action in
        ``states[k]`` while confident).
    signals : list of ndarray
        The learner's input of every step, float32.
    targets : list of int or None
        The user's target of every step (``/truth``, else the operator's marks), None
        where the recording has none.
    recorded : Trajectory
        The recorded ``/state`` messages (at most ``n_steps + 1``).
    prior : Prior or None
        The prior the session started from (its recording's ``/prior``), or None.
    """

    config: dict[str, Any]
    states: np.ndarray
    actions: np.ndarray
    declared: np.ndarray
    signals: list[np.ndarray]
    targets: list[int | None]
    recorded: Trajectory
    prior: Prior | None = None

    @property
    def n_steps(self) -> int:
        return len(self.states)


@dataclass(frozen=True)
class Segment:
    """Steps ``first_step..last_step`` between two recorded declarations.

    ``declared``: the cell the recording declared at ``last_step`` (None for a last segment
    that ends without one); ``target``: the user's target at ``first_step`` (None unknown).
    """

    index: int
    first_step: int
    last_step: int
    declared: int | None
    target: int | None


@dataclass(frozen=True)
class Confident:
    """The first step at which a learner is confident, in a segment or in the session.

    ``target``: the user's target at ``step`` (None unknown); ``correct``: ``task ==
    target`` (None unknown).
    """

    step: int
    task: int
    target: int | None
    correct: bool | None


@dataclass(frozen=True)
class Outcome:
    """One setting's re-scoring of the history.

    Attributes
    ----------
    name : str
        `OWN` for the recording's own settings, else the ``key=value`` given.
    settings : dict
        Every learner setting (``LearnerConfig.to_dict()``).
    differs : dict of str to (recorded value, this value)
        The settings that differ from the recording's.
    trajectory : Trajectory
        Re-scored beliefs after 0..n_steps epochs.
    identical_to_recording : bool
        The re-scored beliefs (confidences, best tasks, confident flags) equal the recorded
        ``/state`` messages, all that the recording holds.
    first_difference_step : int or None
        First step whose beliefs differ from the recorded ones (``n_steps + 1`` for the
        final beliefs), None if none do.
    first_confident : Confident or None
        First confident step of the session.
    segments : list of Confident or None
        First confident step of every segment (None: never confident in it).
    """

    name: str
    settings: dict[str, Any]
    differs: dict[str, tuple[Any, Any]]
    trajectory: Trajectory
    identical_to_recording: bool
    first_difference_step: int | None
    first_confident: Confident | None
    segments: list[Confident | None]

    def summary(self, segments: Sequence[Segment]) -> dict[str, Any]:
        """Segments with a confident step, how many on the target or not, and the median
        number of steps from a segment's start to its first confident step."""
        found = [(c, s) for c, s in zip(self.segments, segments, strict=True) if c is not None]
        delays = [c.step - s.first_step + 1 for c, s in found]
        return {
            "segments_confident": len(found),
            "correct": sum(c.correct is True for c, _ in found),
            "wrong": sum(c.correct is False for c, _ in found),
            "median_steps_to_confidence": float(np.median(delays)) if delays else None,
        }


@dataclass(frozen=True)
class Reanalysis:
    """The re-analysis of one recording: its segments, the recorded beliefs (``/state``)
    and one outcome per setting, the recording's own first."""

    file: str
    session: str
    n_steps: int
    segments: list[Segment]
    recorded: Trajectory
    outcomes: list[Outcome]

    def to_json(self) -> dict[str, Any]:
        """A JSON-able report (``--json``), per-step best tasks and confidences included."""
        outcomes = []
        for outcome in self.outcomes:
            outcomes.append({
                "name": outcome.name,
                "learner": outcome.settings,
                "differs": {
                    key: {"recorded": old, "this": new}
                    for key, (old, new) in outcome.differs.items()
                },
                "identical_to_recording": outcome.identical_to_recording,
                "first_difference_step": outcome.first_difference_step,
                "first_confident": _confident_json(outcome.first_confident),
                "segments": [_confident_json(c) for c in outcome.segments],
                "summary": outcome.summary(self.segments),
            })
        return {
            "file": self.file,
            "session": self.session,
            "steps": self.n_steps,
            "segments": [vars(segment) for segment in self.segments],
            "settings": outcomes,
            "per_step": [
                {
                    "step": step,
                    RECORDED: _beliefs_json(self.recorded, step),
                    **{o.name: _beliefs_json(o.trajectory, step) for o in self.outcomes},
                }
                for step in range(1, self.n_steps + 1)
            ],
        }


def _confident_json(confident: Confident | None) -> dict[str, Any] | None:
    return None if confident is None else vars(confident)


def _beliefs_json(trajectory: Trajectory, step: int) -> dict[str, Any] | None:
    if step > len(trajectory):
        return None
    best = int(trajectory.best_task[step - 1])
    return {
        "best_task": best,
        "confidence": float(trajectory.confidence[step - 1, best]),
        "confident": bool(trajectory.confident[step - 1]),
    }


def recorded_history(recording: Recording, where: str = "") -> RecordedHistory:
    """The recorded (state, action, signal) sequence, truth targets and ``/state`` beliefs.

    A step needs both its move and its epoch: a truncated recording is read up to the last
    move answered by an epoch.

    Raises
    ------
    ValueError
        If the recording has no configuration, no answered move, or epochs whose steps are
        not 1, 2, ... in order.
    """
    where = where or recording.session or "recording"
    if not recording.config:
        raise ValueError(f"{where}: the recording holds no session configuration")
    moves = [m for _, m in recording.messages.get("/move", [])]
    epochs = recording.accepted_epochs()
    n_steps = min(len(moves), len(epochs))
    if n_steps == 0:
        raise ValueError(f"{where}: the recording holds no move answered by an epoch")
    for k, (move, epoch) in enumerate(zip(moves[:n_steps], epochs[:n_steps], strict=True), 1):
        if move["step"] != k or epoch.get("step") != k:
            raise ValueError(
                f"{where}: move #{k} of step {move['step']} and epoch #{k} of step "
                f"{epoch.get('step')}: the recording's steps are not 1, 2, ... in order"
            )
    truth, _ = session_truth(recording, list(range(1, n_steps + 1)))
    states = [m for _, m in recording.messages.get("/state", [])][: n_steps + 1]
    world = config_world(recording.config)
    n_tasks = world.n_tasks
    recorded = Trajectory(
        confidence=np.array([s["confidence"] for s in states], dtype=np.float32).reshape(
            len(states), n_tasks
        ),
        best_task=np.array([s["best_task"] for s in states], dtype=np.int64),
        confident=np.array([s["confident"] for s in states], dtype=bool),
    )
    return RecordedHistory(
        config=recording.config,
        states=np.array([m["from_state"] for m in moves[:n_steps]], dtype=np.int64),
        actions=np.array(
            [world.action_names.index(m["action"]) for m in moves[:n_steps]], dtype=np.int64
        ),
        declared=np.array([m["target_reached"] for m in moves[:n_steps]], dtype=bool),
        signals=recorded_signals(recording)[:n_steps],
        targets=[truth[k]["target"] if k in truth else None for k in range(1, n_steps + 1)],
        recorded=recorded,
        prior=recorded_prior(recording),
    )


def rescore(history: RecordedHistory, settings: LearnerConfig) -> Trajectory:
    """Open-loop beliefs of a learner with ``settings`` over the recorded history.

    The learner observes every recorded step in order and follows the recorded
    declarations (see the module docstring); it never proposes an action.
    """
    loop = open_loop(history.config, settings, history.prior)
    confidence, best, confident = [], [], []

    def keep() -> None:
        beliefs = loop.beliefs()
        confidence.append(beliefs.confidence.astype(np.float32))
        best.append(beliefs.best_task)
        confident.append(beliefs.confident)

    keep()
    for k in range(history.n_steps):
        state, action = int(history.states[k]), int(history.actions[k])
        loop.observe(state, action, history.signals[k], bool(history.declared[k]))
        keep()
    return Trajectory(np.array(confidence), np.array(best, dtype=np.int64), np.array(confident))


def segments_of(history: RecordedHistory) -> list[Segment]:
    """The recording's segments between declared targets (see the module docstring)."""
    segments: list[Segment] = []
    first = 1
    for step in range(1, history.n_steps + 1):
        last = step == history.n_steps
        if history.declared[step - 1] or last:
            declared = int(history.states[step - 1]) if history.declared[step - 1] else None
            segments.append(
                Segment(len(segments) + 1, first, step, declared, history.targets[first - 1])
            )
            first = step + 1
    return segments


def first_confident(
    trajectory: Trajectory, history: RecordedHistory, first: int, last: int
) -> Confident | None:
    """The first step in ``first..last`` at which ``trajectory`` is confident."""
    for step in range(first, last + 1):
        if trajectory.confident[step - 1]:
            task = int(trajectory.best_task[step - 1])
            target = history.targets[step - 1]
            return Confident(step, task, target, None if target is None else task == target)
    return None


def alternative_settings(config: Mapping[str, Any], options: Mapping[str, Any]) -> LearnerConfig:
    """The recording's learner settings with ``options`` (``LearnerConfig`` field: value)
    changed, checked as the service checks a config's ``learner``.

    Raises
    ------
    ValueError
        On no option, an unknown setting, a value of the wrong type or out of range, or a
        ``frame`` other than the recording's.
    """
    if not options:
        raise ValueError("an alternative setting needs at least one key=value")
    try:
        return learner_settings({**config["learner"], **options}, config["frame"])
    except (ValueError, TypeError) as exc:
        raise ValueError(f"bad alternative setting {describe(options)}: {exc}") from None


def describe(options: Mapping[str, Any]) -> str:
    """``key=value, ...`` with JSON values (strings bare)."""
    return ", ".join(
        f"{key}={value if isinstance(value, str) else json.dumps(value)}"
        for key, value in options.items()
    )


def _first_difference(a: Trajectory, b: Trajectory) -> int | None:
    """The first step (1-based row) where two trajectories' beliefs differ, else None."""
    for row in range(min(len(a), len(b))):
        if (
            a.best_task[row] != b.best_task[row]
            or a.confident[row] != b.confident[row]
            or not np.array_equal(a.confidence[row], b.confidence[row])
        ):
            return row + 1
    return None


def _outcome(
    name: str,
    settings: LearnerConfig,
    recorded_settings: LearnerConfig,
    history: RecordedHistory,
    segments: Sequence[Segment],
) -> Outcome:
    trajectory = rescore(history, settings)
    mine, theirs = settings.to_dict(), recorded_settings.to_dict()
    difference = _first_difference(history.recorded, trajectory)
    return Outcome(
        name=name,
        settings=mine,
        differs={key: (theirs[key], mine[key]) for key in mine if mine[key] != theirs[key]},
        trajectory=trajectory,
        identical_to_recording=difference is None and len(history.recorded) > 0,
        first_difference_step=difference,
        first_confident=first_confident(trajectory, history, 1, history.n_steps),
        segments=[
            first_confident(trajectory, history, s.first_step, s.last_step) for s in segments
        ],
    )


def reanalyse(
    recording: Recording | str | os.PathLike[str],
    alternatives: Sequence[Mapping[str, Any]],
) -> Reanalysis:
    """Re-score a recording with its own settings and with every alternative.

    Parameters
    ----------
    recording : Recording or path
    alternatives : sequence of mappings
        Each one alternative setting: ``LearnerConfig`` fields to change (``{"decoder":
        "student_t"}``). All are checked before anything is computed.

    Returns
    -------
    Reanalysis
        ``outcomes[0]`` is the recording's own settings (`RECORDED`), then one per
        alternative, in order.

    Raises
    ------
    ValueError
        On a bad alternative or an unusable recording (the message names it).
    """
    file = ""
    if not isinstance(recording, Recording):
        file = str(recording)
        recording = read_recording(recording)
    where = file or recording.session
    if not recording.config:
        raise ValueError(f"{where}: the recording holds no session configuration")
    config = recording.config
    if is_plane(config):
        raise ValueError(
            f"{where}: a {config['world']} world recording: re-analysis (--option, --compare) "
            "re-scores the discrete worlds' learner; check it with cfbci replay FILE"
        )
    recorded_settings = learner_settings(config["learner"], config["frame"])
    settings = [(describe(o), alternative_settings(config, o)) for o in alternatives]
    history = recorded_history(recording, where)
    segments = segments_of(history)
    outcomes = [
        _outcome(name, s, recorded_settings, history, segments)
        for name, s in [(OWN, recorded_settings), *settings]
    ]
    return Reanalysis(
        file, recording.session, history.n_steps, segments, history.recorded, outcomes
    )
