"""``cfbci session``: a live session on an embedded loopback Zenoh network.

The service and the replay source run as separate processes (``spawn``), Zenoh peers on
loopback TCP endpoints, multicast scouting off. This process, the display, listens on its
own endpoint; the service listens on its own and connects to the display's; the source
connects to both. The display shows the session as it goes
(the session's moves, states, events and truth; not its config, whose only subscriber
must be the service: the source waits for a subscriber to it before sending it): a grid
world as a text grid, another world as the agent's state and a ranked list of tasks, the
continuous world as its probe and best particle, the puddle world as the agent's point,
the most likely task and the taught task's likelihood.

The service runs this one session of the user's own on a private loopback network, so its
memory limit (``max_session_mb``, which guards a shared service against its clients) is the
machine's physical memory.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import queue
import re
import shutil
import tempfile
import time
from collections.abc import Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from acquisition.simulated_source import SourceSettings, SourceSummary, run_source
from calibration_free.puddle import puddle_tasks
from calibration_free.world import GridWorld, World
from cfbci.outputs import place, refuse_existing
from cfbci.service import serve
from cfbci.service.limits import ServiceLimits
from session.plane import PLANE_FRAMES
from wire import protocol
from wire.protocol import ProtocolError
from wire.transport import Pump, Received
from wire.zenoh_config import free_tcp_endpoint, peer_config

#: Seconds the service may take to shut down (close its recordings) after SIGTERM.
SHUTDOWN_TIMEOUT = 30.0
#: Seconds between two refreshes of the display when nothing arrives.
REFRESH = 0.1
_SHADES = " .:-=+*#"
#: Tasks listed by the display of a world without a grid layout.
LISTED = 5


def session_id_for(path: Path) -> str:
    """A valid session id from a recording's file name (its stem, other characters -> '-')."""
    return re.sub(r"[^A-Za-z0-9_-]", "-", path.stem)[:64] or "session"


@dataclass
class Progress:
    """What the display knows of the session so far.

    Attributes
    ----------
    world : World
    steps : int
    step : int
        Step of the latest move.
    agent : int
        The agent's state after the latest move.
    confidence : ndarray, shape (n_tasks,)
        Latest confidence of every task.
    best_task : int
    confident : bool
    correct, wrong : int
        Declared targets that were (not) the user's target (from the truth).
    target : int or None
        The user's target task in the latest truth.
    """

    world: World
    steps: int
    step: int = 0
    agent: int = 0
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    best_task: int = 0
    confident: bool = False
    correct: int = 0
    wrong: int = 0
    target: int | None = None
    _declared: dict[int, int] = field(default_factory=dict)  # step -> declared cell
    _targets: dict[int, int] = field(default_factory=dict)  # step -> the user's target

    def update(self, message: protocol.Message) -> None:
        """Take in one message of the session (moves and truths in any relative order)."""
        fields = message.fields
        if message.kind == "move":
            self.step, self.agent = fields["step"], fields["to_state"]
            if fields["target_reached"]:
                self._declared[fields["step"]] = fields["from_state"]
        elif message.kind == "state":
            assert message.payload is not None
            self.confidence = message.payload
            self.best_task, self.confident = fields["best_task"], fields["confident"]
        elif message.kind == "truth":
            self.target = fields["target"]
            self._targets[fields["step"]] = fields["target"]
        for step in [step for step in self._declared if step in self._targets]:
            correct = self._declared.pop(step) == self.world.task_states[self._targets[step]]
            self.correct += correct
            self.wrong += not correct
        self._targets = {step: t for step, t in self._targets.items() if step >= self.step}

    def render(self) -> Group:
        """Step, score and the world (`_grid_rows` or `_ranked_rows`)."""
        best = float(self.confidence[self.best_task]) if len(self.confidence) else 0.0
        head = Text(
            f"step {self.step}/{self.steps}   targets correct {self.correct} wrong "
            f"{self.wrong}   best task {self.best_task} confidence {best:.3f}"
            f"{' (confident)' if self.confident else ''}"
        )
        if isinstance(self.world, GridWorld):
            return Group(head, *self._grid_rows(self.world.size))
        return Group(head, *self._ranked_rows())

    def _ranked_rows(self) -> list[Text]:
        """The agent's state, then the `LISTED` most confident tasks (``T``: the
        user's target), best first."""
        world = self.world
        rows = [Text(f"agent: {world.state_name(self.agent)}")]
        for task in np.argsort(-self.confidence, kind="stable")[:LISTED]:
            mark = "T" if task == self.target else " "
            style = "bold green" if task == self.best_task else ""
            rows.append(Text(f"{mark} {float(self.confidence[task]):.3f}  "
                             f"{world.task_name(int(task))}", style=style))
        return rows

    def _grid_rows(self, side: int) -> list[Text]:
        """A text grid: ``@`` the agent, ``T`` the target, shades the belief."""
        rows = []
        for row in range(side):
            line = Text()
            for col in range(side):
                cell = row * side + col
                conf = float(self.confidence[cell]) if len(self.confidence) else 0.0
                char = _SHADES[min(int(conf * len(_SHADES)), len(_SHADES) - 1)]
                char = "@" if cell == self.agent else "T" if cell == self.target else char
                style = "bold green" if cell == self.best_task else ""
                line.append(f"[{char}]", style=style)
            rows.append(line)
        return rows


