"""Paper-ready PNG figures of a recorded session (matplotlib, Agg backend, headless).

Each ``*_figure`` function returns a `matplotlib.figure.Figure` built without pyplot
(no global state, safe in worker processes); `session_figures` saves them all as PNG
files and returns their titles and captions. Steps, confidences and accuracies are those
of `replay.metrics` (see its docstring for the definitions and their alignment).

Figures are drawn at their printed size: `FIGURE_WIDTH` inches wide at most, with
the fonts of `PAPER_STYLE` (8 points and more), which every figure function applies
(`paper_figure`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

import matplotlib

matplotlib.use("Agg")

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle

from replay.calibration import CalibrationPanel
from replay.metrics import SessionMetrics
from replay.recording import RANKED, Recording, decode_array
from session.config import config_world

#: Resolution of the saved PNG files, dots per inch.
DPI = 150
#: The widest figure, inches: a one-column paper's text width (a two-column paper's
#: figure across both columns is a little wider), so that fonts print at their size.
FIGURE_WIDTH = 6.5
#: The matplotlib settings of every figure (`paper_figure`): font sizes in points at
#: the printed width, none under 8.
PAPER_STYLE: dict[str, Any] = {
    "font.size": 9,
    "axes.titlesize": 9,
    "axes.labelsize": 9,
    "xtick.labelsize": 8,
    "ytick.labelsize": 8,
    "legend.fontsize": 8,
    "legend.title_fontsize": 8,
    "figure.titlesize": 10,
    "figure.labelsize": 9,
}
#: A belief map's side, inches (a 5 x 5 grid's cell is then about 9 mm).
MAP_SIDE = 1.75
#: Belief maps per row.
MAP_COLUMNS = 3
#: Moves of the current search drawn on a belief map (the most recent ones).
PATH_MOVES = 25
_CORRECT, _WRONG, _UNVERIFIED = "tab:green", "tab:red", "tab:gray"
_TOP, _MARK_Y = 1.1, 1.055  # y limit of the [0, 1] plots, and the height of target marks
_CLASS_COLOURS = ("tab:blue", "tab:red", "tab:green", "tab:purple")

_Params = ParamSpec("_Params")
_Built = TypeVar("_Built", Figure, tuple[Figure, str])


def paper_figure(build: Callable[_Params, _Built]) -> Callable[_Params, _Built]:
    """Build a figure (or a ``(figure, text)`` pair) under `PAPER_STYLE`, drawn once
    within it so that every text, tick labels included, takes its sizes."""

    @functools.wraps(build)
    def styled(*args: _Params.args, **kwargs: _Params.kwargs) -> _Built:
        with matplotlib.rc_context(PAPER_STYLE):
            built = build(*args, **kwargs)
            (built if isinstance(built, Figure) else built[0]).draw_without_rendering()
        return built

    return styled


@dataclass(frozen=True)
class FeatureLayout:
    """How a feature vector is laid out: ``len(ch_names)`` channels of ``n_times`` samples,
    channel-major (features ``c * n_times`` to ``(c + 1) * n_times - 1`` are channel
    ``c``'s).

    A recording's config says it in ``feature_layout``: ``{"ch_names": [...], "n_times":
    T}`` (`of_config`).
    """

    ch_names: tuple[str, ...]
    n_times: int

    @property
    def n_features(self) -> int:
        """Features per vector."""
        return len(self.ch_names) * self.n_times

    @classmethod
    def of_config(cls, config: dict[str, Any]) -> FeatureLayout | None:
        """The layout a config states (None if it states none, or not as a list of names
        and a positive sample count)."""
        stated = config.get("feature_layout")
        if not isinstance(stated, dict):
            return None
        names, n_times = stated.get("ch_names"), stated.get("n_times")
        if (not isinstance(names, list) or not names or not isinstance(n_times, int)
                or isinstance(n_times, bool) or n_times < 1):
            return None
        return cls(tuple(str(name) for name in names), n_times)


@dataclass(frozen=True)
class SavedFigure:
    """A figure written to disk.

    Attributes
    ----------
    kind : str
        "confidence", "belief", "accuracy", "erp" or "latency"; a continuous-world
        session's: "distance", "particles", "probes" or "latency" (`replay.plane_report`).
    path : Path
        The PNG file.
    title : str
        The figure's title.
    caption : str
        What it shows, for a report.
    """

    kind: str
    path: Path
    title: str
    caption: str


def _series(values: list[float | None]) -> np.ndarray:
    """A list with None as a float array with NaN (matplotlib leaves gaps there)."""
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _mark_targets(ax: Axes, metrics: SessionMetrics, y: float, label: bool = True) -> None:
    """Declared targets as vertical lines and markers at height ``y`` (axes data units)."""
    for target in metrics.targets:
        colour = {True: _CORRECT, False: _WRONG, None: _UNVERIFIED}[target.correct]
        ax.axvline(target.step, color=colour, lw=0.8, alpha=0.5, zorder=1)
        ax.plot(target.step, y, marker="v", color=colour, ms=6, zorder=4)


def _unit_axes_over_steps(ax: Axes, metrics: SessionMetrics) -> None:
    """Steps on x (the whole configured session), [0, 1] on y; targets and truncation marked."""
    _mark_targets(ax, metrics, _MARK_Y)
    _mark_truncation(ax, metrics)
    ax.set_xlim(0, max(metrics.configured_steps, metrics.steps, 1) + 1)
    ax.set_ylim(0, _TOP)
    ax.set_yticks(np.linspace(0, 1, 6))


def _legend_below(fig: Figure, ax: Axes, metrics: SessionMetrics) -> None:
    """The plot's legend, with the declared-target markers, below the axes; a light grid."""
    handles, _ = ax.get_legend_handles_labels()
    fig.legend(handles=handles + _target_handles(metrics), loc="outside lower center",
               ncol=2, frameon=False)
    ax.grid(alpha=0.3)


