"""``cfbci bench latency``: end-to-end latency of the live pipeline, the learner's share,
and the queueing delay when one service runs many sessions.

The service runs in its own spawned process, the replay sources in this one (one thread
each, sharing one Zenoh session); they talk over Zenoh on a loopback TCP endpoint
(multicast off). Each of ``sessions`` sessions has ``steps + 1`` epochs on an N x N grid
(default 5 x 5, T = 25 tasks; synthetic raw epochs, feedback frame, default learner, its
own seed). Each source answers a move after ``interval`` seconds (its user's reaction; 0:
as fast as it can). Once the service is up, each source starts after a random phase in
``[0, interval)`` (drawn from ``seed``), so that the sessions are paced independently
rather than in lock step; in a **burst** run every source starts at once instead, so that
all first epochs arrive together. Per epoch k of a session (all but the last):

* **end to end**: from the epoch of step k published by the source to the move of step
  k + 1 taken off the source's subscriber (`SourceSummary.latency_ns`, the source's
  monotonic clock);
* **update**: the learner's own time inside the service, ``observe`` of epoch k plus
  ``propose`` of move k + 1 (`cfbci.service._Session.update_ns`), sent back to this
  process through a pipe when the session ends (the wire protocol has no field for it);
* **queue**: from the epoch's arrival at the service (its pump) to the start of its
  computation (`cfbci.service._Session.queued_ms`): the time it waited behind other
  sessions' messages in the service's single worker;
* **transport + rest**: end to end minus update: encoding, Zenoh both ways, decoding,
  checks, feature extraction, the ``state`` and its balanced accuracy, recording (none
  here), queueing.

The figures pool every session's epochs; each session's own are reported too, and the
worst session (highest end-to-end p99) is named.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import zenoh
from rich.console import Console
from rich.table import Table

from acquisition.simulated_source import SourceSettings, SourceSummary, replay_session
from cfbci.service import serve
from cfbci.service.limits import ServiceLimits
from wire import protocol
from wire.transport import reliable_publisher, wait_for_subscribers
from wire.zenoh_config import free_tcp_endpoint, peer_config

#: Default grid side of the benchmark (T = GRID ** 2 tasks).
GRID = 5
#: Seconds each source waits before answering a move when several sessions run and no
#: interval is given.
SESSIONS_INTERVAL = 0.5
#: Seconds any one wait may take before the benchmark gives up (a failure guard).
TIMEOUT = 60.0
_SESSION = "latency"
#: Epochs at the start of every session left out of the steady-state figures (the first
#: epoch fits the feature extractor, the first moves fill the learner's tables).
WARMUP = 5


def default_interval(sessions: int) -> float:
    """The pacing when none is given: as fast as possible for one session, else
    `SESSIONS_INTERVAL`."""
    return 0.0 if sessions == 1 else SESSIONS_INTERVAL


def _service(listen: Sequence[str], results: Connection, sessions: int, grid: int) -> None:
    """The service process, allowed at least ``sessions`` sessions at once on a
    ``grid`` x ``grid`` world: sends ``(session, update_ns, queued_ms)`` on ``results`` per
    ended session."""
    defaults = ServiceLimits()
    limits = replace(
        defaults,
        max_sessions=max(defaults.max_sessions, sessions),
        max_grid=max(defaults.max_grid, grid),
    )
    serve(listen, (), None, on_end=lambda *timings: results.send(timings), limits=limits)


def _wait_for_service(session: zenoh.Session) -> None:
    """Return once the service's config subscriber is discovered."""
    publisher = reliable_publisher(session, protocol.key(_SESSION, "config"))
    try:
        if not wait_for_subscribers(publisher, TIMEOUT):
            raise TimeoutError(f"the service did not subscribe to configs within {TIMEOUT} s")
    finally:
        publisher.undeclare()


def _collect_reports(receiver: Connection, sessions: int) -> dict[str, tuple[Any, Any]]:
    """``{session: (update_ns, queued_ms)}`` of ``sessions`` sessions, as the service sends
    them (right after each session_ended)."""
    reports = {}
    for _ in range(sessions):
        if not receiver.poll(TIMEOUT * sessions):  # a report waits for its whole session
            raise TimeoutError("the service did not report a session's timings")
        reported, update_ns, queued_ms = receiver.recv()
        reports[reported] = (update_ns, queued_ms)
    return reports