def run_live_session(
    settings: SourceSettings,
    record: Path,
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    console: Console,
    zenoh_config: Path | None = None,
    overwrite: bool = False,
    limits: ServiceLimits | None = None,
) -> dict[str, Any]:
    """Run one live session with a display; return the JSON summary.

    Parameters
    ----------
    settings : SourceSettings
        The session (its ``session`` id names the recording before it is moved to
        ``record``).
    record : Path
        The MCAP file to write.
    listen : sequence of str
        The service's listen endpoints (default: a free loopback port).
    connect : sequence of str
        Endpoints the service connects to.
    console : Console
    zenoh_config : Path or None
        Zenoh JSON5 configuration merged over the defaults, for the service, the source
        and the display alike (the endpoints stay the ones above).
    limits : ServiceLimits, optional
        The embedded service's limits (default `own_limits`).
    overwrite : bool
        Replace ``record`` if it exists (else an existing ``record`` is kept: the
        recording stays in a folder beside it and the error says where).

    The service records into a folder of its own beside ``record``, then the recording
    is moved to ``record``: nothing else in that folder is touched.

    Raises
    ------
    FileExistsError
        When ``record`` exists and ``overwrite`` is false.

    Returns
    -------
    dict
        ``{"world", "steps", "first_target_step", "correct_targets", "wrong_targets",
        "recording"}``, and in the puddle world ``"restarts"`` (epochs that said
        ``reset``). The plane worlds declare no targets: their target counts stay 0.
    """
    context = multiprocessing.get_context("spawn")
    service_endpoints = list(listen) or [free_tcp_endpoint()]
    display_endpoint = free_tcp_endpoint()
    refuse_existing(record, overwrite)
    record.parent.mkdir(parents=True, exist_ok=True)
    private = Path(tempfile.mkdtemp(prefix=".cfbci-session-", dir=record.parent))
    # The display listens before the others start, so they reach it at once and it misses
    # nothing; the source reaches the service through the service's endpoints.
    with zenoh.open(peer_config([display_endpoint], (), zenoh_config)) as session:
        service = context.Process(
            target=serve,
            args=(service_endpoints, [display_endpoint, *connect], private),
            kwargs={
                "zenoh_config": zenoh_config, "resume": False, "limits": limits or own_limits(),
            },
            name="cfbci-service",
        )
        service.start()
        try:
            with ProcessPoolExecutor(1, mp_context=context) as pool:
                future = pool.submit(
                    run_source, settings, [], [*service_endpoints, display_endpoint],
                    zenoh_config,
                )
                summary = _display(session, settings, future, console)
        finally:
            service.terminate()  # SIGTERM: the service closes its recordings and exits
            service.join(SHUTDOWN_TIMEOUT)
            if service.is_alive():
                service.kill()
                service.join()
    _move_recording(private / f"{settings.session}.mcap", record, overwrite)
    shutil.rmtree(private / "priors", ignore_errors=True)  # the prior store of --prior
    private.rmdir()
    result = {
        "world": settings.world,
        "steps": summary.steps,
        "first_target_step": summary.first_target_step,
        "correct_targets": summary.correct_targets,
        "wrong_targets": summary.wrong_targets,
        "recording": str(record),
    }
    if settings.world == "puddle":
        result["restarts"] = sum(r.event == "reset" for r in summary.records)
    return result