def rules_text(metrics: SessionMetrics) -> str:
    """The decision rules of the session with their thresholds, e.g. ``pairwise > 0.93,
    normalised > 0.995``; or, without the re-run's, the configured threshold."""
    rules = metrics.decision_rules()
    if rules:
        return ", ".join(f"{rule} > {threshold:g}" for rule, threshold, _ in rules)
    configured = metrics.settings.learner.get("confidence") if metrics.settings else None
    return f"{configured or 'confidence'} > {metrics.beta:g} (configured)"


def _first_target_signals(metrics: SessionMetrics) -> int:
    """The signals over which a first target's requirement relaxes (0 if not recorded)."""
    learner = metrics.settings.learner if metrics.settings else {}
    return int(learner.get("first_target_signals") or 0)


def _mark_truncation(ax: Axes, metrics: SessionMetrics) -> None:
    """Shade the steps a truncated recording does not hold."""
    if metrics.truncated and metrics.steps < metrics.configured_steps:
        ax.axvspan(metrics.steps + 0.5, metrics.configured_steps + 1, color="0.85", zorder=0,
                   label="not in the file (truncated)")


def _target_handles(metrics: SessionMetrics) -> list[Line2D]:
    """Legend entries of the declared-target marks present in the session."""
    kinds = {t.correct for t in metrics.targets}
    names = {True: "correct target declared", False: "wrong target declared",
             None: "target declared (no truth)"}
    colours = {True: _CORRECT, False: _WRONG, None: _UNVERIFIED}
    return [
        Line2D([], [], color=colours[k], marker="v", lw=0.8, label=names[k])
        for k in (True, False, None)
        if k in kinds
    ]


def _targets_text(metrics: SessionMetrics) -> str:
    return (
        f"{metrics.correct_targets} correct, {metrics.wrong_targets} wrong targets"
        + (f", {metrics.unverified_targets} unverified" if metrics.unverified_targets else "")
    )


