"""``cfbci report`` of a continuous-world recording: its metrics and figures.

The session has no declared targets and no decoder of a best task to score against the
truth; what it has is a goal point (``/truth`` ``target``), the probe points (``/move``
``to_state``) and, after every epoch, the particles with their confidences (``/state``
``points`` and payload). `plane_metrics` fills a `replay.metrics.SessionMetrics`
with what applies (steps, latency, the re-run check, the best particle's distance to the
goal after each epoch); `plane_figures` draws the distance against step, the
particle cloud with the probe points so far at four steps, the probe points over time
and the update latency.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from calibration_free.cardinal import DIRECTIONS
from replay.figures import FIGURE_WIDTH, SavedFigure, latency_figure, paper_figure, save_figures
from replay.metrics import SessionMetrics, latency_summary, session_settings, truth_by_step
from replay.recording import Recording
from replay.rerun import replay_verdict

#: Steps whose particle clouds the report draws.
CLOUD_PANELS = 4


def _goal(recording: Recording) -> np.ndarray | None:
    """The user's goal point (the truths' ``target``), or None without truth."""
    truth = truth_by_step(recording)
    return np.asarray(next(iter(truth.values()))["target"], dtype=float) if truth else None


def _states(recording: Recording) -> list[dict[str, Any]]:
    return [m for _, m in recording.messages.get("/state", [])]


def plane_metrics(recording: Recording, file: str = "") -> SessionMetrics:
    """Measure a continuous-world recording (see the module docstring)."""
    config = recording.config
    moves = [m for _, m in recording.messages.get("/move", [])]
    states = _states(recording)
    n_signals = len(recording.messages.get("/epoch", []))
    goal = _goal(recording)
    distance: list[float | None] = [
        None if goal is None else float(np.linalg.norm(
            np.asarray(s["points"][s["best_task"]]) - goal))
        for s in states[1:]
    ]
    identical, note = replay_verdict(recording)
    update_ms = [float(m["update_ms"]) for m in moves if m.get("update_ms") is not None]
    n_particles = len(states[0]["points"]) if states else 0
    return SessionMetrics(
        file=file, session=recording.session, frame=str(config["frame"]),
        class_names=list(DIRECTIONS), world="continuous",
        world_text=f"continuous world ({n_particles} particles)", grid=None,
        n_tasks=n_particles, signal=str(config.get("signal", "features")), beta=None,
        configured_steps=int(config.get("steps", len(moves))), steps=len(moves),
        n_signals=n_signals, first_target_step=None, targets=[], correct_targets=0,
        wrong_targets=0, unverified_targets=0, steps_per_correct_target=None,
        mean_steps_between_targets=None, update_ms=update_ms,
        latency=latency_summary(update_ms), step=[int(m["step"]) for m in moves], agent=[],
        true_target=[None] * len(moves), confidence_true=[], confidence_best_other=[],
        best_other_task=[], n_seen=list(range(1, n_signals + 1)),
        accuracy_truth=[None] * n_signals, accuracy_self=[None] * n_signals,
        final_accuracy_truth=None, final_accuracy_self=None, chance=1.0 / len(DIRECTIONS),
        replay_identical=identical, replay_note=note, truncated=recording.truncated,
        warning=recording.warning, distance=distance,
        final_distance=distance[-1] if distance else None, settings=session_settings(config),
    )


@paper_figure
def distance_figure(metrics: SessionMetrics) -> Figure:
    """The best particle's distance to the goal against step (log scale)."""
    fig = Figure(figsize=(FIGURE_WIDTH, 3.2), layout="constrained")
    ax = fig.add_subplot()
    values = [np.nan if d is None else d for d in metrics.distance or []]
    ax.semilogy(np.arange(1, len(values) + 1), values, color="tab:blue")
    ax.set_xlabel("step (epochs observed)")
    ax.set_ylabel("distance to the goal")
    ax.set_title(f"Session {metrics.session}: the best particle's distance to the goal")
    ax.grid(alpha=0.3, which="both")
    return fig


