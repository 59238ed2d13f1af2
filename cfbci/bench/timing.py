"""``cfbci bench timing``: the stimulus page's onsets against an independent clock.

One session of the whole lab loop on this machine, every part a real process on loopback
(LSL kept on the loopback by an ``lsl_api.cfg`` of the bench's own, Zenoh on a free
port): ``cfbci serve``, ``cfbci lsl-bridge``, ``cfbci lsl-simulator --onsets`` (the
amplifier and the brain) and ``cfbci view --stimulus``, whose subject page runs in
headless Chromium driven by Selenium, with a short inter-action interval.

The reference. The page marks every show in its performance timeline,
``performance.mark("onset <step>", {startTime: t})`` with ``t`` the timestamp of the
animation frame that shows the move, and the bench records a trace of Chromium's own
(the DevTools protocol's ``Tracing`` domain, category ``blink.user_timing``) for the
whole session. Chromium stamps each mark in the trace at its time origin plus ``t``, in
its trace clock: ``base::TimeTicks``, which on Linux is ``CLOCK_MONOTONIC`` in
microseconds, the clock ``pylsl.local_clock()`` reads (checked at the start of every
run: `check_clock`). The onset marker's LSL timestamp is ``t`` mapped by the offset the
view estimates from WebSocket round trips with the page; the trace's time is mapped by
Chromium itself, which does not share that estimate. So

* ``onset_error_ms``: marker timestamp minus the trace's time of the same show, over the
  valid onsets (median, p99, max of the absolute error);
* ``drift_ms_per_hour``: the slope of that error (signed) against the trace's time, by
  least squares;
* ``refresh_hz``: 1000 / the median refresh period the page reported;
* ``invalid_onsets``: the shows reported invalid (``invalid-onset`` markers);
* ``move_to_frame_ms``: for step k + 1, from the arrival at the bridge of the last EEG
  sample of step k's window (the bridge's ``arrived``, monotonic clock) to the trace's
  time of the frame that first shows move k + 1, minus the deliberate wait: the page shows
  a move no sooner than the interval after the last show, so the latency runs from the
  later of that arrival and the end of that wait. Steps after which the page redraws the
  agent before showing the next move (a new start, a bump into a wall, a declaration)
  wait a whole interval from the move's arrival at the page, which
  the trace does not see: they are left out;
* ``steps``: epochs the bridge published.

``skew_ms`` is a deliberate error: the page's answers to the round trips read its clock
``skew_ms`` ms early, so its offset, and every marker, is ``skew_ms`` ms late against the
trace: the onset error shows it, the page's own report does not.
"""

from __future__ import annotations

import asyncio
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.lsl_streams import loopback_config
from cfbci.view.chromium import headless_options
from replay.recording import read_recording
from wire.zenoh_config import free_tcp_endpoint

#: Debian's programs the bench drives, and the packages that install them.
PROGRAMS = {"chromium": "chromium", "chromedriver": "chromium-driver"}
#: Seconds a part may keep the session waiting (processes, streams, the page).
TIMEOUT = 60.0
TOKEN = "bench-timing-token-0123456789"


def missing() -> str | None:
    """What to install for the bench (one line), or None when everything is there."""
    programs = [package for program, package in PROGRAMS.items() if shutil.which(program) is None]
    python = importlib.util.find_spec("selenium") is None
    if not programs and not python:
        return None
    needs = ([f"apt-get install {' '.join(programs)}"] if programs else []) + (
        ["pip install selenium"] if python else [])
    return "cfbci bench timing needs headless Chromium, its driver and Selenium: " + "; ".join(
        needs)


def check_clock(reads: int = 100) -> float:
    """The difference between ``pylsl.local_clock()`` and ``CLOCK_MONOTONIC``, s: of the
    ``reads`` reads of the one bracketed by two reads of the other, the one whose bracket
    is the narrowest (a process preempted between two reads only widens its bracket, as
    in NTP's best round trip).

    Raises
    ------
    RuntimeError
        If they differ by more than a millisecond: they are not the same clock, and the
        trace is no reference for the LSL timestamps.
    """
    import pylsl

    best_width, difference = float("inf"), 0.0
    for _ in range(reads):
        before = time.clock_gettime(time.CLOCK_MONOTONIC)
        local = pylsl.local_clock()
        after = time.clock_gettime(time.CLOCK_MONOTONIC)
        if after - before < best_width:
            best_width, difference = after - before, abs(local - (before + after) / 2)
    if difference > 1e-3:
        raise RuntimeError(f"pylsl.local_clock() differs from CLOCK_MONOTONIC by "
                           f"{difference:.3f} s: Chromium's trace clock is no reference for "
                           "LSL timestamps here")
    return difference