@paper_figure
def confidence_figure(metrics: SessionMetrics) -> Figure:
    """Confidence of the true task and of the best other task against step.

    Dashed: the confidence a target needs at each step (the threshold of the rule in force,
    more before the first target), from the re-run; without it, the configured threshold.
    Declared targets are vertical lines, green when correct and red when wrong.
    """
    fig = Figure(figsize=(FIGURE_WIDTH, 3.6), layout="constrained")
    ax = fig.add_subplot()
    steps = np.asarray(metrics.step)
    ax.plot(steps, _series(metrics.confidence_true), color="tab:blue", lw=1.3,
            label="true target task", zorder=3)
    ax.plot(steps, _series(metrics.confidence_best_other), color="tab:orange", lw=1.0,
            label="most confident other task", zorder=2)
    if metrics.target_requirement is not None:
        ax.plot(steps, _series(metrics.target_requirement), color="black", ls="--", lw=0.9,
                drawstyle="steps-mid", label=f"a target needs: {rules_text(metrics)}")
    elif metrics.beta is not None:
        ax.axhline(metrics.beta, color="black", ls="--", lw=0.9,
                   label=f"threshold: {rules_text(metrics)}")
    _unit_axes_over_steps(ax, metrics)
    ax.set_xlabel("step (device action)")
    ax.set_ylabel("confidence (rule in force)")
    ax.set_title(
        f"Session {metrics.session}: confidence in the true target\n"
        f"{_world_title(metrics)}, {metrics.frame} frame; {_targets_text(metrics)}"
    )
    _legend_below(fig, ax, metrics)
    return fig


def belief_steps(metrics: SessionMetrics, n: int = 4) -> list[int]:
    """The steps whose belief maps are drawn: ``n`` evenly spaced steps (the last one
    included) and the step of the first declared target, sorted and distinct."""
    last = metrics.steps
    if last == 0:
        return []
    chosen = {max(1, round(last * (i + 1) / n)) for i in range(n)}
    if metrics.first_target_step is not None:
        chosen.add(metrics.first_target_step)
    return sorted(chosen)


def _world_title(metrics: SessionMetrics) -> str:
    """``5×5 grid``, or the description of another world."""
    return f"{metrics.grid}×{metrics.grid} grid" if metrics.grid else metrics.world_text


def _cell_xy(cell: int, grid: int) -> tuple[int, int]:
    row, col = divmod(int(cell), grid)
    return col, row


