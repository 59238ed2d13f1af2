"""``cfbci report`` of a puddle-world recording: its metrics and figures.

The session declares no targets; what it has is the taught task (``/truth`` ``target``, a
task index, the same at every step), every task's normalised likelihood after every epoch
(``/state`` confidences, float32, n_signals 0 to steps), the agent's moves (``/move``
``from_state`` and ``to_state``) and the restarts (the recorded epochs' ``reset``).
`puddle_metrics` fills a `replay.metrics.SessionMetrics` with what applies:
steps, latency, the re-run check, the taught task's likelihood after every epoch
(``confidence_true``, and ``taught_likelihood`` at the update steps, every
``update_every``-th epoch, where the learner refits), the best other task's, and the
restarts; `puddle_figures` draws the taught task's likelihood against steps, the
agent's trajectory over the world with the taught task's puddle and goal, and the update
latency.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from calibration_free.puddle import MIXED_LABELS, TASK_CELLS, PuddleTask, puddle_tasks
from calibration_free.puddle_learner import PuddleConfig
from replay.figures import FIGURE_WIDTH, SavedFigure, latency_figure, paper_figure, save_figures
from replay.metrics import SessionMetrics, latency_summary, session_settings, truth_by_step
from replay.recording import Recording
from replay.rerun import recorded_resets, replay_verdict


def _states_by_signals(recording: Recording) -> dict[int, dict[str, Any]]:
    """The first recorded state of every ``n_signals``."""
    states: dict[int, dict[str, Any]] = {}
    for _, state in recording.messages.get("/state", []):
        states.setdefault(int(state["n_signals"]), state)
    return states


def _update_every(config: dict[str, Any]) -> int:
    return int(config.get("learner", {}).get("update_every", PuddleConfig.update_every))


def puddle_metrics(recording: Recording, file: str = "") -> SessionMetrics:
    """Measure a puddle-world recording (see the module docstring)."""
    config = recording.config
    moves = [m for _, m in recording.messages.get("/move", [])]
    states = _states_by_signals(recording)
    n_signals = len(recording.accepted_epochs())
    truth = truth_by_step(recording)
    taught = int(next(iter(truth.values()))["target"]) if truth else None
    true_target = [None if (t := truth.get(int(m["step"]))) is None else int(t["target"])
                   for m in moves]
    confidence_true: list[float | None] = []
    best_other: list[float | None] = []
    best_other_task: list[int | None] = []
    for k in range(1, n_signals + 1):  # after k epochs
        state = states.get(k)
        if state is None or taught is None:
            confidence_true.append(None)
            best_other.append(None)
            best_other_task.append(None)
            continue
        confidence = np.asarray(state["confidence"], dtype=float)
        confidence_true.append(float(confidence[taught]))
        others = confidence.copy()
        others[taught] = -np.inf
        best_other_task.append(int(np.argmax(others)))
        best_other.append(float(others.max()))
    every = _update_every(config)
    update_steps = [k for k in range(every, n_signals + 1, every)]
    taught_likelihood = [confidence_true[k - 1] for k in update_steps]
    resets = recorded_resets(recording)
    restarts = [k for k, reset in enumerate(resets, start=1) if reset]
    identical, note = replay_verdict(recording)
    update_ms = [float(m["update_ms"]) for m in moves if m.get("update_ms") is not None]
    n_tasks = len(puddle_tasks())
    return SessionMetrics(
        file=file, session=recording.session, frame=str(config["frame"]),
        class_names=list(MIXED_LABELS), world="puddle",
        world_text=f"puddle world ({n_tasks} tasks)", grid=None, n_tasks=n_tasks,
        signal=str(config.get("signal", "features")), beta=None,
        configured_steps=int(config.get("steps", len(moves))), steps=len(moves),
        n_signals=n_signals, first_target_step=None, targets=[], correct_targets=0,
        wrong_targets=0, unverified_targets=0, steps_per_correct_target=None,
        mean_steps_between_targets=None, update_ms=update_ms,
        latency=latency_summary(update_ms), step=[int(m["step"]) for m in moves], agent=[],
        true_target=true_target, confidence_true=confidence_true,
        confidence_best_other=best_other, best_other_task=best_other_task,
        n_seen=list(range(1, n_signals + 1)), accuracy_truth=[None] * n_signals,
        accuracy_self=[None] * n_signals, final_accuracy_truth=None,
        final_accuracy_self=None, chance=1.0 / len(MIXED_LABELS),
        replay_identical=identical, replay_note=note, truncated=recording.truncated,
        warning=recording.warning, update_steps=update_steps,
        taught_likelihood=taught_likelihood,
        final_taught_likelihood=taught_likelihood[-1] if taught_likelihood else None,
        restarts=restarts, goals_reached=len(restarts), settings=session_settings(config),
    )


@paper_figure
def likelihood_figure(metrics: SessionMetrics) -> Figure:
    """The taught task's and the best other task's normalised likelihood against the
    epochs observed (log scale), the update steps marked, the restarts as vertical lines."""
    fig = Figure(figsize=(FIGURE_WIDTH, 3.4), layout="constrained")
    ax = fig.add_subplot()
    epochs = np.arange(1, len(metrics.confidence_true) + 1)
    taught = np.array([np.nan if v is None else v for v in metrics.confidence_true])
    other = np.array([np.nan if v is None else v for v in metrics.confidence_best_other])
    floor = 1e-6
    ax.semilogy(epochs, np.maximum(taught, floor), color="tab:blue", drawstyle="steps-post",
                label="taught task")
    ax.semilogy(epochs, np.maximum(other, floor), color="tab:orange", drawstyle="steps-post",
                lw=0.9, label="most likely other task")
    updates = metrics.update_steps or []
    values = [np.nan if v is None else max(v, floor) for v in metrics.taught_likelihood or []]
    ax.scatter(updates, values, color="tab:blue", s=18, zorder=3, label="at the updates")
    ax.axhline(1.0 / metrics.n_tasks, color="0.5", ls="--", lw=0.9,
               label=f"uniform (1/{metrics.n_tasks})")
    for k, step in enumerate(metrics.restarts or []):
        ax.axvline(step, color="tab:green", lw=0.7, alpha=0.6,
                   label="restart (goal reached)" if k == 0 else None)
    ax.set_ylim(floor, 1.5)
    ax.set_xlabel("epochs observed")
    ax.set_ylabel("normalised likelihood")
    ax.set_title(f"Session {metrics.session}: the taught task's normalised likelihood")
    fig.legend(loc="outside lower center", ncol=3, frameon=False)
    ax.grid(alpha=0.3, which="both")
    return fig


def _cell_patch(cell: int, **style: Any) -> Rectangle:
    row, col = divmod(cell, TASK_CELLS)
    size = 1.0 / TASK_CELLS
    return Rectangle((col * size, row * size), size, size, **style)


@paper_figure
def trajectory_figure(recording: Recording, metrics: SessionMetrics) -> Figure:
    """The agent's moves over the unit square, coloured by step, with the taught task's
    puddle (blue) and goal cell (green), the start and the restart points."""
    moves = [m for _, m in recording.messages.get("/move", [])]
    taught = next((t for t in metrics.true_target if t is not None), None)
    fig = Figure(figsize=(5.6, 4.8), layout="constrained")
    ax = fig.add_subplot()
    task: PuddleTask | None = None if taught is None else puddle_tasks()[taught]
    if task is not None:
        for cell in task.puddle:
            ax.add_patch(_cell_patch(cell, color="tab:blue", alpha=0.35, lw=0))
        ax.add_patch(_cell_patch(task.goal, color="tab:green", alpha=0.35, lw=0))
    for k in range(1, TASK_CELLS):
        ax.axhline(k / TASK_CELLS, color="0.8", lw=0.6)
        ax.axvline(k / TASK_CELLS, color="0.8", lw=0.6)
    if moves:
        segments = np.array([[m["from_state"], m["to_state"]] for m in moves])
        lines = LineCollection(segments, array=np.arange(1, len(moves) + 1), cmap="plasma",
                               lw=1.4)
        ax.add_collection(lines)
        fig.colorbar(lines, ax=ax, label="step")
        ax.scatter(*segments[0, 0], s=60, c="black", marker="o", label="start", zorder=3)
        restarts = [segments[step, 0] for step in metrics.restarts or [] if step < len(moves)]
        if restarts:
            points = np.array(restarts)
            ax.scatter(points[:, 0], points[:, 1], s=50, facecolors="none",
                       edgecolors="black", marker="o", label="restarts", zorder=3)
    handles = [Rectangle((0, 0), 1, 1, color="tab:blue", alpha=0.35, label="puddle"),
               Rectangle((0, 0), 1, 1, color="tab:green", alpha=0.35, label="goal")]
    fig.legend(handles=[*handles, *ax.get_legend_handles_labels()[0]],
               loc="outside lower center", ncol=4, frameon=False)
    ax.set(xlim=(0, 1), ylim=(0, 1), aspect="equal")
    name = "no truth" if task is None else (
        f"task {taught}: goal cell {task.goal}, puddle {list(task.puddle)}")
    ax.set_title(f"Session {metrics.session}: the agent's trajectory\n({name})")
    return fig


def puddle_figures(
    recording: Recording, metrics: SessionMetrics, out_dir: Path, stem: str
) -> list[SavedFigure]:
    """Write the three figures of a puddle session as ``out_dir/<stem>_<kind>.png``
    (kinds likelihood, trajectory, latency)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    every = _update_every(recording.config)
    items = [
        ("likelihood", likelihood_figure(metrics),
         "The taught task's normalised likelihood (the learner's probability of the task "
         f"the teacher has, /truth) after each epoch, with the most likely other task's; "
         f"they change at the updates (dots, every {every} epochs); green lines: the agent "
         "entered the goal cell and restarted."),
        ("trajectory", trajectory_figure(recording, metrics),
         "Every move of the agent (from its state to the move's outcome, coloured by step) "
         "over the unit square and its 5 x 5 task cells, with the taught task's puddle "
         "(blue) and goal cell (green); after a restart the next move starts elsewhere."),
        ("latency", latency_figure(metrics),
         "Distribution of the learner's update time per step as recorded by the service "
         "(observe the epoch + propose the next move, ms)."),
    ]
    return save_figures(items, out_dir, stem)