def cloud_steps(n_states: int, n: int = CLOUD_PANELS) -> list[int]:
    """``n`` evenly spaced epochs counts in 1..n_states - 1, the last included."""
    if n_states < 2:
        return [0]
    return sorted(set(np.linspace(1, n_states - 1, n).round().astype(int).tolist()))


@paper_figure
def cloud_figure(recording: Recording, metrics: SessionMetrics) -> Figure:
    """The particle cloud (coloured by confidence), the best particle, the goal and the
    probe points so far, after `cloud_steps` epochs (two panels to a row)."""
    states = _states(recording)
    probes = np.array([m["to_state"] for _, m in recording.messages.get("/move", [])])
    goal = _goal(recording)
    chosen = cloud_steps(len(states))
    n_cols = min(len(chosen), 2)
    n_rows = -(-len(chosen) // n_cols)
    fig = Figure(figsize=(FIGURE_WIDTH, 2.9 * n_rows + 0.9), layout="constrained")
    axes = fig.subplots(n_rows, n_cols, squeeze=False).ravel()
    for ax in axes[len(chosen):]:
        ax.set_visible(False)
    axes = axes[: len(chosen)]
    scatter = None
    for ax, k in zip(axes, chosen, strict=True):
        state = states[k]
        points = np.asarray(state["points"])
        if len(probes):
            seen = probes[:k]
            ax.scatter(seen[:, 0], seen[:, 1], s=8, c="grey", alpha=0.6, marker=".",
                       label="probe points")
        scatter = ax.scatter(points[:, 0], points[:, 1], c=state["confidence"], s=24,
                             cmap="viridis", vmin=0, vmax=1, label="particles")
        best = points[state["best_task"]]
        ax.scatter(*best, s=90, facecolors="none", edgecolors="tab:orange", marker="s",
                   linewidths=1.5, label="best particle")
        if goal is not None:
            ax.scatter(*goal, s=140, c="tab:red", marker="*", label="goal")
        ax.set(xlim=(0, 1), ylim=(0, 1), aspect="equal", title=f"after {k} epochs")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncol=4,
               frameon=False)
    if scatter is not None:
        fig.colorbar(scatter, ax=list(axes), label="confidence W", shrink=0.8)
    fig.suptitle(f"Session {metrics.session}: particles and probe points")
    return fig


@paper_figure
def probes_figure(recording: Recording, metrics: SessionMetrics) -> Figure:
    """Every probe point, coloured by its step, and the goal."""
    probes = np.array([m["to_state"] for _, m in recording.messages.get("/move", [])])
    goal = _goal(recording)
    fig = Figure(figsize=(5, 4.2), layout="constrained")
    ax = fig.add_subplot()
    if len(probes):
        shown = ax.scatter(probes[:, 0], probes[:, 1], c=np.arange(1, len(probes) + 1),
                           cmap="plasma", s=14)
        fig.colorbar(shown, ax=ax, label="step")
    if goal is not None:
        ax.scatter(*goal, s=160, c="tab:red", marker="*", label="goal")
        ax.legend(loc="lower left")
    ax.set(xlim=(0, 1), ylim=(0, 1), aspect="equal")
    ax.set_title(f"Session {metrics.session}: probe points over time")
    return fig


def plane_figures(
    recording: Recording, metrics: SessionMetrics, out_dir: Path, stem: str
) -> list[SavedFigure]:
    """Write the four figures of a continuous-world session as ``out_dir/<stem>_<kind>.png``
    (kinds distance, particles, probes, latency)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    items = [
        ("distance", distance_figure(metrics),
         "Euclidean distance from the best particle (the most confident goal hypothesis) to "
         "the user's goal (/truth), after each epoch; flat until the first scoring."),
        ("particles", cloud_figure(recording, metrics),
         "The goal hypotheses (particles) coloured by their confidence W, after evenly "
         "spaced numbers of epochs, with the probe points so far (grey), the best particle "
         "(orange square) and the user's goal (red star)."),
        ("probes", probes_figure(recording, metrics),
         "Every probe point the device chose, coloured by its step, and the user's goal."),
        ("latency", latency_figure(metrics),
         "Distribution of the learner's update time per step as recorded by the service "
         "(observe the epoch + propose the next probe, ms)."),
    ]
    return save_figures(items, out_dir, stem)
