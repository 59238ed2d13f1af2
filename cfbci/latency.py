"""``cfbci bench latency``: end-to-end latency of the live pipeline, and the learner's share.

The service runs in its own spawned process, the replay source in this one; they talk over
Zenoh on a loopback TCP endpoint (multicast off). One session of ``steps + 1`` epochs at
T = 25 tasks (5 x 5 grid, synthetic raw epochs, feedback frame, default learner) runs as
fast as it can (no reaction time). Per epoch k (all but the last):

* **end to end**: from the epoch of step k published by the source to the move of step
  k + 1 taken off the source's subscriber (:attr:`SourceSummary.latency_ns`, the source's
  monotonic clock);
* **update**: the learner's own time inside the service, ``observe`` of epoch k plus
  ``propose`` of move k + 1 (:attr:`cfbci.service._Session.update_ns`), sent back to this
  process through a pipe when the session ends (the wire protocol has no field for it);
* **transport + rest**: end to end minus update: encoding, Zenoh both ways, decoding,
  checks, feature extraction, the ``state`` and its balanced accuracy, recording (none
  here), queueing.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import zenoh
from rich.console import Console
from rich.table import Table

from acquisition.replay_source import SourceSettings, replay_session
from cfbci.service import serve
from wire.zenoh_config import free_tcp_endpoint, peer_config

#: Grid side of the benchmark (T = GRID ** 2 tasks).
GRID = 5
#: Seconds any one wait may take before the benchmark gives up (a failure guard).
TIMEOUT = 60.0
_SESSION = "latency"


def _service(listen: Sequence[str], results: Connection) -> None:
    """The service process: sends ``(session, update_ns)`` on ``results`` per ended session."""
    serve(listen, (), None, on_end=lambda session, update_ns: results.send((session, update_ns)))


def _stats_ms(values_ns: np.ndarray) -> dict[str, float]:
    """Median, 99th percentile and maximum of durations in ns, as ms."""
    return {
        "median": float(np.median(values_ns)) / 1e6,
        "p99": float(np.percentile(values_ns, 99)) / 1e6,
        "max": float(np.max(values_ns)) / 1e6,
    }


def bench_latency(steps: int, seed: int = 0) -> dict[str, Any]:
    """Run the benchmark session and summarise its ``steps`` measured epochs.

    Parameters
    ----------
    steps : int
        Measured epochs (>= 1); the session has ``steps + 1`` (the last epoch has no move).
    seed : int
        Session seed.

    Returns
    -------
    dict
        ``{"steps", "end_to_end_ms", "update_ms", "transport_ms", "non_learner_share"}``;
        each ``*_ms`` is ``{"median", "p99", "max"}`` in ms; ``non_learner_share`` is the
        total transport + rest time over the total end-to-end time, in [0, 1].

    Raises
    ------
    TimeoutError
        If the service does not answer or report within :data:`TIMEOUT` seconds.
    """
    if steps < 1:
        raise ValueError(f"--steps must be at least 1; got {steps}")
    context = multiprocessing.get_context("spawn")
    endpoint = free_tcp_endpoint()
    receiver, sender = context.Pipe(duplex=False)
    service = context.Process(
        target=_service, args=([endpoint], sender), name="cfbci-latency-service"
    )
    service.start()
    try:
        settings = SourceSettings(_SESSION, seed=seed, steps=steps + 1, grid=GRID, timeout=TIMEOUT)
        with zenoh.open(peer_config((), [endpoint])) as session:
            summary = replay_session(session, settings)
        # The service reports right after session_ended, which the source has seen.
        if not receiver.poll(TIMEOUT):
            raise TimeoutError(f"the service did not report its timings within {TIMEOUT} s")
        reported, update_ns = receiver.recv()
    finally:
        service.terminate()
        service.join(TIMEOUT)
        if service.is_alive():
            service.kill()
            service.join()
    end_to_end = np.asarray(summary.latency_ns, dtype=np.float64)
    update = np.asarray(update_ns, dtype=np.float64)
    if reported != _SESSION or len(end_to_end) != steps or len(update) != steps:
        raise RuntimeError(
            f"expected {steps} timings of session {_SESSION!r}; got {len(end_to_end)} "
            f"end-to-end and {len(update)} update timings of session {reported!r}"
        )
    transport = end_to_end - update
    return {
        "steps": steps,
        "end_to_end_ms": _stats_ms(end_to_end),
        "update_ms": _stats_ms(update),
        "transport_ms": _stats_ms(transport),
        "non_learner_share": float(transport.sum() / end_to_end.sum()),
    }


def print_latency(report: dict[str, Any], console: Console) -> None:
    """The report as a table (ms), and the non-learner share of the end-to-end time."""
    table = Table(
        title=f"bench latency: {report['steps']} epochs, T = {GRID * GRID}"
    )
    for column in ("ms", "median", "p99", "max"):
        table.add_column(column, justify="right")
    for name, key in (
        ("end to end", "end_to_end_ms"), ("learner update", "update_ms"),
        ("transport + rest", "transport_ms"),
    ):
        table.add_row(name, *(f"{report[key][stat]:.3f}" for stat in ("median", "p99", "max")))
    console.print(table)
    console.print(
        f"non-learner share of the end-to-end time: {report['non_learner_share']:.1%} "
        "(total transport + rest over total end to end)"
    )