def _move_recording(written: Path, record: Path, overwrite: bool) -> None:
    """Move the service's recording to ``record`` (see `cfbci.outputs.place`); kept where
    it is if ``record`` appeared during the session."""
    try:
        place(written, record, overwrite)
    except FileExistsError:
        raise FileExistsError(
            f"{record} appeared during the session; the recording is kept as {written}"
        ) from None


@dataclass
class PlaneProgress:
    """What the display knows of a continuous-world session: the latest probe, the best
    particle and the user's goal (from the truth).

    Attributes
    ----------
    steps, step : int
    probe : list of float
        The latest probe point.
    best : list of float
        The best particle after the latest epoch.
    confidence : float
        Its confidence.
    goal : list of float or None
    """

    steps: int
    step: int = 0
    probe: list[float] = field(default_factory=lambda: [0.0, 0.0])
    best: list[float] = field(default_factory=lambda: [0.0, 0.0])
    confidence: float = 0.0
    goal: list[float] | None = None

    def update(self, message: protocol.Message) -> None:
        """Take in one message of the session."""
        fields = message.fields
        if message.kind == "move":
            self.step, self.probe = fields["step"], fields["to_state"]
        elif message.kind == "state" and fields["points"]:
            assert message.payload is not None
            self.best = fields["points"][fields["best_task"]]
            self.confidence = float(message.payload[fields["best_task"]])
        elif message.kind == "truth":
            self.goal = fields["target"]

    def render(self) -> Group:
        """Step, probe, best particle and its distance to the goal."""
        distance = "-" if self.goal is None else (
            f"{float(np.linalg.norm(np.subtract(self.best, self.goal))):.4f}")
        return Group(
            Text(f"step {self.step}/{self.steps}   probe ({self.probe[0]:.3f}, "
                 f"{self.probe[1]:.3f})"),
            Text(f"best particle ({self.best[0]:.3f}, {self.best[1]:.3f}) confidence "
                 f"{self.confidence:.3f}   distance to the goal {distance}"),
        )