class _Markers(threading.Thread):
    """Reads the onset markers from LSL until ``stop`` is set: (marker, timestamp) pairs.
    (Not the bridge's moves: an inlet of the bench's could let the bridge send the first
    move before the view reads the stream.)"""

    def __init__(self, onsets: str) -> None:
        super().__init__(name="bench-timing-markers", daemon=True)
        self.name = onsets
        self.markers: list[tuple[str, float]] = []
        self.stop = threading.Event()
        self.ready = threading.Event()

    def run(self) -> None:
        from pylsl.util import LostError

        from acquisition.lsl_streams import resolve_inlet

        onsets = resolve_inlet(self.name, TIMEOUT)
        self.ready.set()
        try:
            while not self.stop.is_set():
                value, stamp = onsets.pull_sample(timeout=0.02)
                if value is not None:
                    self.markers.append((value[0], stamp))
        except LostError:  # the view ended
            pass
        values, stamps = onsets.pull_chunk(timeout=0.0, as_numpy=False)
        self.markers.extend((value[0], stamp) for value, stamp in zip(values, stamps,
                                                                     strict=True))


async def _trace(address: str, started: threading.Event, stop: asyncio.Event,
                 events: list[dict[str, Any]]) -> None:
    """Record Chromium's ``blink.user_timing`` trace (browser-wide) until ``stop``."""
    import aiohttp

    async with aiohttp.ClientSession() as client:
        async with client.get(f"http://{address}/json/version") as answer:
            url = (await answer.json())["webSocketDebuggerUrl"]
        async with client.ws_connect(url, max_msg_size=0) as socket:
            await socket.send_json({"id": 1, "method": "Tracing.start", "params": {
                "traceConfig": {"includedCategories": ["blink.user_timing"],
                                "recordMode": "recordContinuously"},
                "transferMode": "ReportEvents"}})
            while (await socket.receive_json(timeout=TIMEOUT)).get("id") != 1:
                pass
            started.set()
            await stop.wait()
            await socket.send_json({"id": 2, "method": "Tracing.end"})
            while (message := await socket.receive_json(timeout=TIMEOUT)).get(
                    "method") != "Tracing.tracingComplete":
                if message.get("method") == "Tracing.dataCollected":
                    events.extend(message["params"]["value"])


class _Tracer:
    """A Chromium trace recorded in a thread of its own: `start`, then `finish` returns
    the ``onset <step>`` marks as (step, trace time in s of the monotonic clock)."""

    def __init__(self, address: str) -> None:
        self.address, self.events = address, []
        self.started = threading.Event()
        self.loop = asyncio.new_event_loop()
        self.stop = asyncio.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.error: BaseException | None = None

    def _run(self) -> None:
        try:
            self.loop.run_until_complete(
                _trace(self.address, self.started, self.stop, self.events))
        except BaseException as error:  # reported by start and finish
            self.error = error
            self.started.set()

    def start(self) -> None:
        self.thread.start()
        self.started.wait(TIMEOUT)
        if self.error is not None or not self.started.is_set():
            raise RuntimeError(f"Chromium's trace did not start: {self.error}")

    def finish(self) -> list[tuple[int, float]]:
        self.loop.call_soon_threadsafe(self.stop.set)
        self.thread.join(TIMEOUT)
        if self.error is not None:
            raise RuntimeError(f"Chromium's trace failed: {self.error}")
        return [(int(e["name"].split()[1]), e["ts"] / 1e6) for e in self.events
                if e.get("cat") == "blink.user_timing" and e.get("name", "").startswith("onset ")]


