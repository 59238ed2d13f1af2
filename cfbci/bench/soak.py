"""``cfbci bench soak``: a service left running, over one long session and many short ones.

Each part gets a fresh service, spawned in its own process as ``cfbci serve`` runs it
(recording on, to a temporary directory unless ``--record-dir``), with this process as the
source over Zenoh on a loopback TCP endpoint (multicast off): the service's resident memory
is then its own, not mixed with the source's, and every part of the service (transport,
learner, recorder) is exercised. Synthetic raw epochs, 5 x 5 grid (T = 25), feedback frame,
default learner, as fast as the service answers (no reaction time).

* **Long session** (``--steps``, default 10,000): after every step's move and state have
  arrived, the service's resident set size (``VmRSS`` of ``/proc/<pid>/status``, Linux) is
  read; per step also the end-to-end time (epoch of step k published to the move of step
  k + 1 received, the source's clock) and the learner's update inside the service
  (`cfbci.service._Session.update_ns`, sent back through a pipe at the end). A row
  per ``--every`` steps is printed as the session runs; the table at the end gives, per
  window, the RSS and its growth, the median and 99th percentile of both times, and a
  speed reference taken at the window's end while the service waits: the median of 30
  steps of the same learner run offline in this process at a short history (50 to 350
  signals). The machine's load moves every time; the learner's update over the reference
  is what grows with the history.
  *Growth*: least-squares slopes of RSS (KB per step) and of the per-step times (ms per
  1,000 steps) over the first and the second half of the session after its first window
  (warm-up): for growth that is at most linear in the history, the second half's RSS slope
  is no larger than the first's. Beside it, what the history itself takes, measured in
  this process with ``tracemalloc``: the memory the MCAP writer keeps per message until the
  file is closed (its chunk indexes) times the recording's messages per step, and the
  memory per step of the service's learner for the same config run offline (steps 40 to
  200, random feature vectors of the recording's size), both what it keeps and its peak
  within a step (a step's temporaries grow with the history too, and RSS holds the peak).
  Each part records to its own directory: a service starting on a directory reads the
  recordings there (to resume unfinished sessions).
* **Short sessions** (``--sessions``, default 200, of ``--session-steps`` steps each, one
  after the other, distinct ids): the RSS before the first, after each. The growth from
  the end of the first session to the end of the last, per session, is what a leak would
  show (with glibc, `cfbci.memory.keep_freed_memory` keeps freed memory in the heap,
  so RSS holds the peak: memory a session freed is reused by the next, and does not make
  the curve go down and up).
"""

from __future__ import annotations

import json
import resource
import tempfile
import time
import tracemalloc
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from mcap.reader import make_reader
from rich.console import Console

from acquisition.simulated_source import SourceSettings, replay_session
from calibration_free.learner import CalibrationFreeLearner
from calibration_free.streams import StepRecord
from calibration_free.world import GridWorld
from cfbci.service import serve
from cfbci.service.process import SPAWN, spawned
from replay.recording import SessionRecorder, decode_array, read_recording
from session.config import learner_settings
from session.tasks import TaskSession
from wire.zenoh_config import free_tcp_endpoint, peer_config

#: Grid side of the soak sessions (T = GRID ** 2 tasks).
GRID = 5
#: Seconds any one wait may take before the soak gives up (a failure guard).
TIMEOUT = 60.0
_MB = 2**20
_LONG = "soak-long"


def _service(listen: Sequence[str], record_dir: Path, results: Connection) -> None:
    """The service process: sends ``(session, update_ns)`` on ``results`` per ended session."""
    serve(listen, (), record_dir,
          on_end=lambda session, update_ns, _queued_ms: results.send((session, update_ns)))


def rss_bytes(pid: int) -> int:
    """Resident set size of a process, bytes (``VmRSS`` in ``/proc/<pid>/status``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"/proc/{pid}/status has no VmRSS line")


@dataclass
class _Service:
    """A running service process, the Zenoh session that reaches it, and its reports."""

    pid: int
    session: zenoh.Session
    results: Connection

    def update_ns(self, session: str) -> list[int]:
        """The learner's per-epoch times of an ended session (see `cfbci.bench.latency`)."""
        if not self.results.poll(TIMEOUT):
            raise TimeoutError(f"the service did not report session {session!r} in {TIMEOUT} s")
        reported, update_ns = self.results.recv()
        if reported != session:
            raise RuntimeError(f"expected the timings of session {session!r}, got {reported!r}")
        return update_ns