def _stats_ms(values_ns: np.ndarray) -> dict[str, float]:
    """Median, 99th percentile and maximum of durations in ns, as ms."""
    return {
        "median": float(np.median(values_ns)) / 1e6,
        "p99": float(np.percentile(values_ns, 99)) / 1e6,
        "max": float(np.max(values_ns)) / 1e6,
    }


def _timings(
    end_to_end_ns: np.ndarray, update_ns: np.ndarray, queue_ms: np.ndarray
) -> dict[str, dict[str, float]]:
    """``end_to_end_ms``, ``update_ms``, ``queue_ms`` and ``transport_ms`` (each
    ``{"median", "p99", "max"}`` in ms) of a set of epochs: durations in ns, queueing in
    ms, arrays of the same length."""
    return {
        "end_to_end_ms": _stats_ms(end_to_end_ns),
        "update_ms": _stats_ms(update_ns),
        "queue_ms": _stats_ms(queue_ms * 1e6),
        "transport_ms": _stats_ms(end_to_end_ns - update_ns),
    }


def bench_latency(
    steps: int,
    seed: int = 0,
    sessions: int = 1,
    interval: float | None = None,
    grid: int = GRID,
    burst: bool = False,
) -> dict[str, Any]:
    """Run the benchmark sessions and summarise their measured epochs.

    Parameters
    ----------
    steps : int
        Measured epochs per session (>= 1); a session has ``steps + 1`` (the last epoch
        has no move).
    seed : int
        Seed of the first session; session i has seed ``seed + i``. Also the phases' seed.
    sessions : int
        Concurrent sessions on the one service (>= 1).
    interval : float or None
        Seconds each source waits before answering a move (>= 0); None:
        `default_interval`.
    grid : int
        Grid side (>= 2).
    burst : bool
        Every source starts at once (phases 0) instead of after a random phase.

    Returns
    -------
    dict
        ``{"steps", "sessions", "interval_s", "grid", "tasks", "burst", "end_to_end_ms",
        "update_ms", "queue_ms", "transport_ms", "steady_end_to_end_ms",
        "non_learner_share", "worst_session", "per_session"}``; each ``*_ms`` is
        ``{"median", "p99", "max"}`` in ms over all sessions' epochs (``steady_*``: without
        each session's first `WARMUP` epochs; None when ``steps <= WARMUP``);
        ``non_learner_share`` is the total transport + rest time over the total end-to-end
        time, in [0, 1]; ``per_session`` lists ``{"session", "seed", "phase_s"}`` and the
        four timings of each session; ``worst_session`` is the id of the one with the
        highest end-to-end p99.

    Raises
    ------
    TimeoutError
        If the service does not answer or report within `TIMEOUT` seconds.
    """
    if steps < 1:
        raise ValueError(f"--steps must be at least 1; got {steps}")
    if sessions < 1:
        raise ValueError(f"--sessions must be at least 1; got {sessions}")
    if grid < 2:
        raise ValueError(f"--grid must be at least 2; got {grid}")
    interval = default_interval(sessions) if interval is None else interval
    if interval < 0:
        raise ValueError(f"--interval must be >= 0 s; got {interval}")
    phases = (
        np.zeros(sessions) if burst
        else np.random.default_rng(seed).uniform(0.0, interval, sessions)
    )
    ids = [_SESSION if sessions == 1 else f"{_SESSION}-{i}" for i in range(sessions)]
    summaries, reports = _run_sessions(ids, steps, seed, interval, grid, phases)
    per_session, pooled, steady = [], [], []
    for i, (sid, summary) in enumerate(zip(ids, summaries, strict=True)):
        update_ns, queued_ms = reports.get(sid, ([], []))
        if not len(summary.latency_ns) == len(update_ns) == len(queued_ms) == steps:
            raise RuntimeError(
                f"expected {steps} timings of session {sid!r}; got {len(summary.latency_ns)} "
                f"end-to-end, {len(update_ns)} update and {len(queued_ms)} queueing timings"
            )
        epochs = (
            np.asarray(summary.latency_ns, dtype=np.float64),
            np.asarray(update_ns, dtype=np.float64),
            np.asarray(queued_ms, dtype=np.float64),
        )
        pooled.append(epochs)
        steady.append(epochs[0][WARMUP:])
        per_session.append(
            {"session": sid, "seed": seed + i, "phase_s": float(phases[i]), **_timings(*epochs)}
        )
    end_to_end, update, queue = (np.concatenate(column) for column in zip(*pooled, strict=True))
    steady_ns = np.concatenate(steady)
    worst = max(per_session, key=lambda row: row["end_to_end_ms"]["p99"])
    return {
        "steps": steps,
        "sessions": sessions,
        "interval_s": interval,
        "grid": grid,
        "tasks": grid * grid,
        "burst": burst,
        **_timings(end_to_end, update, queue),
        "steady_end_to_end_ms": _stats_ms(steady_ns) if len(steady_ns) else None,
        "non_learner_share": float((end_to_end - update).sum() / end_to_end.sum()),
        "worst_session": worst["session"],
        "per_session": per_session,
    }