class _Run:
    """The processes of one bench session, in a scratch folder."""

    def __init__(self, folder: Path, steps: int, interval: float, seed: int) -> None:
        self.folder, self.steps, self.interval, self.seed = folder, steps, interval, seed
        self.name = f"bench-timing-{os.getpid()}"
        self.names = {kind: f"{kind}-{self.name}" for kind in ("moves", "onsets", "eeg")}
        self.endpoint = free_tcp_endpoint()
        self.env = os.environ | {"LSLAPICFG": str(folder / "lsl_api.cfg"),
                                 "CFBCI_VIEW_TOKEN": TOKEN}

    def start(self, role: str, *args: str, stdout: Any = None) -> subprocess.Popen:
        """``cfbci ARGS`` as a process, its log in ``<role>.log``."""
        with (self.folder / f"{role}.log").open("w") as log:
            return subprocess.Popen([sys.executable, "-m", "cfbci.cli", *args], env=self.env,
                                    stdout=stdout or log, stderr=log, text=True)

    def log(self, role: str) -> str:
        text = (self.folder / f"{role}.log").read_text()
        return f"{role} log ({self.folder / f'{role}.log'}):\n{text[-3000:]}"

    def view(self) -> tuple[subprocess.Popen, str]:
        """``cfbci view --stimulus``: the process and the subject page's address."""
        view = self.start("view", "view", "--connect", self.endpoint, "--port", "0",
                          "--stimulus", "--moves", self.names["moves"], "--onsets",
                          self.names["onsets"], "--interval", str(self.interval),
                          "--onset-log", str(self.folder / "onsets.jsonl"),
                          stdout=subprocess.PIPE)
        assert view.stdout is not None
        for line in view.stdout:
            if line.startswith("subject view: "):
                return view, line.removeprefix("subject view: ").strip().replace(
                    "session=ID&", "")
        raise RuntimeError(f"cfbci view did not start. {self.log('view')}")

    def clients(self) -> tuple[subprocess.Popen, subprocess.Popen]:
        """The simulator (listening for the page's onsets) and the bridge."""
        common = ["--session", self.name, "--seed", str(self.seed), "--connect",
                  self.endpoint, "--timeout", str(TIMEOUT), "--eeg", self.names["eeg"]]
        simulator = self.start("simulator", "lsl-simulator", *common, "--onsets",
                               self.names["onsets"])
        bridge = self.start("bridge", "lsl-bridge", *common, "--markers",
                            self.names["onsets"], "--moves", self.names["moves"], "--steps",
                            str(self.steps), "--json", str(self.folder / "bridge.json"))
        return simulator, bridge


def _stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