@paper_figure
def belief_figure(recording: Recording, metrics: SessionMetrics) -> Figure:
    """Belief maps (confidence of every target cell) at `belief_steps`; in a world
    without a grid layout, `ranking_figure`.

    Each panel is the ``/state`` the learner chose that step's move on; row 0 of the grid is
    at the top (``up`` moves towards it). Marked: the agent's cell, the user's true target,
    the learner's best cell, and the most recent moves of the current search (since the
    last declared target, at most `PATH_MOVES`), more opaque when more recent. Maps
    are `MAP_SIDE` inches a side, `MAP_COLUMNS` to a row.
    """
    states = [m for _, m in recording.messages.get("/state", [])]
    chosen = [k for k in belief_steps(metrics) if k - 1 < len(states)]
    grid = metrics.grid
    if grid is None:
        return ranking_figure(recording, states, chosen, metrics)
    n_cols = min(max(len(chosen), 1), MAP_COLUMNS)
    n_rows = -(-max(len(chosen), 1) // n_cols)
    fig = Figure(figsize=(FIGURE_WIDTH, (MAP_SIDE + 0.55) * n_rows + 1.3),
                 layout="constrained")
    axes = fig.subplots(n_rows, n_cols, squeeze=False)
    shown = [ax for ax, _ in zip(axes.ravel(), chosen, strict=False)]
    for ax in axes.ravel()[len(chosen):]:
        ax.set_visible(False)
    cell = MAP_SIDE * 72 / grid  # a cell's side, points: markers scale with it
    image = None
    declared = [t.step for t in metrics.targets]
    for index, (ax, step) in enumerate(zip(shown, chosen, strict=True)):
        state = states[step - 1]
        confidence = np.asarray(state["confidence"], dtype=float).reshape(grid, grid)
        image = ax.imshow(confidence, cmap="viridis", vmin=0, vmax=1, origin="upper")
        start = max([s for s in declared if s < step], default=0) + 1
        start = max(start, step - PATH_MOVES)
        path = [_cell_xy(c, grid) for c in metrics.agent[start - 1 : step]]
        if len(path) > 1:
            xs, ys = np.array(path, dtype=float).T
            for i in range(len(path) - 1):
                alpha = 0.25 + 0.75 * (i + 1) / (len(path) - 1)
                ax.plot(xs[i : i + 2], ys[i : i + 2], color="white", lw=1.5, alpha=alpha)
        x, y = _cell_xy(metrics.agent[step - 1], grid)
        ax.plot(x, y, "o", ms=0.7 * cell, mfc="none", mec="white", mew=2.0)
        target = metrics.true_target[step - 1]
        if target is not None:
            tx, ty = _cell_xy(target, grid)
            ax.plot(tx, ty, "*", ms=0.55 * cell, mfc="tab:red", mec="white", mew=0.8)
        bx, by = _cell_xy(state["best_task"], grid)
        ax.add_patch(Rectangle(
            (bx - 0.46, by - 0.46), 0.92, 0.92, fill=False, ec="tab:orange", lw=2.0))
        label = f"step {step}"
        if step == metrics.first_target_step:
            label += " (first target)"
        elif step in declared:
            label += " (target declared)"
        ax.set_title(label)
        ax.set_xticks(range(grid))
        ax.set_yticks(range(grid))
        if index + n_cols >= len(chosen):  # no map below
            ax.set_xlabel("column")
        if index % n_cols == 0:
            ax.set_ylabel("row")
    if image is not None:
        bar = fig.colorbar(image, ax=shown, orientation="horizontal", location="bottom",
                           shrink=0.6, aspect=40)
        bar.set_label("confidence of the cell as target (rule in force)")
    handles = [
        Line2D([], [], ls="", marker="o", ms=10, mfc="none", mec="white", mew=2,
               label="agent"),
        Line2D([], [], ls="", marker="*", ms=11, mfc="tab:red", mec="white",
               label="true target"),
        Line2D([], [], ls="", marker="s", ms=9, mfc="none", mec="tab:orange", mew=2,
               label="learner's best cell"),
        Line2D([], [], color="white", lw=1.5, label="recent path"),
    ]
    legend = fig.legend(handles=handles, loc="outside lower center", ncol=4,
                        facecolor="0.5", framealpha=0.4)
    legend.get_frame().set_edgecolor("none")
    fig.suptitle(f"Session {metrics.session}: belief over target cells")
    return fig


@paper_figure
def ranking_figure(
    recording: Recording, states: list[dict], chosen: list[int], metrics: SessionMetrics
) -> Figure:
    """The `RANKED` most confident tasks, by name, at each of the ``chosen`` steps.

    One panel per step (the ``/state`` that step's move was chosen on), best task on top:
    the user's true target in red (listed last, below a gap, when it is not among them),
    the others grey; the agent's state in the panel's title; dashed, the confidence a
    target needed at the step (the re-run's; without it, the configured threshold).
    """
    world = config_world(recording.config)
    bars = min(RANKED, metrics.n_tasks) + 1  # at most: the target below the others
    fig = Figure(figsize=(FIGURE_WIDTH, max(len(chosen), 1) * (0.2 * bars + 0.8) + 0.9),
                 layout="constrained")
    axes = fig.subplots(max(len(chosen), 1), 1, squeeze=False)[:, 0]
    declared = [t.step for t in metrics.targets]
    for ax, step in zip(axes, chosen, strict=False):
        confidence = np.asarray(states[step - 1]["confidence"], dtype=float)
        ranked = list(np.argsort(-confidence, kind="stable")[:RANKED])
        target = metrics.true_target[step - 1]
        if target is not None and target not in ranked:
            ranked.append(target)
        colours = ["tab:red" if t == target else "0.55" for t in ranked]
        rows = np.arange(len(ranked)) + (np.arange(len(ranked)) >= RANKED) * 0.5
        ax.barh(rows, confidence[ranked], color=colours, height=0.7)
        ax.set_yticks(rows, [f"{world.task_name(int(t))}" for t in ranked])
        ax.invert_yaxis()
        ax.set_xlim(0, 1)
        needed = (metrics.beta if metrics.target_requirement is None
                  else metrics.target_requirement[step - 1])
        if needed is not None:
            ax.axvline(needed, color="black", ls="--", lw=0.8)
        note = " (first target declared)" if step == metrics.first_target_step else (
            " (target declared)" if step in declared else "")
        agent = world.state_name(metrics.agent[step - 1])
        ax.set_title(f"step {step}{note}; agent: {agent}", loc="right")
        ax.grid(axis="x", alpha=0.3)
    dashed = ("the confidence a target needed" if metrics.target_requirement is not None
              else f"the configured threshold {metrics.beta:g}")
    axes[-1].set_xlabel(f"confidence of the task as target (rule in force; dashed: {dashed})")
    handles = [
        Rectangle((0, 0), 1, 1, color="tab:red", label="true target"),
        Rectangle((0, 0), 1, 1, color="0.55", label="other task"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=2, frameon=False)
    fig.suptitle(f"Session {metrics.session}: most confident tasks, {metrics.world_text}")
    return fig


@paper_figure
def accuracy_figure(metrics: SessionMetrics) -> Figure:
    """Decoder balanced accuracy against the number of signals observed.

    Against the recorded true labels (re-run learner, best task's out-of-fold
    predictions) and the recording's self-estimate (against the best task's own labels),
    with the chance level ``1 / n_classes``.
    """
    fig = Figure(figsize=(FIGURE_WIDTH, 3.6), layout="constrained")
    ax = fig.add_subplot()
    seen = np.asarray(metrics.n_seen)
    ax.plot(seen, _series(metrics.accuracy_truth), color="tab:blue", lw=1.8, zorder=3,
            label="vs true labels")
    ax.plot(seen, _series(metrics.accuracy_self), color="tab:orange", lw=1.0, ls="--",
            zorder=4, label="self-estimate (vs best task's labels)")
    ax.axhline(metrics.chance, color="black", ls=":", lw=1.0,
               label=f"chance ({metrics.chance:g})")
    _unit_axes_over_steps(ax, metrics)
    ax.set_xlabel("signals observed (= step of the latest epoch)")
    ax.set_ylabel(f"balanced accuracy ({folds_text(metrics)} CV)")
    final = metrics.final_accuracy_truth
    ax.set_title(
        f"Session {metrics.session}: decoder balanced accuracy of the best task\n"
        f"{len(metrics.class_names)} classes ({', '.join(metrics.class_names)}); final vs "
        f"truth {'n/a' if final is None else f'{final:.2f}'}"
    )
    _legend_below(fig, ax, metrics)
    return fig


def folds_text(metrics: SessionMetrics) -> str:
    """``10-fold``: the session's cross-validation folds (``n_folds``), if recorded."""
    folds = metrics.settings.learner.get("n_folds") if metrics.settings else None
    return f"{folds}-fold" if folds else "k-fold"


def _labelled_signals(recording: Recording) -> tuple[np.ndarray, np.ndarray, str]:
    """Recorded epochs (n, ...) with their true labels (n,), and their units."""
    truth = {int(m["step"]): int(m["label"]) for _, m in recording.messages.get("/truth", [])}
    epochs, labels, units = [], [], "uV"
    for index, (_, message) in enumerate(recording.messages.get("/epoch", [])):
        label = truth.get(int(message.get("step", index + 1)))
        if label is None:
            continue
        epochs.append(decode_array(message))
        labels.append(label)
        units = message.get("units", units)
    if not epochs:
        return np.zeros((0,)), np.zeros(0, dtype=int), units
    return np.stack(epochs).astype(float), np.asarray(labels), units


def _unit(units: str) -> str:
    return "µV" if units in ("uV", "µV") else units


@paper_figure
def erp_figure(
    recording: Recording, metrics: SessionMetrics, layout: FeatureLayout | None = None
) -> tuple[Figure, str]:
    """Grand averages of the recorded signals by true class; returns (figure, what).

    Raw epochs (``signal`` "epochs"): one panel per channel, time in ms after the action
    onset (``tmin`` and ``sfreq`` of the config). Features: where their layout is known
    (the config's ``feature_layout``, else ``layout``) and fits them, one panel per
    channel, class means against the sample within the channel; otherwise class means
    against feature index. Feedback frame: error and correct averages and the difference
    wave (error minus correct); guidance frame: the mean of each of the four classes.
    ``what`` describes it.
    """
    signals, labels, units = _labelled_signals(recording)
    unit = _unit(units)
    names = metrics.class_names
    feedback = metrics.frame == "feedback"
    raw = metrics.signal == "epochs" and signals.ndim == 3
    counts = [int(np.sum(labels == k)) for k in range(len(names))]
    means = [signals[labels == k].mean(axis=0) if counts[k] else None for k in range(len(names))]
    layout = FeatureLayout.of_config(recording.config) or layout
    n_features = next((m.size for m in means if m is not None), 0)
    channels = None
    if raw:
        what = "grand averages of the raw epochs"
        config = recording.config
        channels = config.get("ch_names") or [f"ch{i}" for i in range(signals.shape[1])]
        x = (config["tmin"] + np.arange(signals.shape[2]) / config["sfreq"]) * 1e3
        xlabel, ylabel = "time after action onset (ms)", f"amplitude ({unit})"
    elif layout is not None and layout.n_features == n_features:
        what = (f"class means of the feature vectors per channel\n({len(layout.ch_names)} "
                f"channels x {layout.n_times} samples; the recording holds no raw epochs)")
        channels = [f"{name} (features {c * layout.n_times}-{(c + 1) * layout.n_times - 1})"
                    for c, name in enumerate(layout.ch_names)]
        means = [None if m is None else m.reshape(len(channels), layout.n_times)
                 for m in means]
        x = np.arange(layout.n_times)
        # The wire protocol labels every epoch payload "uV", but a dataset's feature
        # vectors may be in other units (s4.mat's are µV, move_finger.mat's are not).
        xlabel, ylabel = "sample within the channel", "feature value (units of the dataset)"
    else:
        what = "class means of the feature vectors (the recording holds no raw epochs)"
    if feedback:
        what += "\nerror vs correct, and the difference wave (error − correct)"
    else:
        what += "\none curve per true class (guidance frame, 4 classes: no error/correct)"
    if channels is not None:
        n_cols = min(2, len(channels))
        n_rows = int(np.ceil(len(channels) / n_cols))
        fig = Figure(figsize=(FIGURE_WIDTH, 2.3 * n_rows + 1.0), layout="constrained")
        axes = fig.subplots(n_rows, n_cols, squeeze=False, sharex=True, sharey=True).ravel()
        for channel, ax in enumerate(axes):
            if channel >= len(channels):
                ax.set_visible(False)
                continue
            _plot_means(ax, x, [m[channel] if m is not None else None for m in means],
                        names, counts, feedback, markers=not raw)
            if raw:
                ax.axvline(0, color="black", lw=0.8)
            ax.set_title(channels[channel])
            if channel + n_cols >= len(channels):
                ax.set_xlabel(xlabel)
                ax.tick_params(labelbottom=True)
            if channel % n_cols == 0:
                ax.set_ylabel(ylabel)
    else:
        flat = [m.reshape(-1) if m is not None else None for m in means]
        fig = Figure(figsize=(FIGURE_WIDTH, 3.4), layout="constrained")
        ax = fig.add_subplot()
        _plot_means(ax, np.arange(n_features), flat, names, counts, feedback, markers=True)
        ax.set_xlabel("feature index")
        ax.set_ylabel("feature value (units of the dataset)")
    handles, labels_ = fig.axes[0].get_legend_handles_labels() if fig.axes else ([], [])
    if handles:
        fig.legend(handles, labels_, loc="outside lower center", ncol=min(len(handles), 3),
                   frameon=False)
    fig.suptitle(f"Session {metrics.session}: {what}")
    return fig, " ".join(what.split())


def _plot_means(ax: Axes, x: np.ndarray, means: list[np.ndarray | None], names: list[str],
                counts: list[int], feedback: bool, markers: bool = False) -> None:
    """Class means (and, for feedback, the error - correct difference) on one axes."""
    style = {"marker": ".", "ms": 4} if markers else {}
    if len(x) == 0:
        ax.text(0.5, 0.5, "no labelled signal", ha="center", va="center",
                transform=ax.transAxes)
        return
    for k, (mean, name) in enumerate(zip(means, names, strict=True)):
        if mean is not None:
            ax.plot(x, mean, color=_CLASS_COLOURS[k], lw=1.1, label=f"{name} (n={counts[k]})",
                    **style)
    if feedback and means[0] is not None and means[1] is not None:
        ax.plot(x, means[1] - means[0], color="black", lw=1.4, ls="--",
                label="difference (error − correct)", **style)
    ax.axhline(0, color="0.6", lw=0.6)
    ax.grid(alpha=0.3)


@paper_figure
def latency_figure(metrics: SessionMetrics) -> Figure:
    """Histogram of the learner's update time per step, ms, with median, p90 and p99."""
    fig = Figure(figsize=(FIGURE_WIDTH, 3.2), layout="constrained")
    ax = fig.add_subplot()
    values = np.asarray(metrics.update_ms, dtype=float)
    latency = metrics.latency
    if latency is None:
        ax.text(0.5, 0.5, "no update time recorded", ha="center", va="center",
                transform=ax.transAxes)
    else:
        upper = max(latency.p99_ms * 1.5, latency.median_ms * 2)
        shown = values[values <= upper]
        ax.hist(shown, bins=60, range=(0, upper), color="tab:blue", alpha=0.75)
        for value, name, style in ((latency.median_ms, "median", "-"),
                                   (latency.p90_ms, "90th percentile", "--"),
                                   (latency.p99_ms, "99th percentile", ":")):
            ax.axvline(value, color="black", ls=style, lw=1.1, label=f"{name} {value:.1f} ms")
        beyond = len(values) - len(shown)
        ax.plot([], [], " ", label=f"max {latency.max_ms:.1f} ms"
                + (f"\n({beyond} step(s) above {upper:.0f} ms\nnot shown)" if beyond else ""))
        ax.set_xlim(0, upper)
        ax.legend(frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_xlabel("learner update time per step (ms; observe + propose)")
    ax.set_ylabel("steps")
    ax.set_title(
        f"Session {metrics.session}: learner update latency "
        f"({len(values)} steps, {metrics.n_tasks} task hypotheses)"
    )
    ax.grid(alpha=0.3)
    return fig


def threshold_caption(metrics: SessionMetrics) -> str:
    """What the dashed line of the confidence figure is, with the session's rules and
    thresholds."""
    rules = metrics.decision_rules()
    if not rules:
        if metrics.beta is None:
            return ""
        return (f"Dashed: the configured threshold {metrics.beta:g} (the re-run did not "
                "reproduce the recording: the rule in force at each step is not known).")
    text = ("Dashed: the confidence a declared target needed at each step (the re-run of the "
            "learner): the threshold of the rule in force ("
            + "; ".join(f"{rule} > {threshold:g} at {steps} steps"
                        for rule, threshold, steps in rules) + ")")
    signals = _first_target_signals(metrics)
    if signals:
        text += (", more before the first target, relaxing from 1 to the threshold over the "
                 f"first {signals} signals")
    return text + "."


def session_figures(
    recording: Recording, metrics: SessionMetrics, out_dir: Path, stem: str,
    layout: FeatureLayout | None = None,
) -> list[SavedFigure]:
    """Write the five figures of a session as ``out_dir/<stem>_<kind>.png``.

    Parameters
    ----------
    recording : Recording
    metrics : SessionMetrics
        Of ``recording`` (`replay.metrics.session_metrics`).
    out_dir : Path
        Created if missing.
    stem : str
        File name prefix, unique per session.
    layout : FeatureLayout, optional
        The feature vectors' layout where the recording's config does not state it
        (`erp_figure`).

    Returns
    -------
    list of SavedFigure
        In the order confidence, belief, accuracy, erp, latency.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    erp, erp_what = erp_figure(recording, metrics, layout)
    chosen = ", ".join(str(s) for s in belief_steps(metrics))
    belief_caption = (
        f"Confidence of every {'cell' if metrics.grid else 'task'} as the target at steps "
        f"{chosen} (evenly spaced, and the step of the first declared target), in the state "
        "each step's move was chosen on."
    )
    threshold = "" if metrics.beta is None else f" {metrics.beta:g}"
    items = [
        ("confidence", confidence_figure(metrics),
         "Confidence, by the decision rule in force, of the user's true target task and of "
         "the most confident other task, in the state the learner chose each move on. "
         f"{threshold_caption(metrics)} Triangles and vertical lines: declared targets (green "
         "correct, red wrong). After each declared target the user picks a new target and "
         "the learner restarts its likelihoods (all tasks equal)."),
        ("belief", belief_figure(recording, metrics), belief_caption + (
         " Circle: the agent; star: the user's true target; orange square: the learner's most "
         f"likely cell; white line: the last moves (at most {PATH_MOVES}) since the previous "
         "declared target, more opaque when more recent. Row 0 is at the top."
         if metrics.grid else
         f" The world has no grid layout: the {RANKED} most confident tasks, best first, by "
         "their state's name; red: the user's true target (below the others when not among "
         "them); dashed: "
         + ("the confidence a target needed at the step (the re-run's)."
            if metrics.target_requirement is not None
            else f"the configured threshold{threshold}."))),
        ("accuracy", accuracy_figure(metrics),
         f"Cross-validated ({folds_text(metrics)}) balanced accuracy of the decoder of the "
         "learner's most likely task, after each signal: against the recorded true labels "
         "(out-of-fold predictions of the re-run learner) and the learner's own estimate "
         f"(against that task's hypothesised labels). Dotted: chance ({metrics.chance:g})."),
        ("erp", erp,
         f"{erp_what[0].upper()}{erp_what[1:]}. Classes are the recorded true labels of the "
         "epochs (/truth); n per class in the legend."
         + (" Time 0 is the action onset (times from the recording's tmin and sfreq)."
            if metrics.signal == "epochs" else "")),
        ("latency", latency_figure(metrics),
         "Distribution of the learner's update time per step as recorded by the service "
         "(observe the epoch + propose the next move, ms), with its median, 90th and 99th "
         "percentiles."),
    ]
    return save_figures(items, out_dir, stem)


@paper_figure
def calibration_figure(panels: Sequence[CalibrationPanel]) -> Figure:
    """Reliability diagrams, two to a row, one per panel (all steps, then each decision
    rule's), each titled for the steps it counts: per confidence bin, the fraction of steps
    whose best task was the user's target, against the diagonal of a calibrated
    confidence; bar labels give each bin's steps; the vertical line is the panel's
    threshold (none on a pooled panel of several thresholds)."""
    n_cols = min(len(panels), 2)
    n_rows = -(-len(panels) // n_cols)
    width = FIGURE_WIDTH if n_cols > 1 else FIGURE_WIDTH / 2 + 0.4
    figure = Figure(figsize=(width, 3.0 * n_rows + 0.8), layout="constrained")
    axes = figure.subplots(n_rows, n_cols, squeeze=False, sharey=True).ravel()
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    for ax, panel in zip(axes, panels, strict=False):
        filled = [b for b in panel.curve if b.steps]
        centres = [(b.low + b.high) / 2 for b in filled]
        width = panel.curve[0].high - panel.curve[0].low
        bars = ax.bar(centres, [b.fraction_right for b in filled], width=0.9 * width,
                      color="#4c72b0")
        ax.bar_label(bars, labels=[str(b.steps) for b in filled], padding=2)
        ax.plot([0, 1], [0, 1], color="black", linestyle="--", linewidth=1)
        if panel.threshold is not None:
            ax.axvline(panel.threshold, color="#c44e52", linewidth=1)
        ax.set(xlim=(0, 1), ylim=(0, 1.12),
               title=panel.title.replace(" (threshold", "\n(threshold"))
        ax.tick_params(labelleft=True)
    for index, ax in enumerate(axes[: len(panels)]):
        if index + n_cols >= len(panels):  # no panel below
            ax.set_xlabel("confidence of the best task (binned)")
        if index % n_cols == 0:
            ax.set_ylabel("fraction of steps it was\nthe user's target")
    handles = [
        Rectangle((0, 0), 1, 1, color="#4c72b0", label="fraction of the bin's steps right "
                  "(label: its steps)"),
        Line2D([], [], color="black", ls="--", lw=1, label="calibrated"),
    ]
    if any(p.threshold is not None for p in panels):
        handles.append(Line2D([], [], color="#c44e52", lw=1, label="the rule's threshold"))
    figure.legend(handles=handles, loc="outside lower center", ncol=len(handles),
                  frameon=False)
    figure.suptitle("Confidence calibration"
                    + (", all steps and per decision rule" if len(panels) > 1 else ""))
    return figure


def save_figures(
    items: list[tuple[str, Figure, str]], out_dir: Path, stem: str
) -> list[SavedFigure]:
    """Write each ``(kind, figure, caption)`` as ``out_dir/<stem>_<kind>.png``, in order."""
    saved = []
    for kind, figure, caption in items:
        path = out_dir / f"{stem}_{kind}.png"
        figure.savefig(path, dpi=DPI)
        title = figure.get_suptitle() or figure.axes[0].get_title()
        title = "; ".join(" ".join(line.split()) for line in title.splitlines())
        saved.append(SavedFigure(kind, path, title, caption))
    return saved
