"""Figures of merit of a recorded session, computed from its `Recording`.

Pure computation (no plotting, no files): `session_metrics` gives one session's
`SessionMetrics`, `aggregate` the median, minimum and maximum of every scalar
metric over the sessions whose world it applies to (`WORLD_METRICS`), and
`session_settings` what a session ran with (seed, dataset, learner settings against
the defaults).

Steps and alignment
-------------------
Step ``k`` (1-based) is the ``k``-th ``/move``. It is answered by the epoch of step ``k``
(the user's reaction to it), whose ``/truth`` (step ``k``) holds the user's target *while*
move ``k`` was made and the true class of that epoch. The ``k``-th ``/state`` accompanies
move ``k``: it is the belief the learner chose move ``k`` on, after ``k - 1`` signals (the
recording holds one more, final, state after the last signal).

* **Declared target** at step ``k``: move ``k`` has ``target_reached`` True, in the state
  ``from_state``. It is *correct* when ``from_state`` is the state of the truth target (a
  task) of step ``k`` (in a grid, the same cell), *wrong* otherwise, and *unverified* when
  the truth of step ``k`` is missing (a truncated recording, or a step before the
  operator's first mark).
* **Truth**: the recorded ``/truth`` (the simulated user's); a recording without it (a
  session with a person) takes the operator's marks instead (``target_marked`` events,
  docs/protocol.md, "Operator controls"): from a mark at step ``s`` on, the user's target
  is the marked one until the next mark; the steps before the first mark have no truth,
  and the epochs' true classes are unknown (no decoder accuracy against the truth).
* **Confidence of the true task** at step ``k``: ``confidence[target_k]`` of the ``k``-th
  state, with ``target_k`` the truth target of step ``k``; the **best other task** is the
  task of highest confidence among the others.
* **Steps per correct target**: ``steps / correct_targets`` (the user's cost of one correct
  selection, first search included). **Mean steps between targets**: mean difference of
  the steps of successive declared targets, correct or wrong (the first search excluded;
  it is ``first_target_step``), i.e. the speed once the decoder is calibrated by use.
* **Decoder balanced accuracy against the truth** after ``t`` signals: the learner is re-run
  over the recording (`replay.rerun.recompute`, identical to the service); after it
  has observed the epochs of steps ``1..t``, take its best task ``b_t`` (the one the
  ``/state`` after ``t`` signals names) and the out-of-fold class probabilities of ``b_t``'s
  decoder for those ``t`` signals (``TaskModels.cv_proba[b_t]``: each signal predicted by
  the decoder trained, with ``b_t``'s hypothesised labels, on the folds it is not in);
  the predicted class is the argmax (ties to the lower class); the accuracy is the mean,
  over the true classes present among the ``t`` signals, of the fraction of that class's
  signals predicted as it (the recorded true labels, ``/truth`` ``label``). None while
  fewer than two true classes are present. This is exactly the recording's own
  ``balanced_accuracy`` (the **self-estimate**) with the true labels in place of the
  best task's hypothesised ones: the two coincide when those labels are the truth.
* **Decision rule** at step ``k``: the confidence rule and its threshold in force in the
  ``k``-th state, and the confidence a target needed there (the threshold, or more before
  the first target while the history is short:
  `calibration_free.learner.first_target_requirement`), from the re-run (the state
  of step 1, before any signal, has no requirement recorded).
* **Update latency**: the moves' ``update_ms`` (the learner's observe + propose time, ms;
  the first move has none), summarised by median, 90th and 99th percentiles (linear
  interpolation, numpy's default) and maximum.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from calibration_free.config import DEFAULT_BETA
from calibration_free.frames import FRAMES, Frame
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.world import GridWorld, World
from replay.calibration import RuleCounts, calibration_counts, counts_by_rule
from replay.recording import Recording
from replay.rerun import first_divergence, recompute
from session.config import (
    config_world,
    learner_settings,
    recorded_config,
    resolved_config,
    world_text,
)
from session.plane import PLANE_FRAMES

#: The scalar metrics `aggregate` summarises, with their meaning (and unit).
SCALAR_METRICS: dict[str, str] = {
    "steps": "moves recorded",
    "first_target_step": "step of the first declared target",
    "correct_targets": "declared targets that were the user's target",
    "wrong_targets": "declared targets that were not",
    "steps_per_correct_target": "steps / correct targets",
    "mean_steps_between_targets": "mean steps between successive declared targets",
    "final_accuracy_truth": "decoder balanced accuracy vs true labels, last step",
    "final_accuracy_self": "decoder balanced accuracy, self-estimate, last step",
    "final_distance": "continuous world: the best particle's distance to the goal, last step",
    "final_taught_likelihood": "puddle world: the taught task's normalised likelihood, last "
    "update",
    "goals_reached": "puddle world: restarts (the agent entered the taught goal cell)",
    "latency_median_ms": "median learner update, ms",
    "latency_p90_ms": "90th percentile learner update, ms",
    "latency_p99_ms": "99th percentile learner update, ms",
    "latency_max_ms": "maximum learner update, ms",
}

#: The scalar metrics that apply to one kind of world only, by kind: "discrete" (the grid,
#: line and pick-and-place worlds, which declare targets and score a best task's decoder)
#: and each plane world; the others apply to every world.
WORLD_METRICS: dict[str, tuple[str, ...]] = {
    "discrete": ("first_target_step", "correct_targets", "wrong_targets",
                 "steps_per_correct_target", "mean_steps_between_targets",
                 "final_accuracy_truth", "final_accuracy_self"),
    "continuous": ("final_distance",),
    "puddle": ("final_taught_likelihood", "goals_reached"),
}


def metric_applies(name: str, world: str) -> bool:
    """Whether the scalar metric ``name`` applies to a session of ``world`` (a
    `SessionMetrics.world`)."""
    kind = world if world in PLANE_FRAMES else "discrete"
    return all(name not in names or owner == kind for owner, names in WORLD_METRICS.items())


@dataclass(frozen=True)
class SessionSettings:
    """What a session ran with, from its recorded configuration.

    Attributes
    ----------
    seed : int or None
        The session seed (None: not recorded).
    dataset : dict
        The config's ``dataset`` object as recorded (``description``, and ``path``,
        ``synthetic_accuracy`` or ``class_order`` where they apply).
    learner : dict
        Every learner setting the session ran with (defaults included; a recording made
        before a setting existed: the value that reproduces its learner).
    defaults : dict
        The same settings' defaults for the session's world and frame, in this version
        ({} when the recorded settings are not valid here).
    non_default : list of str
        The settings whose value is not the default, sorted.
    """

    seed: int | None
    dataset: dict[str, Any]
    learner: dict[str, Any]
    defaults: dict[str, Any]
    non_default: list[str] = field(default_factory=list)


def session_settings(config: dict[str, Any]) -> SessionSettings:
    """The `SessionSettings` of a recorded configuration."""
    try:
        learner = resolved_config(recorded_config(config))["learner"]
        defaults = resolved_config({**config, "learner": {}})["learner"]
    except (KeyError, TypeError, ValueError):  # settings of another version: as recorded
        learner, defaults = dict(config.get("learner", {})), {}
    changed = sorted(k for k, v in learner.items() if k in defaults and defaults[k] != v)
    seed = config.get("seed")
    return SessionSettings(None if seed is None else int(seed), dict(config.get("dataset", {})),
                           learner, defaults, changed)


@dataclass(frozen=True)
class DeclaredTarget:
    """A target the learner declared reached.

    Attributes
    ----------
    step : int
        Step of the declaring move (1-based).
    cell : int
        The declared state (the move's ``from_state``; a grid's cell).
    true_target : int or None
        The user's target task at that step (None: no truth recorded for it).
    correct : bool or None
        Whether ``cell`` is the state of ``true_target`` (None when unverified).
    """

    step: int
    cell: int
    true_target: int | None
    correct: bool | None


@dataclass(frozen=True)
class Latency:
    """Distribution of the learner's update time, ms (``n`` values)."""

    n: int
    median_ms: float
    p90_ms: float
    p99_ms: float
    max_ms: float
    mean_ms: float