def _run_sessions(
    ids: list[str], steps: int, seed: int, interval: float, grid: int, phases: np.ndarray
) -> tuple[list[SourceSummary], dict[str, tuple[Any, Any]]]:
    """Run the sessions against a fresh service process: the sources' summaries, and the
    service's ``{session: (update_ns, queued_ms)}``."""
    context = multiprocessing.get_context("spawn")
    endpoint = free_tcp_endpoint()
    receiver, sender = context.Pipe(duplex=False)
    service = context.Process(
        target=_service, args=([endpoint], sender, len(ids), grid),
        name="cfbci-latency-service",
    )
    service.start()
    try:
        with zenoh.open(peer_config((), [endpoint])) as session, ThreadPoolExecutor(
            len(ids) + 1
        ) as pool:
            # Read the reports as they come: the service blocks once the pipe is full.
            collected = pool.submit(_collect_reports, receiver, len(ids))
            _wait_for_service(session)  # else every source waits for it, and starts with it

            def run(i: int) -> SourceSummary:
                time.sleep(phases[i])  # the session's phase
                return replay_session(session, SourceSettings(
                    ids[i], seed=seed + i, steps=steps + 1, grid=grid, timeout=TIMEOUT,
                    interval=interval,
                ))

            summaries = list(pool.map(run, range(len(ids))))
            return summaries, collected.result()
    finally:
        service.terminate()
        service.join(TIMEOUT)
        if service.is_alive():
            service.kill()
            service.join()


def print_latency(report: dict[str, Any], console: Console) -> None:
    """The report as a table (ms): pooled epochs, steady state and the worst session; the
    non-learner share of the end-to-end time."""
    pacing = "all starting at once" if report["burst"] else "random phases"
    table = Table(
        title=f"bench latency: {report['sessions']} session(s) x {report['steps']} epochs, "
        f"T = {report['tasks']}, answers after {report['interval_s']:g} s"
        + (f", {pacing}" if report["sessions"] > 1 else "")
    )
    for column in ("ms", "median", "p99", "max"):
        table.add_column(column, justify="right")
    worst = next(r for r in report["per_session"] if r["session"] == report["worst_session"])
    rows = [
        ("end to end", report["end_to_end_ms"]),
        ("learner update", report["update_ms"]),
        ("queueing", report["queue_ms"]),
        ("transport + rest", report["transport_ms"]),
        (f"end to end after {WARMUP} epochs", report["steady_end_to_end_ms"]),
    ]
    if report["sessions"] > 1:
        rows.append((f"end to end, worst session ({worst['session']})", worst["end_to_end_ms"]))
    for name, timing in rows:
        if timing is not None:
            table.add_row(name, *(f"{timing[stat]:.3f}" for stat in ("median", "p99", "max")))
    console.print(table)
    console.print(
        f"non-learner share of the end-to-end time: {report['non_learner_share']:.1%} "
        "(total transport + rest over total end to end)"
    )
