"""``cfbci bench flood``: a real session against a service a hostile client floods.

Three processes on loopback Zenoh (spawned; multicast off): the service (recording), the
replay source of one real session, and a hostile client that floods the service with
malformed and adversarial messages (`attacks`): undecodable bytes, header lengths
that lie, huge numbers, oversized payloads, maximum-size configs it follows (and feeds a
maximum-size epoch), valid configs for sessions nobody follows, and garbage on the real
session's own keys (at most `LIVE_SHARE` of the rate limit), before the real
session starts and while it runs. Before the real session asks for a slot, a *slot hog*
sends four configs per slot of the service (`slot_hog`) while it listens to every
session's events (``cfbci/**/event``) but never answers their challenge, as a client that
tries to hold every slot does: none of its sessions may start, and the real one must.
Afterwards:

* the real session's decisions equal ``cfbci simulate``'s for its seed, and its recording
  replays identically (`replay.rerun.replay_check`);
* the largest queueing delay any of its epochs saw in the service's intake (the
  ``queued_ms`` the service records with each move), and the end-to-end latency;
* the service's peak resident memory (``VmHWM``) against `memory_bound`;
* the service's exit code after SIGTERM (0: clean).
"""

from __future__ import annotations

import json
import multiprocessing
import queue
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, replace
from multiprocessing.synchronize import Event
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from rich.console import Console
from rich.table import Table

from acquisition.simulated_source import SourceSettings, SourceSummary, run_source
from acquisition.sources import DataSpec
from calibration_free.config import LearnerConfig
from calibration_free.world import GridWorld
from cfbci.offline.simulation import SessionConfig, run_session
from cfbci.service import serve
from cfbci.service.limits import ServiceLimits, world_memory_bytes
from replay.recording import read_recording
from replay.rerun import replay_check
from wire import protocol
from wire.intake import QUEUE_BYTES
from wire.transport import Pump, Received, reliable_publisher
from wire.zenoh_config import free_tcp_endpoint, peer_config

#: Seconds any one wait may take before the benchmark gives up (a failure guard).
TIMEOUT = 120.0
#: Seconds between two sendings of an unanswered maximum-size config.
RESEND_S = 1.0
#: Resident memory of an idle service (Python, numpy, scipy, Zenoh), MiB: a measured
#: figure with margin, the base of `memory_bound`.
BASE_MB = 250.0
_LIVE = "real"
#: Share of the rate limit the flood spends on the real session's own keys. The limit is
#: per session id, whoever sends: a flood on a session's keys beyond it throttles that
#: session (its source's re-sending still gets one epoch through per interval); only
#: access control (docs/deployment.md) keeps others off a session's keys.
LIVE_SHARE = 0.5
_SPAWN = multiprocessing.get_context("spawn")


def memory_bound(limits: ServiceLimits) -> float:
    """The stated bound of the service's resident memory, MiB: the base, every session at
    its memory limit, and the intake's FIFOs full (one per session and the shared one)."""
    queues = (limits.max_sessions + 1) * QUEUE_BYTES / 2**20
    return BASE_MB + limits.max_sessions * limits.max_session_mb + queues


def _frame(header: dict[str, Any] | bytes, payload: bytes = b"") -> bytes:
    text = header if isinstance(header, bytes) else json.dumps(header).encode()
    return len(text).to_bytes(4, "little") + text + payload


def _epoch_header(session: str, seq: int, step: int, shape: list[int]) -> dict[str, Any]:
    return {
        "v": protocol.VERSION, "kind": "epoch", "session": session, "seq": seq, "t_ns": 1,
        "step": step, "signal": "features", "shape": shape, "dtype": "float32", "units": "uV",
    }


def _config(grid: int, steps: int, frame: str = "feedback") -> dict[str, Any]:
    return {
        "seed": 0, "world": "grid", "grid": grid, "frame": frame, "steps": steps, "learner": {},
        "dataset": {}, "signal": "features",
    }