@dataclass
class SessionMetrics:
    """Everything `session_metrics` measures in one recording (see the module doc).

    Per-step series are lists (None where undefined), JSON-ready.

    Attributes
    ----------
    file, session : str
        Path of the recording, and its session name.
    frame : str
        "feedback" or "guidance"; ``class_names`` its classes (truth labels 0..K-1).
    world : str
        The world's kind ("grid", "line", "pick-and-place"); ``world_text`` a description.
    grid : int or None
        Side of a grid world (``grid ** 2`` cells and tasks); None in a world without a
        grid layout (its beliefs are shown as ranked lists of tasks).
    n_tasks : int
        Task hypotheses of the world.
    signal : str
        "epochs" (raw epochs recorded) or "features".
    beta : float or None
        The learner's configured confidence threshold (``beta`` in force for the frame);
        None in a world without one (the plane worlds).
    configured_steps : int
        Steps the session was configured for.
    steps : int
        Moves recorded.
    n_signals : int
        Epochs recorded (signals the learner observed).
    first_target_step : int or None
    targets : list of DeclaredTarget
    correct_targets, wrong_targets, unverified_targets : int
    steps_per_correct_target : float or None
        ``steps / correct_targets``.
    mean_steps_between_targets : float or None
        Mean gap, in steps, between successive declared targets (needs two).
    update_ms : list of float
        The learner's update time of every move that has one, ms, in step order.
    latency : Latency or None
    step : list of int
        1..steps: the x axis of the per-step series below.
    agent : list of int
        The agent's state at each step (the move's ``from_state``).
    true_target : list of int or None
        The user's target task at each step (truth).
    confidence_true, confidence_best_other : list of float or None
        Confidence of the true task, and of the most confident other task, when the
        learner chose each step's move (the puddle world's: after each epoch, over
        ``n_seen``).
    best_other_task : list of int or None
        The task of ``confidence_best_other``.
    n_seen : list of int
        1..n_signals: the x axis of the accuracy series (signals observed).
    accuracy_truth : list of float or None
        Decoder balanced accuracy against the true labels after ``n_seen`` signals.
    accuracy_self : list of float or None
        The recording's self-estimated balanced accuracy after ``n_seen`` signals.
    final_accuracy_truth, final_accuracy_self : float or None
        The last values of the two series.
    chance : float
        Chance balanced accuracy, ``1 / n_classes``.
    replay_identical : bool or None
        The re-run reproduced every recorded move, state and target event (the prefix
        the file holds, if truncated); None if the re-run failed.
    replay_note : str or None
        The first divergence, or why the re-run failed.
    truncated : bool
    warning : str or None
        Where a truncated recording ends (byte offset, messages, last step), and where a
        damaged one is damaged.
    damage : dict or None
        A damaged recording's damaged regions and what of it the report uses
        (`replay.extent.usable_part`; set by `cfbci.recordings.report`); None if
        undamaged.
    distance : list of float or None
        Continuous world: the best particle's distance to the goal after each epoch
        (None elsewhere; see `replay.plane_report`).
    final_distance : float or None
        Its last value.
    calibration_counts : list of [int, int] or None
        Per confidence bin (`replay.calibration`), the states with a known target whose
        best task's confidence falls in it, and those whose best task was the target.
    calibration_counts_by_rule : list of RuleCounts or None
        The same split by the decision rule in force at each state (the pairwise W against
        ``beta``, the normalised likelihood against ``calibrated_beta`` in calibrated
        segments), known from the re-run: None unless it reproduced the recording.
    decision_rule, decision_threshold : list of str, list of float, or None
        The confidence rule and its threshold in force at each step (the re-run's; None
        unless it reproduced the recording).
    target_requirement : list of float or None
        The confidence a target needed at each step (None at step 1; as
        ``decision_rule``).
    update_steps : list of int or None
        Puddle world: the epochs after which the learner updated (every ``update_every``;
        None elsewhere; see `replay.puddle_report`).
    taught_likelihood : list of float or None
        Puddle world: the taught task's normalised likelihood after those epochs (float32,
        as the states carry it).
    final_taught_likelihood : float or None
        Its last value.
    restarts : list of int or None
        Puddle world: the steps whose epoch said ``reset`` (the agent entered the goal cell
        and restarted).
    goals_reached : int or None
        Their number.
    settings : SessionSettings or None
        Seed, dataset and learner settings of the session.
    truth : str or None
        The truth the targets were judged by (`session_truth`; None: not said).
    """

    file: str
    session: str
    frame: str
    class_names: list[str]
    world: str
    world_text: str
    grid: int | None
    n_tasks: int
    signal: str
    beta: float | None
    configured_steps: int
    steps: int
    n_signals: int
    first_target_step: int | None
    targets: list[DeclaredTarget]
    correct_targets: int
    wrong_targets: int
    unverified_targets: int
    steps_per_correct_target: float | None
    mean_steps_between_targets: float | None
    update_ms: list[float]
    latency: Latency | None
    step: list[int]
    agent: list[int]
    true_target: list[int | None]
    confidence_true: list[float | None]
    confidence_best_other: list[float | None]
    best_other_task: list[int | None]
    n_seen: list[int]
    accuracy_truth: list[float | None]
    accuracy_self: list[float | None]
    final_accuracy_truth: float | None
    final_accuracy_self: float | None
    chance: float
    replay_identical: bool | None
    replay_note: str | None
    truncated: bool
    warning: str | None
    distance: list[float | None] | None = None
    final_distance: float | None = None
    calibration_counts: list[list[int]] | None = None
    calibration_counts_by_rule: list[RuleCounts] | None = None
    update_steps: list[int] | None = None
    taught_likelihood: list[float | None] | None = None
    final_taught_likelihood: float | None = None
    restarts: list[int] | None = None
    goals_reached: int | None = None
    decision_rule: list[str] | None = None
    decision_threshold: list[float] | None = None
    target_requirement: list[float | None] | None = None
    settings: SessionSettings | None = None
    damage: dict[str, Any] | None = None
    truth: str | None = None

    def scalars(self) -> dict[str, float | int | None]:
        """The `SCALAR_METRICS` that apply to this session's world
        (`metric_applies`)."""
        latency = self.latency
        values: dict[str, float | int | None] = {
            name: getattr(self, name) for name in SCALAR_METRICS if hasattr(self, name)
        }
        for name in ("median_ms", "p90_ms", "p99_ms", "max_ms"):
            values[f"latency_{name}"] = getattr(latency, name) if latency else None
        return {k: v for k, v in values.items() if metric_applies(k, self.world)}

    def decision_rules(self) -> list[tuple[str, float, int]]:
        """Each ``(rule, threshold)`` in force at some step, in the order they first are,
        with its number of steps ([] unless the re-run gave them)."""
        pairs = list(zip(self.decision_rule or [], self.decision_threshold or [], strict=True))
        return [(rule, threshold, pairs.count((rule, threshold)))
                for rule, threshold in dict.fromkeys(pairs)]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (no NaN: undefined values are None)."""
        return asdict(self)


def latency_summary(update_ms: list[float]) -> Latency | None:
    """Median, 90th and 99th percentiles (linear interpolation), max and mean, ms."""
    if not update_ms:
        return None
    values = np.asarray(update_ms, dtype=float)
    p50, p90, p99 = np.percentile(values, [50, 90, 99])
    return Latency(
        len(values), float(p50), float(p90), float(p99), float(values.max()), float(values.mean())
    )


def declared_targets(
    moves: list[dict[str, Any]], truth: dict[int, dict[str, Any]], world: World
) -> list[DeclaredTarget]:
    """The declared targets of the moves, judged against the truth of their step."""
    targets = []
    for move in moves:
        if not move.get("target_reached"):
            continue
        step, cell = int(move["step"]), int(move["from_state"])
        true = truth.get(step, {}).get("target")
        correct = None if true is None else cell == int(world.task_states[true])
        targets.append(DeclaredTarget(step, cell, true, correct))
    return targets


def truth_by_step(recording: Recording) -> dict[int, dict[str, Any]]:
    """The ``/truth`` messages by step (the latest one if a step repeats)."""
    return {int(m["step"]): m for _, m in recording.messages.get("/truth", [])}


#: What `session_truth` says it used when the recording holds ``/truth``.
SIMULATED_TRUTH = "the simulated user's truth (/truth)"


def operator_marks(recording: Recording) -> list[tuple[int, Any]]:
    """The operator's marks, ``(step, target)`` of every ``target_marked`` event, in the
    order they were recorded."""
    return [(int(m["step"]), m["target"]) for _, m in recording.messages.get("/event", [])
            if m.get("event") == "target_marked"]


def session_truth(
    recording: Recording, steps: list[int]
) -> tuple[dict[int, dict[str, Any]], str]:
    """The truth the report judges ``steps`` by, and what it is (module docstring).

    Returns
    -------
    truth : dict
        ``{step: {"target": ...}}`` (with ``"label"`` from ``/truth``); a step without
        truth is left out.
    text : str
        `SIMULATED_TRUTH`, the operator's marks with their number and the steps they leave
        without truth, or that there is no truth.
    """
    truth = truth_by_step(recording)
    if truth:
        return truth, SIMULATED_TRUTH
    marks = operator_marks(recording)
    if not marks:
        return {}, "none: the recording holds no /truth and no operator's marks"
    marked: dict[int, dict[str, Any]] = {}
    for step in steps:  # the last mark at or before each step
        targets = [target for mark, target in marks if mark <= step]
        if targets:
            marked[step] = {"target": targets[-1]}
    first = min(mark for mark, _ in marks)
    before = f"steps 1 to {first - 1} have no truth" if first > 1 else "every step has one"
    return marked, (f"the operator's marks ({len(marks)} mark{'s' * (len(marks) != 1)}, "
                    f"the first at step {first}: {before}; the epochs' classes are unknown: "
                    "no decoder accuracy against the truth)")


def _signal_steps(recording: Recording) -> list[int]:
    """The step of every recorded epoch, in order (its ``step`` field, else its rank)."""
    epochs = recording.messages.get("/epoch", [])
    return [int(m.get("step", i + 1)) for i, (_, m) in enumerate(epochs)]


def _confidences(
    states: list[dict[str, Any]], targets: list[int | None], n_steps: int
) -> tuple[list[float | None], list[float | None], list[int | None]]:
    """Per step: confidence of the true task, of the best other task, and that task."""
    true_conf: list[float | None] = []
    other_conf: list[float | None] = []
    other_task: list[int | None] = []
    for k in range(n_steps):
        target = targets[k]
        confidence = states[k].get("confidence") if k < len(states) else None
        if target is None or confidence is None:
            true_conf.append(None)
            other_conf.append(None)
            other_task.append(None)
            continue
        values = np.asarray(confidence, dtype=float)
        others = values.copy()
        others[target] = -np.inf
        best = int(np.argmax(others))
        true_conf.append(float(values[target]))
        other_conf.append(float(values[best]))
        other_task.append(best)
    return true_conf, other_conf, other_task


@dataclass
class _Rerun:
    """What the re-run of the learner gives: accuracy vs truth per signal, divergence, and
    at each recorded state the decision rule (rule, threshold) in force and the confidence
    a target needed (None at the first state) (None unless the re-run reproduced the
    recording)."""

    accuracy_truth: list[float | None]
    identical: bool | None
    note: str | None
    rules: list[tuple[str, float]] | None = None
    required: list[float | None] | None = None


def _rerun(recording: Recording, n_classes: int) -> _Rerun:
    """Re-run the learner, measuring its best task's decoder against the true labels."""
    truth = truth_by_step(recording)
    labels = np.array(
        [int(truth.get(step, {}).get("label", -1)) for step in _signal_steps(recording)],
        dtype=int,
    )
    one_hot = np.zeros((len(labels), n_classes))
    known = labels >= 0
    one_hot[np.flatnonzero(known), labels[known]] = 1.0
    accuracy: list[float | None] = []
    required: list[float | None] = [None]  # the first state's, before any signal

    def measure(step: int, learner: CalibrationFreeLearner) -> None:
        # The self-estimate's exact definition, against the true labels (unknown ones
        # weigh 0); and what the next move's state requires of a target.
        beliefs = learner.beliefs()
        truth = one_hot[:step]
        prior = learner.history.n_signals - step  # a prior's signals come first, their
        if prior > 0:  # truth unknown: they weigh 0
            truth = np.vstack([np.zeros((prior, n_classes)), truth])
        accuracy.append(learner.balanced_accuracy(beliefs.best_task, truth))
        required.append(beliefs.required)

    try:
        moves, states, events = recompute(recording, measure)
    except (KeyError, ValueError, TypeError) as error:
        return _Rerun([None] * len(labels), None, f"re-run failed: {error!r}")
    if recording.truncated:  # compare only what the file holds
        n_moves = len(recording.messages.get("/move", []))
        n_states = len(recording.messages.get("/state", []))
        n_events = sum(
            m.get("event") == "target_reached" for _, m in recording.messages.get("/event", [])
        )
        moves, states, events = moves[:n_moves], states[:n_states], events[:n_events]
    divergence = first_divergence(recording, moves, states, events)
    if divergence is not None:
        return _Rerun(accuracy, False, divergence.describe())
    return _Rerun(accuracy, True, None, [(s["rule"], s["threshold"]) for s in states],
                  required[: len(states)])