@contextmanager
def _browser(folder: Path, skew_ms: float) -> Iterator[Any]:
    """Headless Chromium whose pages answer the view's round trips ``skew_ms`` early."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = headless_options(str(shutil.which("chromium")), folder / "chromium-profile",
                               "--window-size=1280,800")
    driver = webdriver.Chrome(options=options, service=Service(shutil.which("chromedriver")))
    try:
        if skew_ms:
            driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": (
                "const send = WebSocket.prototype.send; WebSocket.prototype.send = function (d) {"
                " const m = JSON.parse(d); if (m.type === 'pong') {"
                f" m.page_ms -= {float(skew_ms)}; d = JSON.stringify(m); }}"
                " return send.call(this, d); };")})
        yield driver
    finally:
        driver.quit()


def run_session(steps: int, interval: float, seed: int, skew_ms: float,
                folder: Path) -> dict[str, Any]:
    """One session through the page in Chromium: the raw material of `figures`.

    Returns
    -------
    dict
        ``marks`` (step, trace time s), ``markers`` (text, LSL timestamp s), ``moves``
        and ``epochs`` (the recording's), ``onsets`` (the view's onset log), ``bridge``
        (its report), ``interval`` (s).
    """
    from selenium.webdriver.support.ui import WebDriverWait

    (folder / "lsl_api.cfg").write_text(loopback_config(f"cfbci-bench-timing-{os.getpid()}"))
    os.environ["LSLAPICFG"] = str(folder / "lsl_api.cfg")  # before this process's first LSL
    run = _Run(folder, steps, interval, seed)
    with ExitStack() as running:
        serve = run.start("serve", "serve", "--listen", run.endpoint, "--record-dir",
                          str(folder))
        running.callback(_stop, serve)
        view, address = run.view()
        running.callback(_stop, view)
        browser = running.enter_context(_browser(folder, skew_ms))
        tracer = _Tracer(browser.capabilities["goog:chromeOptions"]["debuggerAddress"])
        tracer.start()
        browser.get(address)
        WebDriverWait(browser, TIMEOUT).until(lambda b: b.execute_script(
            "return document.getElementById('view').dataset.stimulus") == "on")
        streams = _Markers(run.names["onsets"])
        streams.start()
        if not streams.ready.wait(TIMEOUT):
            raise RuntimeError("the view's onset stream was not found")
        simulator, bridge = run.clients()
        running.callback(_stop, simulator)
        running.callback(_stop, bridge)
        try:
            bridge.wait(steps * (interval + 10.0) + TIMEOUT)
        finally:
            streams.stop.set()
            streams.join(TIMEOUT)
        if bridge.returncode != 0:
            raise RuntimeError(f"the bridge failed (status {bridge.returncode}). "
                               f"{run.log('bridge')}\n{run.log('simulator')}\n{run.log('view')}")
        marks = tracer.finish()
    onsets = [json.loads(line) for line in (folder / "onsets.jsonl").read_text().splitlines()]
    recording = read_recording(folder / f"{run.name}.mcap").messages
    return {"marks": marks, "markers": streams.markers,
            "moves": [m for _, m in recording["/move"]],
            "epochs": [m for _, m in recording["/epoch"]],
            "onsets": onsets, "bridge": json.loads((folder / "bridge.json").read_text()),
            "interval": interval}


def _stats(values: np.ndarray, keys: tuple[str, ...]) -> dict[str, float]:
    """Median, p99 and max of ``values`` (those of ``keys``); NaN for none."""
    every = {"median": np.median, "p99": lambda v: np.percentile(v, 99), "max": np.max}
    return {key: float(every[key](values)) if len(values) else float("nan") for key in keys}


def _continuing(previous: dict[str, Any], move: dict[str, Any]) -> bool:
    """Whether the page shows ``move`` straight after ``previous`` (no redraw of the agent:
    ``previous`` left it plainly in the cell ``move`` starts from)."""
    plain = previous["action"] != "goal" and previous["to_state"] != previous["from_state"]
    return plain and move["from_state"] == previous["to_state"]


def figures(raw: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The bench's figures (the module's docstring) from `run_session`'s raw material, and
    what they rest on: the valid onsets and the latencies counted, the signed mean error.

    Raises
    ------
    RuntimeError
        If a valid onset marker has no mark of its step in the trace.
    """
    marks: dict[int, list[float]] = {}
    for step, when in raw["marks"]:
        marks.setdefault(step, []).append(when)
    errors, times, invalid = [], [], 0
    for text, stamp in raw["markers"]:
        word, step_text = text.split()[:2]
        if word != "onset":
            invalid += word == "invalid-onset"
            continue
        shows = np.asarray(marks.get(int(step_text), []))
        if not len(shows):
            raise RuntimeError(f"no mark of step {step_text} in Chromium's trace")
        nearest = shows[np.argmin(np.abs(shows - stamp))]
        errors.append(stamp - nearest)
        times.append(nearest)
    error_ms = np.asarray(errors) * 1e3
    hours = (np.asarray(times) - (times[0] if times else 0.0)) / 3600
    drift = float(np.polyfit(hours, error_ms, 1)[0]) if len(set(times)) > 1 else float("nan")
    moves = {move["step"]: move for move in raw["moves"]}
    arrived = {e["step"]: e["arrived"] for e in raw["bridge"]["epochs"]}
    measured = [step for step in sorted(arrived)
                if step + 1 in marks and step in marks and step in moves and step + 1 in moves
                and _continuing(moves[step], moves[step + 1])]
    latency = [min(marks[step + 1]) - max(arrived[step], max(marks[step]) + raw["interval"])
               for step in measured]
    # Its parts, from the recording's times (monotonic clock): the epoch's arrival at the
    # service to the next move's, and that move to the frame.
    received = {m["step"]: m["t_ns"] / 1e9 for m in raw["epochs"]}
    service = [moves[step + 1]["t_ns"] / 1e9 - received[step] for step in measured]
    delivery = [min(marks[step + 1]) - moves[step + 1]["t_ns"] / 1e9 for step in measured]
    periods = [o["period_ms"] for o in raw["onsets"] if o.get("period_ms")]
    return ({
        "onset_error_ms": _stats(np.abs(error_ms), ("median", "p99", "max")),
        "drift_ms_per_hour": drift,
        "refresh_hz": 1e3 / float(np.median(periods)) if periods else float("nan"),
        "invalid_onsets": invalid,
        "move_to_frame_ms": _stats(np.asarray(latency) * 1e3, ("median", "p99")),
        "steps": len(raw["bridge"]["epochs"]),
    }, {"onsets": len(errors), "latencies": len(latency),
        "service_ms": _stats(np.asarray(service) * 1e3, ("median", "p99")),
        "move_to_frame_from_service_ms": _stats(np.asarray(delivery) * 1e3, ("median", "p99")),
        "mean_error_ms": float(error_ms.mean()) if len(error_ms) else float("nan")})


def bench_timing(onsets: int, interval: float, seed: int = 0,
                 skew_ms: float = 0.0) -> tuple[dict[str, Any], dict[str, Any]]:
    """Run the bench: (the figures of the JSON, what they rest on: counts, the signed
    mean error, the clock check, ms).

    Raises
    ------
    ValueError
        On bad settings.
    RuntimeError
        If a part fails (with its log) or the clocks differ (`check_clock`).
    """
    if onsets < 2:
        raise ValueError(f"--onsets must be at least 2; got {onsets}")
    if not 0 <= interval <= 10:
        raise ValueError(f"--interval must be in 0..10 s; got {interval}")
    with tempfile.TemporaryDirectory(prefix="cfbci-bench-timing-") as scratch:
        raw = run_session(onsets, interval, seed, skew_ms, Path(scratch))
        clock = check_clock()
    result, basis = figures(raw)
    return result, basis | {"clock_difference_ms": clock * 1e3}