@dataclass
class PuddleProgress:
    """What the display knows of a puddle-world session: the agent's latest move, the most
    likely task and, from the truth, the taught task's normalised likelihood.

    Attributes
    ----------
    steps, step : int
    agent : list of float
        The latest move's ``to_state``.
    restarts : int
        Moves that did not start where the previous one ended (the agent restarted).
    best_task : int
    best : float
        Its normalised likelihood.
    taught : int or None
        The taught task (truth).
    confidence : ndarray
        Every task's normalised likelihood.
    """

    steps: int
    step: int = 0
    agent: list[float] = field(default_factory=lambda: [0.0, 0.0])
    restarts: int = 0
    best_task: int = 0
    best: float = 0.0
    taught: int | None = None
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def update(self, message: protocol.Message) -> None:
        """Take in one message of the session."""
        fields = message.fields
        if message.kind == "move":
            if self.step and fields["step"] == self.step + 1 and fields["from_state"] != (
                    self.agent):
                self.restarts += 1
            self.step, self.agent = fields["step"], fields["to_state"]
        elif message.kind == "state":
            assert message.payload is not None
            self.confidence = message.payload
            self.best_task = fields["best_task"]
            self.best = float(message.payload[self.best_task])
        elif message.kind == "truth":
            self.taught = fields["target"]

    def render(self) -> Group:
        """Step, the agent's point, restarts, the best and the taught task."""
        tasks = puddle_tasks()

        def name(task: int) -> str:
            return f"goal {tasks[task].goal}, puddle {list(tasks[task].puddle)}"

        taught = "-" if self.taught is None or not len(self.confidence) else (
            f"{float(self.confidence[self.taught]):.3f} ({name(self.taught)})")
        return Group(
            Text(f"step {self.step}/{self.steps}   agent ({self.agent[0]:.3f}, "
                 f"{self.agent[1]:.3f})   restarts {self.restarts}"),
            Text(f"most likely task {self.best_task} ({name(self.best_task)}) {self.best:.3f}"
                 f"   taught task {taught}"),
        )


def _display(
    session: zenoh.Session,
    settings: SourceSettings,
    future: Future[SourceSummary],
    console: Console,
) -> SourceSummary:
    """Show the session until the source is done; return its summary."""
    progress: Progress | PlaneProgress | PuddleProgress
    if settings.world == "puddle":
        progress = PuddleProgress(settings.steps)
    elif settings.world in PLANE_FRAMES:
        progress = PlaneProgress(settings.steps)
    else:
        progress = Progress(settings.make_world(), settings.steps)
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    # Not cfbci/<session>/* : a subscriber to the config would tell the source that the
    # service is listening before it is.
    pumps = [
        Pump(session, protocol.key(settings.session, kind), kind, inbox)
        for kind in ("move", "state", "event", "truth")
    ]
    try:
        with Live(progress.render(), console=console, transient=False) as live:
            while not future.done() or not inbox.empty():
                try:
                    received = inbox.get(timeout=REFRESH)
                except queue.Empty:
                    continue
                try:
                    progress.update(protocol.decode(received.data, key_expr=received.key_expr))
                except ProtocolError:
                    continue  # the service reports bad messages; the display skips them
                live.update(progress.render())
    finally:
        for pump in pumps:
            pump.close()
    return future.result()


def own_limits() -> ServiceLimits:
    """The limits of the service of ``cfbci session``: the defaults, but a session may
    commit the machine's physical memory (see the module docstring)."""
    physical_mb = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2**20
    return ServiceLimits(max_session_mb=max(ServiceLimits().max_session_mb, physical_mb))


def print_summary(result: dict[str, Any], console: Console, elapsed: float) -> None:
    """A one-table summary of a live session."""
    table = Table(title="cfbci session")
    if result.get("world") in ("continuous", "puddle"):  # no targets are declared there
        outcome = {"world": result["world"]}
        if "restarts" in result:
            outcome["restarts (goal reached)"] = str(result["restarts"])
    else:
        outcome = {
            "first target": str(result["first_target_step"] or "-"),
            "correct": str(result["correct_targets"]),
            "wrong": str(result["wrong_targets"]),
        }
    row = {"steps": str(result["steps"]), **outcome, "recording": result["recording"],
           "time": f"{elapsed:.1f} s"}
    for column in row:
        table.add_column(column)
    table.add_row(*row.values())
    console.print(table)


def write_json(result: dict[str, Any], path: Path) -> None:
    """Write the summary as JSON."""
    path.write_text(json.dumps(result, indent=2) + "\n")


def default_recording(directory: Path = Path("runs")) -> Path:
    """``runs/<YYYYmmdd-HHMMSS>.mcap``."""
    return directory / f"{time.strftime('%Y%m%d-%H%M%S')}.mcap"