def _mean_gap(steps: list[int]) -> float | None:
    return float(np.mean(np.diff(steps))) if len(steps) >= 2 else None


def session_metrics(recording: Recording, file: str = "", rerun: bool = True) -> SessionMetrics:
    """Measure one recorded session (definitions in the module docstring).

    Parameters
    ----------
    recording : Recording
        A recording with its configuration (complete or truncated).
    file : str
        Its path, for the report.
    rerun : bool, default True
        Re-run the learner for the decoder accuracy against the truth (about 10 s for 500
        steps on a 5 x 5 grid); False leaves that series None.

    Returns
    -------
    SessionMetrics

    Raises
    ------
    ValueError
        If the recording holds no configuration, or an unknown frame or world (or a grid
        world without its side).
    """
    config = recording.config
    where = file or recording.session or "recording"
    if not config:
        raise ValueError(f"{where}: the recording holds no session configuration")
    frame = config.get("frame", "feedback")
    try:
        if frame not in FRAMES:
            raise ValueError(f"unknown frame {frame!r}")
        world = config_world(config)
    except (KeyError, ValueError) as error:
        raise ValueError(
            f"{where}: the configuration has no valid frame and world ({error}): {config}"
        ) from None
    try:
        beta = learner_settings(config.get("learner", {}), frame).frame_beta
    except (ValueError, TypeError):  # settings of another version: the frame's default
        beta = DEFAULT_BETA[frame]
    frame_ = Frame(world, frame)
    n_classes = frame_.n_classes
    moves = [m for _, m in recording.messages.get("/move", [])]
    states = [m for _, m in recording.messages.get("/state", [])]
    n_steps = len(moves)
    steps = [int(m["step"]) for m in moves]
    truth, truth_text = session_truth(recording, steps)
    targets = [truth.get(step, {}).get("target") for step in steps]
    true_conf, other_conf, other_task = _confidences(states, targets, n_steps)
    counted = [k for k, (s, t) in enumerate(zip(states, targets, strict=False))
               if t is not None and "confidence" in s]
    best = [(float(states[k]["confidence"][states[k]["best_task"]]),
             states[k]["best_task"] == targets[k]) for k in counted]
    calibration = calibration_counts([c for c, _ in best], [r for _, r in best])

    declared = declared_targets(moves, truth, world)
    correct = sum(t.correct is True for t in declared)
    wrong = sum(t.correct is False for t in declared)
    update_ms = [float(m["update_ms"]) for m in moves if m.get("update_ms") is not None]

    n_signals = len(recording.messages.get("/epoch", []))
    self_by_count = {int(s["n_signals"]): s.get("balanced_accuracy") for s in states}
    accuracy_self = [self_by_count.get(t) for t in range(1, n_signals + 1)]
    if rerun:
        replay = _rerun(recording, n_classes)
    else:
        replay = _Rerun([None] * n_signals, None, "not re-run")
    accuracy_truth = replay.accuracy_truth
    calibration_by_rule = None
    rules = thresholds = required = None
    if replay.rules is not None:
        calibration_by_rule = counts_by_rule(
            [c for c, _ in best], [r for _, r in best], [replay.rules[k] for k in counted]
        )
        rules = [rule for rule, _ in replay.rules[:n_steps]]
        thresholds = [float(threshold) for _, threshold in replay.rules[:n_steps]]
        required = (replay.required or [])[:n_steps]

    warning = recording.warning
    if recording.truncated:
        last = steps[-1] if steps else 0
        warning = (
            f"{warning}; it ends after the move of step {last} "
            f"({n_signals} epochs, {len(truth)} truths of {config.get('steps', '?')} steps)"
        )
    return SessionMetrics(
        file=file,
        session=recording.session,
        frame=frame,
        class_names=list(frame_.class_names()),
        world=world.name,
        world_text=world_text(world),
        grid=world.size if isinstance(world, GridWorld) else None,
        n_tasks=world.n_tasks,
        signal=str(config.get("signal", "features")),
        beta=float(beta),
        configured_steps=int(config.get("steps", n_steps)),
        steps=n_steps,
        n_signals=n_signals,
        first_target_step=declared[0].step if declared else None,
        targets=declared,
        correct_targets=correct,
        wrong_targets=wrong,
        unverified_targets=len(declared) - correct - wrong,
        steps_per_correct_target=n_steps / correct if correct else None,
        mean_steps_between_targets=_mean_gap([t.step for t in declared]),
        update_ms=update_ms,
        latency=latency_summary(update_ms),
        step=steps,
        agent=[int(m["from_state"]) for m in moves],
        true_target=targets,
        confidence_true=true_conf,
        confidence_best_other=other_conf,
        best_other_task=other_task,
        n_seen=list(range(1, n_signals + 1)),
        accuracy_truth=accuracy_truth,
        accuracy_self=accuracy_self,
        final_accuracy_truth=accuracy_truth[-1] if accuracy_truth else None,
        final_accuracy_self=accuracy_self[-1] if accuracy_self else None,
        chance=1.0 / n_classes,
        replay_identical=replay.identical,
        replay_note=replay.note,
        truncated=recording.truncated,
        warning=warning,
        calibration_counts=calibration,
        calibration_counts_by_rule=calibration_by_rule,
        decision_rule=rules,
        decision_threshold=thresholds,
        target_requirement=required,
        settings=session_settings(config),
        truth=truth_text,
    )


def aggregate(sessions: list[SessionMetrics]) -> dict[str, dict[str, float | int | None]]:
    """Median, minimum and maximum of every `SCALAR_METRICS` over sessions.

    A metric is summarised over the sessions whose world it applies to
    (`metric_applies`), and left out when it applies to none of them; sessions where
    it is undefined (None) are left out of it; ``n`` counts the sessions that define it.

    Returns
    -------
    dict
        ``{metric: {"median", "min", "max", "n"}}``, plus ``"sessions"`` and
        ``"truncated"`` counts under ``"_count"``.
    """
    result: dict[str, dict[str, float | int | None]] = {}
    scalars = [s.scalars() for s in sessions]
    for name in SCALAR_METRICS:
        if not any(name in v for v in scalars):
            continue
        values = np.array([v[name] for v in scalars if v.get(name) is not None], dtype=float)
        if len(values):
            result[name] = {
                "median": float(np.median(values)),
                "min": float(values.min()),
                "max": float(values.max()),
                "n": len(values),
            }
        else:
            result[name] = {"median": None, "min": None, "max": None, "n": 0}
    result["_count"] = {
        "sessions": len(sessions),
        "truncated": sum(s.truncated for s in sessions),
    }
    return result
