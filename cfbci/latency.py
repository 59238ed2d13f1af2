"""``cfbci bench latency``: end-to-end latency of the live pipeline, the learner's share,
and the queueing delay when one service runs many sessions.

The service runs in its own spawned process, the replay sources in this one (one thread
each, sharing one Zenoh session); they talk over Zenoh on a loopback TCP endpoint
(multicast off). Each of ``sessions`` sessions has ``steps + 1`` epochs at T = 25 tasks
(5 x 5 grid, synthetic raw epochs, feedback frame, default learner, its own seed). Each
source answers a move after ``interval`` seconds (its user's reaction; 0: as fast as it
can), and the sources start ``interval / sessions`` apart, so that the sessions are paced
independently rather than in lock step. Per epoch k of a session (all but the last):

* **end to end**: from the epoch of step k published by the source to the move of step
  k + 1 taken off the source's subscriber (:attr:`SourceSummary.latency_ns`, the source's
  monotonic clock);
* **update**: the learner's own time inside the service, ``observe`` of epoch k plus
  ``propose`` of move k + 1 (:attr:`cfbci.service._Session.update_ns`), sent back to this
  process through a pipe when the session ends (the wire protocol has no field for it);
* **queueing**: from the epoch's arrival at the service (its pump) to the start of its
  computation (:attr:`cfbci.service._Session.queued_ms`): the time it waited behind other
  sessions' messages in the service's single worker;
* **transport + rest**: end to end minus update: encoding, Zenoh both ways, decoding,
  checks, feature extraction, the ``state`` and its balanced accuracy, recording (none
  here), queueing.

The figures pool every session's epochs.
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

from acquisition.replay_source import SourceSettings, SourceSummary, replay_session
from cfbci.limits import ServiceLimits
from cfbci.service import serve
from wire.zenoh_config import free_tcp_endpoint, peer_config

#: Grid side of the benchmark (T = GRID ** 2 tasks).
GRID = 5
#: Seconds any one wait may take before the benchmark gives up (a failure guard).
TIMEOUT = 60.0
_SESSION = "latency"
#: Epochs at the start of every session left out of the steady-state figures (the first
#: epoch fits the feature extractor, the first moves fill the learner's tables).
WARMUP = 5


def _service(listen: Sequence[str], results: Connection, sessions: int) -> None:
    """The service process, allowed at least ``sessions`` sessions at once: sends
    ``(session, update_ns, queued_ms)`` on ``results`` per ended session."""
    defaults = ServiceLimits()
    limits = replace(defaults, max_sessions=max(defaults.max_sessions, sessions))
    serve(listen, (), None, on_end=lambda *timings: results.send(timings), limits=limits)


def _stats_ms(values_ns: np.ndarray) -> dict[str, float]:
    """Median, 99th percentile and maximum of durations in ns, as ms."""
    return {
        "median": float(np.median(values_ns)) / 1e6,
        "p99": float(np.percentile(values_ns, 99)) / 1e6,
        "max": float(np.max(values_ns)) / 1e6,
    }


def bench_latency(
    steps: int, seed: int = 0, sessions: int = 1, interval: float = 0.0
) -> dict[str, Any]:
    """Run the benchmark sessions and summarise their measured epochs.

    Parameters
    ----------
    steps : int
        Measured epochs per session (>= 1); a session has ``steps + 1`` (the last epoch
        has no move).
    seed : int
        Seed of the first session; session i has seed ``seed + i``.
    sessions : int
        Concurrent sessions on the one service (>= 1).
    interval : float
        Seconds each source waits before answering a move (>= 0).

    Returns
    -------
    dict
        ``{"steps", "sessions", "interval_s", "end_to_end_ms", "update_ms", "queued_ms",
        "transport_ms", "steady_end_to_end_ms", "non_learner_share"}``; each ``*_ms`` is
        ``{"median", "p99", "max"}`` in ms over all sessions' epochs (``steady_*``: without
        each session's first :data:`WARMUP` epochs; None when ``steps <= WARMUP``);
        ``non_learner_share`` is the total transport + rest time over the total end-to-end
        time, in [0, 1].

    Raises
    ------
    TimeoutError
        If the service does not answer or report within :data:`TIMEOUT` seconds.
    """
    if steps < 1:
        raise ValueError(f"--steps must be at least 1; got {steps}")
    if sessions < 1:
        raise ValueError(f"--sessions must be at least 1; got {sessions}")
    if interval < 0:
        raise ValueError(f"--interval must be >= 0 s; got {interval}")
    context = multiprocessing.get_context("spawn")
    endpoint = free_tcp_endpoint()
    receiver, sender = context.Pipe(duplex=False)
    service = context.Process(
        target=_service, args=([endpoint], sender, sessions), name="cfbci-latency-service"
    )
    service.start()
    ids = [_SESSION if sessions == 1 else f"{_SESSION}-{i}" for i in range(sessions)]
    try:
        with zenoh.open(peer_config((), [endpoint])) as session, ThreadPoolExecutor(
            sessions
        ) as pool:
            def run(i: int) -> SourceSummary:
                time.sleep(interval * i / sessions)  # independent phases
                return replay_session(session, SourceSettings(
                    ids[i], seed=seed + i, steps=steps + 1, grid=GRID, timeout=TIMEOUT,
                    interval=interval,
                ))

            summaries = list(pool.map(run, range(sessions)))
        reports = {}
        for _ in ids:  # the service reports right after each session_ended
            if not receiver.poll(TIMEOUT):
                raise TimeoutError(f"the service did not report its timings within {TIMEOUT} s")
            reported, update_ns, queued_ms = receiver.recv()
            reports[reported] = (update_ns, queued_ms)
    finally:
        service.terminate()
        service.join(TIMEOUT)
        if service.is_alive():
            service.kill()
            service.join()
    end_to_end, update, queued, steady = [], [], [], []
    for sid, summary in zip(ids, summaries, strict=True):
        update_ns, queued_ms = reports.get(sid, ([], []))
        if not len(summary.latency_ns) == len(update_ns) == len(queued_ms) == steps:
            raise RuntimeError(
                f"expected {steps} timings of session {sid!r}; got {len(summary.latency_ns)} "
                f"end-to-end, {len(update_ns)} update and {len(queued_ms)} queueing timings"
            )
        end_to_end += summary.latency_ns
        steady += summary.latency_ns[WARMUP:]
        update += update_ns
        queued += queued_ms
    end_to_end_ns = np.asarray(end_to_end, dtype=np.float64)
    transport = end_to_end_ns - np.asarray(update, dtype=np.float64)
    return {
        "steps": steps,
        "sessions": sessions,
        "interval_s": interval,
        "end_to_end_ms": _stats_ms(end_to_end_ns),
        "update_ms": _stats_ms(np.asarray(update, dtype=np.float64)),
        "queued_ms": _stats_ms(np.asarray(queued, dtype=np.float64) * 1e6),
        "transport_ms": _stats_ms(transport),
        "steady_end_to_end_ms": _stats_ms(np.asarray(steady, dtype=np.float64)) if steady
        else None,
        "non_learner_share": float(transport.sum() / end_to_end_ns.sum()),
    }


def print_latency(report: dict[str, Any], console: Console) -> None:
    """The report as a table (ms), and the non-learner share of the end-to-end time."""
    table = Table(
        title=f"bench latency: {report['sessions']} session(s) x {report['steps']} epochs, "
        f"T = {GRID * GRID}, answers after {report['interval_s']:g} s"
    )
    for column in ("ms", "median", "p99", "max"):
        table.add_column(column, justify="right")
    rows = [(name, key) for name, key in (
        ("end to end", "end_to_end_ms"), ("learner update", "update_ms"),
        ("queueing", "queued_ms"), ("transport + rest", "transport_ms"),
        (f"end to end after {WARMUP} epochs", "steady_end_to_end_ms"),
    ) if report[key] is not None]
    for name, key in rows:
        table.add_row(name, *(f"{report[key][stat]:.3f}" for stat in ("median", "p99", "max")))
    console.print(table)
    console.print(
        f"non-learner share of the end-to-end time: {report['non_learner_share']:.1%} "
        "(total transport + rest over total end to end)"
    )