@contextmanager
def _running_service(record_dir: Path) -> Iterator[_Service]:
    """A fresh service in a spawned process (`cfbci.service.process.spawned`)."""
    endpoint = free_tcp_endpoint()
    receiver, sender = SPAWN.Pipe(duplex=False)
    with spawned(_service, [endpoint], record_dir, sender, name="cfbci-soak-service") as process:
        assert process.pid is not None
        with zenoh.open(peer_config((), [endpoint])) as session:
            yield _Service(process.pid, session, receiver)


def _settings(session: str, steps: int, seed: int) -> SourceSettings:
    return SourceSettings(session, seed=seed, steps=steps, grid=GRID, timeout=TIMEOUT)


def _slope(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of y against x."""
    return float(np.polyfit(x, y, 1)[0])


def _window_row(
    end: int, every: int, rss: np.ndarray, end_to_end: np.ndarray, update: np.ndarray
) -> dict[str, float]:
    """Figures of steps ``end - every + 1 .. end`` (1-based; times of epochs in the window)."""
    window = slice(end - every, end)
    e2e, upd = end_to_end[window], update[window]
    start_rss = rss[end - every - 1] if end > every else rss[0]
    return {
        "step": end,
        "rss_mb": float(rss[end - 1]) / _MB,
        "rss_growth_mb": float(rss[end - 1] - start_rss) / _MB,
        "end_to_end_median_ms": float(np.median(e2e)) / 1e6,
        "end_to_end_p99_ms": float(np.percentile(e2e, 99)) / 1e6,
        "update_median_ms": float(np.median(upd)) / 1e6,
        "update_p99_ms": float(np.percentile(upd, 99)) / 1e6,
    }


def _growth(rss: np.ndarray, end_to_end: np.ndarray, update: np.ndarray, every: int) -> dict:
    """Slopes over the first and second half of the steps after the first window."""
    steps = len(rss)
    start = min(every, steps // 2)
    middle = (start + steps) // 2
    halves = {"first": (start, middle), "second": (middle, steps - 1)}
    growth: dict[str, Any] = {"halves": {k: [a + 1, b + 1] for k, (a, b) in halves.items()}}
    for name, values, scale in (
        ("rss_kb_per_step", rss, 1 / 1024),
        ("end_to_end_ms_per_1000_steps", end_to_end, 1000 / 1e6),
        ("update_ms_per_1000_steps", update, 1000 / 1e6),
    ):
        growth[name] = {
            half: _slope(np.arange(a, b), values[a:b]) * scale for half, (a, b) in halves.items()
        }
    return growth


def _recorder_bytes_per_message(n_messages: int = 3000) -> float:
    """Python memory a recorder holds per message until it is closed, bytes (tracemalloc)."""
    header = {"seq": 0, "t_ns": 0, "step": 1, "action": "up", "update_ms": 1.0}
    with tempfile.TemporaryDirectory() as directory:
        with SessionRecorder(Path(directory) / "probe.mcap", "probe", {}) as recorder:
            tracemalloc.start()
            try:
                before = tracemalloc.get_traced_memory()[0]
                for seq in range(n_messages):
                    recorder.record("/move", {**header, "seq": seq}, seq)
                after = tracemalloc.get_traced_memory()[0]
            finally:
                tracemalloc.stop()
    return (after - before) / n_messages


def _recording_figures(path: Path, steps: int) -> tuple[float, int]:
    """Messages per step of a closed recording (its statistics), and its feature size."""
    with path.open("rb") as file:
        reader = make_reader(file)
        summary = reader.get_summary()
        if summary is None or summary.statistics is None:
            raise RuntimeError(f"{path}: the recording was not closed")
        _, _, message = next(reader.iter_messages(topics=["/features"]))
    [n_features] = json.loads(message.data)["shape"]
    return summary.statistics.message_count / steps, n_features


class _OfflineSession:
    """The service's session for the soak's config, stepped in this process on random
    feature vectors from cell 0: the reference for the memory a step of history takes and
    for the machine's speed at the moment (what the learner keeps, and its cost at a short
    history, do not depend on the values).

    Parameters
    ----------
    n_features : int
        Length of the feature vectors.
    steps : int
        Steps it will be asked for (`step`).
    """

    def __init__(self, n_features: int, steps: int) -> None:
        world = GridWorld(GRID)
        settings = learner_settings({}, "feedback")
        learner = CalibrationFreeLearner(world, settings, np.random.default_rng(0))
        # One more step than signals: the last signal's next action is chosen too.
        self.session = TaskSession(world, learner, 0, steps + 1, start=0)
        self.session.start()
        self.n_features = n_features
        self._rng = np.random.default_rng(1)

    def step(self) -> int:
        """One update (a signal observed and the next action chosen, as a service's step);
        its time, ns."""
        signal = self._rng.normal(size=self.n_features).astype(np.float32)
        started = time.perf_counter_ns()
        self.session.observe(signal)
        return time.perf_counter_ns() - started


def _learner_bytes_per_step(
    n_features: int, steps: int = 200, warmup: int = 40
) -> tuple[float, float]:
    """Python memory the learner's history takes per step, bytes (tracemalloc, from step
    ``warmup`` to step ``steps`` of an `_OfflineSession`): what it keeps between
    steps, and its peak within a step (what it keeps plus the step's temporaries, which
    also grow with the history; with freed memory kept in the heap, RSS follows the peak).
    """
    offline = _OfflineSession(n_features, steps)
    for _ in range(warmup - 1):
        offline.step()
    tracemalloc.start()
    try:
        kept_before, peak_before = _traced_step(offline)
        for _ in range(steps - warmup - 1):
            offline.step()
        kept_after, peak_after = _traced_step(offline)
    finally:
        tracemalloc.stop()
    n = steps - warmup
    return (kept_after - kept_before) / n, (peak_after - peak_before) / n


def _traced_step(offline: _OfflineSession) -> tuple[int, int]:
    """One step under tracemalloc: bytes traced after it, and their peak during it."""
    tracemalloc.reset_peak()
    offline.step()
    return tracemalloc.get_traced_memory()


class _SpeedReference:
    """Median time of 30 offline learner steps at a short history (50 to 350 signals
    over a 10,000-step soak), taken at every window of the long session while the service
    waits: how fast the machine is then, so that growth can be told from load.

    Parameters
    ----------
    recording : Path
        The long session's recording (its feature size).
    windows : int
        Windows of the long session (calls of `measure_ms`).
    warmup, steps : int
        Offline steps before the first window, and per window.
    """

    def __init__(self, recording: Path, windows: int, warmup: int = 50, steps: int = 30) -> None:
        self._recording, self._windows = recording, windows
        self._warmup, self._steps = warmup, steps
        self._offline: _OfflineSession | None = None

    def measure_ms(self) -> float:
        if self._offline is None:  # the feature size, from the recording so far
            features = read_recording(self._recording).messages["/features"][0][1]
            self._offline = _OfflineSession(
                decode_array(features).size, self._warmup + self._windows * self._steps
            )
            for _ in range(self._warmup):
                self._offline.step()
        offline = self._offline
        return float(np.median([offline.step() for _ in range(self._steps)])) / 1e6


def soak_long(
    steps: int, seed: int, every: int, record_dir: Path, console: Console
) -> dict[str, Any]:
    """Run the long session; return its per-step series, its windows and its growth.

    Parameters
    ----------
    steps : int
        Steps of the session (>= 2 * every).
    seed : int
    every : int
        Steps per window (a printed row).
    record_dir : Path
        Where the service records.
    console : Console
        Where the rows go as the session runs.

    Returns
    -------
    dict
        ``{"steps", "every", "seconds", "rss_idle_mb", "rss_mb": [steps], "end_to_end_ms":
        [steps - 1], "update_ms": [steps - 1], "windows": [...], "growth": {...},
        "recorder": {...}, "learner": {...}}`` (memory in MB, times in ms).
    """
    rss: list[int] = []
    reference_ms: list[float] = []
    reference = _SpeedReference(record_dir / f"{_LONG}.mcap", steps // every)
    started = time.perf_counter()

    with _running_service(record_dir) as service:

        def on_step(record: StepRecord) -> None:
            rss.append(rss_bytes(service.pid))
            if record.step % every == 0:
                reference_ms.append(reference.measure_ms())
                console.print(
                    f"step {record.step:>6}: service RSS {rss[-1] / _MB:7.1f} MB "
                    f"({(rss[-1] - rss[max(0, record.step - every - 1)]) / _MB:+.1f} MB over "
                    f"the last {every} steps), {time.perf_counter() - started:6.0f} s",
                    soft_wrap=True,
                )

        idle = rss_bytes(service.pid)
        summary = replay_session(service.session, _settings(_LONG, steps, seed), on_step)
        update_ns = service.update_ns(_LONG)
    rss_array = np.asarray(rss, dtype=np.float64)
    end_to_end = np.asarray(summary.latency_ns, dtype=np.float64)
    update = np.asarray(update_ns, dtype=np.float64)
    if not len(rss_array) == steps == len(end_to_end) + 1 == len(update) + 1:
        raise RuntimeError(
            f"expected {steps} steps; got {len(rss_array)} RSS samples, {len(end_to_end)} "
            f"end-to-end and {len(update)} update times"
        )
    windows = [
        {**_window_row(end, every, rss_array, end_to_end, update), "reference_ms": ms}
        for end, ms in zip(range(every, steps + 1, every), reference_ms, strict=True)
    ]
    per_message = _recorder_bytes_per_message()
    per_step, n_features = _recording_figures(record_dir / f"{_LONG}.mcap", steps)
    learner_kept, learner_peak = _learner_bytes_per_step(n_features)
    return {
        "steps": steps,
        "every": every,
        "seconds": time.perf_counter() - started,
        "rss_idle_mb": idle / _MB,
        "rss_mb": (rss_array / _MB).tolist(),
        "end_to_end_ms": (end_to_end / 1e6).tolist(),
        "update_ms": (update / 1e6).tolist(),
        "windows": windows,
        "growth": _growth(rss_array, end_to_end, update, every),
        "recorder": {
            "bytes_per_message": per_message,
            "messages_per_step": per_step,
            "kb_per_step": per_message * per_step / 1024,
        },
        "learner": {
            "n_features": n_features,
            "kb_per_step": learner_kept / 1024,
            "peak_kb_per_step": learner_peak / 1024,
        },
    }


def soak_short(sessions: int, steps: int, seed: int, record_dir: Path) -> dict[str, Any]:
    """Run ``sessions`` sessions of ``steps`` steps one after the other in one service.

    Returns
    -------
    dict
        ``{"sessions", "steps", "rss_before_mb", "rss_mb": [sessions] (after each),
        "growth_mb" (after the last minus after the first), "per_session_kb"}``, where
        ``per_session_kb`` is the median of the growths from one session to the next: a
        leak grows the service at every session (a kept learner of 10 steps: about 1.1 MB
        each), a one-off allocation (a thread's arena, a transport buffer) at one only.
    """
    rss: list[int] = []
    with _running_service(record_dir) as service:
        before = rss_bytes(service.pid)
        for i in range(sessions):
            name = f"soak-short-{i:04d}"
            replay_session(service.session, _settings(name, steps, seed + i))
            service.update_ns(name)  # the session has ended in the service
            rss.append(rss_bytes(service.pid))
    growth = rss[-1] - rss[0]
    return {
        "sessions": sessions,
        "steps": steps,
        "rss_before_mb": before / _MB,
        "rss_mb": [value / _MB for value in rss],
        "growth_mb": growth / _MB,
        "per_session_kb": float(np.median(np.diff(rss))) / 1024 if sessions > 1 else 0.0,
    }


def bench_soak(
    steps: int = 10_000,
    sessions: int = 200,
    session_steps: int = 20,
    seed: int = 0,
    every: int = 1000,
    record_dir: Path | None = None,
    console: Console | None = None,
) -> dict[str, Any]:
    """The long session, then the short sessions, each in a fresh service.

    Parameters
    ----------
    steps : int
        Steps of the long session (>= 2 * every).
    sessions : int
        Short sessions (>= 2).
    session_steps : int
        Steps of each short session (>= 1).
    seed : int
        Seed of the long session and of the first short one (the others count up).
    every : int
        Steps per window of the long session.
    record_dir : Path or None
        Where the services record; None: a temporary directory, removed afterwards.
    console : Console or None
        Progress output.

    Returns
    -------
    dict
        ``{"grid", "long": soak_long(...), "short": soak_short(...), "bench_peak_rss_mb"}``.
    """
    if every < 1 or steps < 2 * every:
        raise ValueError(f"--steps ({steps}) must be at least twice --every ({every})")
    if sessions < 2 or session_steps < 1:
        raise ValueError(
            f"--sessions must be at least 2 and --session-steps at least 1; got {sessions} "
            f"and {session_steps}"
        )
    console = console or Console()
    with tempfile.TemporaryDirectory(prefix="cfbci-soak-") as temporary:
        # One directory per part: a service starting on a directory reads its recordings
        # (to resume unfinished sessions), which would charge the long one to the short ones.
        base = record_dir or Path(temporary)
        long_dir, short_dir = base / "long", base / "short"
        for directory in (long_dir, short_dir):
            directory.mkdir(parents=True, exist_ok=True)
        console.print(f"long session: {steps} steps, T = {GRID * GRID}, recording to {long_dir}")
        long = soak_long(steps, seed, every, long_dir, console)
        console.print(f"{sessions} short sessions of {session_steps} steps, recording to "
                      f"{short_dir}")
        short = soak_short(sessions, session_steps, seed, short_dir)
    return {
        "grid": GRID,
        "long": long,
        "short": short,
        "bench_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