def attacks(live: str, limits: ServiceLimits, round_: int) -> list[tuple[str, str, bytes]]:
    """One round of hostile messages: ``(category, key expression, bytes)``.

    ``live`` is the real session's id (its keys get garbage too); ids of the flood's own
    sessions carry ``round_`` so that every round names new ones.
    """
    rng = np.random.default_rng(round_)
    other = f"flood-{round_}"
    huge = 2**63 - 1
    config_header = {"v": protocol.VERSION, "kind": "config", "session": other, "seq": 0,
                     "t_ns": 1, **_config(2**62, 10**18)}
    oversized = limits.max_message_bytes + 1
    return [
        ("undecodable bytes", f"cfbci/{live}/epoch", rng.bytes(64)),
        ("undecodable bytes", f"cfbci/{live}/config", b"\xff\xfe" + rng.bytes(30)),
        ("undecodable bytes", f"cfbci/{other}/truth", rng.bytes(3)),
        ("undecodable bytes", "cfbci/_/config", rng.bytes(16)),
        ("lying header length", f"cfbci/{live}/epoch", (2**32 - 1).to_bytes(4, "little") + b"{}"),
        ("lying header length", f"cfbci/{other}/epoch", (1000).to_bytes(4, "little") + b"{}"),
        ("lying header length", f"cfbci/{live}/epoch", _frame(b"")),
        ("huge numbers", f"cfbci/{live}/epoch",
         _frame(_epoch_header(live, huge, huge, [2**31, 2**31]), bytes(8))),
        ("huge numbers", f"cfbci/{live}/epoch",
         _frame(json.dumps(_epoch_header(live, 1, 1, [1])).replace('"seq": 1', '"seq": 1e400')
                .encode(), bytes(4))),
        ("huge numbers", f"cfbci/{other}/config", _frame(config_header)),
        ("oversized payload", f"cfbci/{live}/epoch",
         _frame(_epoch_header(live, 2, 1, [oversized // 4]), bytes(oversized // 4 * 4))),
        ("garbage on the live session's keys", f"cfbci/{live}/epoch",
         _frame(_epoch_header(live, round_, 10**6, [4]), bytes(16))),
        ("garbage on the live session's keys", f"cfbci/{live}/epoch",
         _frame(_epoch_header(live, round_, 1, [3]), np.full(3, np.nan, "<f4").tobytes())),
        ("garbage on the live session's keys", f"cfbci/{live}/truth",
         _frame({"v": protocol.VERSION, "kind": "truth", "session": live, "seq": 0, "t_ns": 1,
                 "step": 10**9, "target": 0, "label": 0})),
        ("unfollowed config", f"cfbci/nobody-{round_}/config",
         protocol.encode(protocol.Message("config", f"nobody-{round_}", 0, 1, _config(3, 10)))),
    ]


def largest_fitting_features(limits: ServiceLimits, grid: int, steps: int) -> int:
    """The longest feature vector (<= ``max_features``) with which a session of
    `_config` (``grid``, ``steps``, feedback, default learner) stays within
    ``max_session_mb`` by `world_memory_bytes`; 0 if none does."""
    world, learner, budget = GridWorld(grid), LearnerConfig(), limits.max_session_mb * 2**20
    fits = [
        d for d in range(1, limits.max_features + 1)
        if world_memory_bytes(world, learner, steps, d) <= budget
    ]
    return max(fits, default=0)


def _maximum_sessions(limits: ServiceLimits) -> list[tuple[str, dict[str, Any], int]]:
    """Sessions at the limits the flood follows: ``(id, config, features of its epoch)``.

    Largest grid, most steps; all but one get the longest epoch within the memory limit
    (so they commit about ``max_session_mb`` each and stay until the idle timeout), the
    last one an epoch of ``max_features`` (over the limit: rejected at that epoch).
    """
    config = _config(limits.max_grid, limits.max_steps)
    fitting = largest_fitting_features(limits, limits.max_grid, limits.max_steps)
    sizes = [fitting] * (limits.max_sessions - 2) + [limits.max_features]
    return [(f"maximum-{i}", config, d) for i, d in enumerate(sizes) if d > 0]


def slot_hog(limits: ServiceLimits) -> list[tuple[str, bytes]]:
    """The slot hog's configs: ``(key expression, bytes)``, four per slot of ``limits``."""
    return [
        (protocol.key(f"hog-{i}", "config"),
         protocol.encode(protocol.Message("config", f"hog-{i}", 0, 1, _config(3, 10))))
        for i in range(4 * limits.max_sessions)
    ]


def _flood(endpoint: str, limits: ServiceLimits, rounds: int, done: Event, counts: Any) -> None:
    """The hostile client (a spawned process): garbage until the real session has started
    (it watches its events), then maximum-size sessions, and rounds of `attacks`
    until ``rounds`` are sent or ``done`` is set."""
    sent: Counter[str] = Counter()
    if rounds == 0:  # the reference run: no flood at all
        return
    with zenoh.open(peer_config((), [endpoint])) as session:
        publishers: dict[str, zenoh.Publisher] = {}
        live_window = [0, 0]  # the current second, messages sent on the live keys in it

        def put(key_expr: str, data: bytes, category: str) -> None:
            if key_expr.startswith(f"{protocol.PREFIX}/{_LIVE}/"):
                second = int(time.monotonic())
                live_window[:] = [second, live_window[1] + 1 if live_window[0] == second else 1]
                if live_window[1] > LIVE_SHARE * limits.rate:
                    return  # see LIVE_SHARE
            if key_expr not in publishers:
                publishers[key_expr] = reliable_publisher(session, key_expr)
            publishers[key_expr].put(data)
            sent[category] += 1

        # One subscription to every session's events, declared before the first message.
        events: queue.SimpleQueue[Received] = queue.SimpleQueue()
        pump = Pump(session, f"{protocol.PREFIX}/**/event", "event", events)
        seen: set[tuple[str, str]] = set()  # (session, event) pairs received so far
        challenges: dict[str, tuple[int, str]] = {}  # session -> (config_t_ns, challenge)

        def received(sid: str, names: tuple[str, ...], timeout: float) -> bool:
            """Whether ``sid`` has sent one of the events ``names``, waiting up to
            ``timeout`` s for it."""
            deadline = time.monotonic() + timeout
            while not any((sid, name) in seen for name in names):
                try:
                    sample = events.get(timeout=max(0.0, deadline - time.monotonic()))
                except queue.Empty:
                    return False
                message = protocol.decode(sample.data)
                seen.add((message.session, message.fields["event"]))
                if message.fields["event"] == "session_pending":
                    challenges[message.session] = (
                        message.fields["config_t_ns"], message.fields["challenge"])
            return True

        for key_expr, data in slot_hog(limits):
            put(key_expr, data, "slot hog config")

        round_ = 0
        while round_ < rounds and not received(_LIVE, ("session_started",), 0.0):
            for category, key_expr, data in attacks(_LIVE, limits, round_):
                if "config" not in category:
                    put(key_expr, data, category)
            round_ += 1
        for sid, config, n_features in _maximum_sessions(limits):
            # Like a real client, re-sent until answered: the flood itself may have filled
            # the intake's shared FIFO, where configs of new sessions wait.
            config_message = protocol.encode(protocol.Message("config", sid, 0, 1, config))
            give_up = time.monotonic() + TIMEOUT
            put(protocol.key(sid, "config"), config_message, "maximum-size config")
            answered = ("session_started", "session_rejected")
            while not received(sid, answered, 0.0):
                if time.monotonic() > give_up:
                    raise TimeoutError(f"flood: session {sid!r} unanswered after {TIMEOUT} s")
                if sid in challenges:  # it follows these sessions: it answers the challenge
                    config_t_ns, challenge = challenges[sid]
                    put(protocol.key(sid, "ready"), protocol.encode(protocol.Message(
                        "ready", sid, 0, 1, {"config_t_ns": config_t_ns, "challenge": challenge},
                    )), "ready of a maximum-size config")
                if not received(sid, (*answered, "session_pending"), RESEND_S) or (
                    sid in challenges and not received(sid, answered, RESEND_S)
                ):
                    put(protocol.key(sid, "config"), config_message,
                        "maximum-size config, re-sent")
            # (an epoch before the session starts would only be an error)
            epoch = np.ones(n_features, dtype=np.float32)
            put(protocol.key(sid, "epoch"),
                protocol.encode(protocol.Message(
                    "epoch", sid, 0, 1, {"step": 1, "signal": "features"}, epoch)),
                "maximum-size epoch")
        while round_ < rounds and not done.is_set():
            for category, key_expr, data in attacks(_LIVE, limits, round_):
                put(key_expr, data, category)
            round_ += 1
        received("-", (), 0.0)  # takes in the events that came meanwhile
        sent["slot hog sessions started"] = sum(
            name == "session_started" and sid.startswith("hog-") for sid, name in seen)
        pump.close()
        for publisher in publishers.values():
            publisher.undeclare()
    counts.update(dict(sent))


def _peak_rss_mb(pid: int) -> float:
    """Peak resident memory of a process (``VmHWM`` of /proc/<pid>/status), MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmHWM in /proc/{pid}/status")


def _service(endpoint: str, record_dir: Path, limits: ServiceLimits) -> None:
    serve([endpoint], (), record_dir, limits=limits)


@dataclass(frozen=True)
class FloodReport:
    """What ``cfbci bench flood`` measured (see the module docstring).

    Attributes
    ----------
    steps, grid, seed : int
        The real session.
    sent : dict of str to int
        Hostile messages sent, per category.
    decisions_equal_simulation, replay_identical : bool
    queued_ms_max, queued_ms_median : float
        Queueing delay of the real session's epochs in the service's intake, ms.
    end_to_end_ms : dict of str to float
        Epoch published to next move received by the real source: median, p99, max, ms.
    peak_rss_mb, rss_bound_mb : float
        The service's peak resident memory, and `memory_bound`, MiB.
    exit_code : int or None
        The service's exit code after SIGTERM.
    elapsed_s : float
        Wall time of the real session.
    """

    steps: int
    grid: int
    seed: int
    sent: dict[str, int]
    decisions_equal_simulation: bool
    replay_identical: bool
    queued_ms_max: float
    queued_ms_median: float
    end_to_end_ms: dict[str, float]
    peak_rss_mb: float
    rss_bound_mb: float
    exit_code: int | None
    elapsed_s: float


def bench_flood(
    steps: int = 300,
    grid: int = 5,
    seed: int = 0,
    rounds: int = 2000,
    limits: ServiceLimits | None = None,
    record_dir: Path | None = None,
) -> FloodReport:
    """Run the flood (see the module docstring) and measure.

    Parameters
    ----------
    steps, grid, seed : int
        The real session (synthetic raw epochs, feedback frame).
    rounds : int
        Rounds of `attacks` (15 messages each), at most; the flood stops when the
        real session ends. 0: no flood (the reference).
    limits : ServiceLimits, optional
        The service's limits; default `ServiceLimits` with a 20 s idle timeout.
    record_dir : Path, optional
        Where the service records (default: a temporary directory, removed afterwards).
    """
    limits = limits or replace(ServiceLimits(), idle_timeout=20.0)
    if record_dir is None:
        with tempfile.TemporaryDirectory() as directory:
            return bench_flood(steps, grid, seed, rounds, limits, Path(directory))
    endpoint = free_tcp_endpoint()
    service = _SPAWN.Process(target=_service, args=(endpoint, record_dir, limits))
    manager = _SPAWN.Manager()
    done, counts = manager.Event(), manager.dict()
    flood = _SPAWN.Process(target=_flood, args=(endpoint, limits, rounds, done, counts))
    settings = SourceSettings(_LIVE, seed=seed, steps=steps, grid=grid, timeout=TIMEOUT)
    service.start()
    try:
        flood.start()
        with _SPAWN.Pool(1) as pool:
            begun = time.monotonic()
            result = pool.apply_async(run_source, (settings, [], [endpoint]))
            summary: SourceSummary = result.get(TIMEOUT * 10)
            elapsed = time.monotonic() - begun
        done.set()
        flood.join(TIMEOUT)
        assert service.pid is not None
        peak = _peak_rss_mb(service.pid)
    finally:
        done.set()
        service.terminate()
        service.join(TIMEOUT)
        if service.is_alive():
            service.kill()
            service.join()
        if flood.is_alive():
            flood.kill()
            flood.join()
        sent = dict(counts)
        manager.shutdown()
    trace: list[Any] = []
    config = SessionConfig(steps=steps, grid=grid)
    run_session(seed, config, DataSpec().resolve("feedback"), trace.append)
    path = record_dir / f"{_LIVE}.mcap"
    queued = np.asarray([m["queued_ms"] for _, m in read_recording(path).messages["/move"]
                         if "queued_ms" in m])
    latency = np.asarray(summary.latency_ns, dtype=np.float64) / 1e6
    return FloodReport(
        steps=steps, grid=grid, seed=seed, sent=sent,
        decisions_equal_simulation=summary.records == trace,
        replay_identical=replay_check(path).divergence is None,
        queued_ms_max=float(queued.max()), queued_ms_median=float(np.median(queued)),
        end_to_end_ms={
            "median": float(np.median(latency)), "p99": float(np.percentile(latency, 99)),
            "max": float(latency.max()),
        },
        peak_rss_mb=peak, rss_bound_mb=memory_bound(limits), exit_code=service.exitcode,
        elapsed_s=elapsed,
    )


def print_flood(report: FloodReport, console: Console) -> None:
    """The figures of a flood run."""
    table = Table(title=f"bench flood: {report.steps} steps, grid {report.grid}")
    table.add_column("hostile messages sent")
    table.add_column("count", justify="right")
    for category, count in sorted(report.sent.items()):
        table.add_row(category, str(count))
    console.print(table)
    e2e = report.end_to_end_ms
    for line in (
        f"real session: decisions equal the simulation: {report.decisions_equal_simulation}; "
        f"recording replays identically: {report.replay_identical}; {report.elapsed_s:.1f} s",
        f"queueing delay of its epochs in the service: max {report.queued_ms_max:.2f} ms, "
        f"median {report.queued_ms_median:.3f} ms",
        f"epoch to next move: median {e2e['median']:.2f} ms, p99 {e2e['p99']:.2f} ms, "
        f"max {e2e['max']:.2f} ms",
        f"service peak resident memory {report.peak_rss_mb:.0f} MiB (bound "
        f"{report.rss_bound_mb:.0f} MiB); exit code after SIGTERM {report.exit_code}",
    ):
        console.print(line, soft_wrap=True)


