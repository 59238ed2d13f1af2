"""The operator's commands (docs/protocol.md, "Operator controls") on live sessions: real
Zenoh on loopback, a real service and simulated source in spawned processes, ``cfbci
control`` and the browser view's operator page in headless Chromium.

A pause lasts longer than the service's idle timeout on purpose: that the session
survives it is what is tested (the wait is the pause, not a synchronisation). Every other
wait is for a message, with a timeout that only guards against a hang.
"""

from __future__ import annotations

import os
import queue
import signal
import time
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import pytest
import zenoh
from live import SPAWN, TIMEOUT
from selenium import webdriver
from selenium.webdriver.common.by import By
from selenium.webdriver.support import expected_conditions
from selenium.webdriver.support.ui import WebDriverWait
from test_view import browser

from acquisition.simulated_source import SourceSettings, SourceSummary, run_source
from acquisition.sources import DataSpec
from calibration_free.streams import StepRecord
from cfbci.cli import main
from cfbci.offline.simulation import SessionConfig, run_session
from cfbci.service import serve
from cfbci.service.limits import ServiceLimits
from cfbci.service.process import spawned
from cfbci.view.server import Access, run_view
from replay.recording import read_recording
from replay.rerun import replay_check
from wire import protocol
from wire.operator import send_command
from wire.transport import Pump, Received
from wire.zenoh_config import free_tcp_endpoint, peer_config

__all__ = ["browser"]  # the fixture, shared with tests/test_view.py

STEPS, GRID, SEED = 40, 3, 3
IDLE = 1.0  # the service's idle and start timeouts, s: a pause lasts 3 of them
LIMITS = ServiceLimits(idle_timeout=IDLE, start_timeout=30.0)
INTERVAL = 0.1  # the source's wait between a move and its answer, s


def simulated(seed: int) -> list[StepRecord]:
    """The trace of ``cfbci simulate`` for the seed (the unpaused session's decisions)."""
    trace: list[StepRecord] = []
    run_session(seed, SessionConfig(steps=STEPS, grid=GRID), DataSpec().resolve("feedback"),
                trace.append)
    return trace


@contextmanager
def service(record_dir: Path, connect: tuple[str, ...] = ()) -> Iterator[str]:
    """A service with short timeouts (`LIMITS`) in a spawned process: its endpoint."""
    endpoint = free_tcp_endpoint()
    with spawned(serve, [endpoint], list(connect), record_dir, limits=LIMITS):
        yield endpoint


@contextmanager
def source(sid: str, endpoint: str) -> Iterator[Future[SourceSummary]]:
    """The simulated source of session ``sid`` in a spawned process; if the test fails
    meanwhile, the operator ends the session, so that the source ends too."""
    settings = SourceSettings(sid, seed=SEED, steps=STEPS, grid=GRID, interval=INTERVAL)
    with ProcessPoolExecutor(1, mp_context=SPAWN) as pool:
        try:
            yield pool.submit(run_source, settings, [], [endpoint])
        except BaseException:
            with zenoh.open(peer_config((), [endpoint])) as session, suppress(Exception):
                send_command(session, sid, "end")
            raise


class Watch:
    """The moves and events of one session, as the service published them."""

    def __init__(self, session: zenoh.Session, sid: str) -> None:
        self.inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
        self.pumps = [Pump(session, protocol.key(sid, kind), kind, self.inbox)
                      for kind in ("move", "event")]
        self.moves: list[int] = []
        self.events: list[dict[str, Any]] = []

    def take(self, timeout: float) -> bool:
        """Take one message in (False: none came within ``timeout`` s)."""
        try:
            received = self.inbox.get(timeout=max(timeout, 0))
        except queue.Empty:
            return False
        message = protocol.decode(received.data, key_expr=received.key_expr)
        if message.kind == "move":
            self.moves.append(message.fields["step"])
        else:
            self.events.append(message.fields)
        return True

    def until_move(self, step: int) -> None:
        while not self.moves or self.moves[-1] < step:
            assert self.take(TIMEOUT), f"no move of step {step}"

    def close(self) -> None:
        for pump in self.pumps:
            pump.close()


@pytest.fixture
def operator() -> Iterator[list[zenoh.Session]]:
    """Zenoh sessions the test opens (closed after it)."""
    sessions: list[zenoh.Session] = []
    yield sessions
    for session in sessions:
        session.close()


def _cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    status = main(["control", *args])
    return status, capsys.readouterr().out


@contextmanager
def watched(tmp_path: Path, sid: str, operator: list[zenoh.Session],
            step: int) -> Iterator[tuple[str, Watch, Future[SourceSummary]]]:
    """A service and the source of ``sid``, watched from a Zenoh session of the test's
    until the move of ``step``: the service's endpoint, the watch, the source's summary."""
    with service(tmp_path) as endpoint, source(sid, endpoint) as future:
        session = zenoh.open(peer_config((), [endpoint]))
        operator.append(session)
        watch = Watch(session, sid)
        try:
            watch.until_move(step)
            yield endpoint, watch, future
        finally:
            watch.close()


def test_a_pause_longer_than_the_idle_timeout_holds_the_session_and_it_completes_as_simulated(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], operator: list[zenoh.Session],
) -> None:
    sid = "lab-pause"
    with watched(tmp_path, sid, operator, 3) as (endpoint, watch, future):
        session = operator[-1]
        status, out = _cli(capsys, "pause", sid, "--connect", endpoint, "--json")
        assert status == 0 and '"session_paused"' in out
        while not any(e["event"] == "session_paused" for e in watch.events):
            assert watch.take(TIMEOUT)
        paused = next(e for e in watch.events if e["event"] == "session_paused")
        step = paused["step"]
        # Pause three idle timeouts long: the session neither ends nor moves on.
        until = time.monotonic() + 3 * IDLE
        while watch.take(until - time.monotonic()):
            pass
        assert max(watch.moves) == step
        assert not [e for e in watch.events if e["event"] in ("session_rejected",
                                                               "session_ended")]
        # A second pause, a target that is no cell: refused, the session untouched.
        with pytest.raises(ValueError, match="paused already"):
            send_command(session, sid, "pause")
        with pytest.raises(ValueError, match="no task of the session's world"):
            send_command(session, sid, "target", GRID * GRID)
        target = 4  # the cell the subject says they chose
        marked = send_command(session, sid, "target", target)
        assert (marked["event"], marked["target"], marked["step"]) == (
            "target_marked", target, step)
        status, out = _cli(capsys, "resume", sid, "--connect", endpoint)
        assert status == 0 and out.startswith("session_resumed: resumed by the operator")
        summary = future.result(TIMEOUT)
        with pytest.raises(ValueError, match="not running"):
            send_command(session, sid, "resume")

    assert summary.records == simulated(SEED)  # every decision as without the pause
    path = tmp_path / f"{sid}.mcap"
    recording = read_recording(path)
    logged = [(m["event"], m.get("step"), m.get("target"))
              for _, m in recording.messages["/event"] if "step" in m]
    assert logged == [("session_paused", step, None), ("target_marked", step, target),
                      ("session_resumed", step, None)]
    texts = [m["message"] for _, m in recording.messages["/log"]]
    assert any(t.startswith("session_paused: paused by the operator") for t in texts)
    result = replay_check(path)
    assert result.divergence is None and (result.moves, result.states) == (STEPS, STEPS + 1)
    assert [m["event"] for _, m in recording.messages["/event"]][-1] == "session_ended"
    assert main(["replay", str(path)]) == 0
    assert "identical" in capsys.readouterr().out


def test_the_operator_ends_a_session_early_and_its_recording_replays(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], operator: list[zenoh.Session],
) -> None:
    sid = "lab-end"
    with watched(tmp_path, sid, operator, 8) as (endpoint, _, future):
        status, out = _cli(capsys, "end", sid, "--connect", endpoint)
        assert status == 0 and "ended by the operator" in out
        summary = future.result(TIMEOUT)  # the source ends, without an error
    recording = read_recording(tmp_path / f"{sid}.mcap")
    last = recording.messages["/event"][-1][1]
    ended = last["step"]  # the last move's step: its epoch was not taken
    assert last["event"] == "session_ended" and 8 <= ended < STEPS
    assert summary.steps in (ended - 1, ended)  # the last move shown before the end, or not
    assert summary.records == simulated(SEED)[: summary.steps]
    result = replay_check(tmp_path / f"{sid}.mcap")
    assert result.divergence is None and (result.moves, result.states) == (ended, ended)


def test_a_service_killed_during_a_pause_resumes_the_session_paused(tmp_path: Path) -> None:
    sid = "lab-kill"
    endpoint, observer_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    args = ([endpoint], [observer_endpoint], tmp_path)
    with zenoh.open(peer_config([observer_endpoint], ())) as session:
        watch = Watch(session, sid)
        first = SPAWN.Process(target=serve, args=args, kwargs={"limits": LIMITS})
        first.start()
        with source(sid, endpoint) as future:
            watch.until_move(3)
            step = send_command(session, sid, "pause")["step"]
            assert first.pid is not None
            os.kill(first.pid, signal.SIGKILL)
            first.join(TIMEOUT)
            with spawned(serve, *args, limits=LIMITS):  # same directory, same endpoints
                # Paused after the restart: its "still paused" event, or, if that came before
                # this observer was connected to the new service again, a second pause
                # refused as such (the command waits for the service to subscribe).
                try:
                    answer = send_command(session, sid, "pause")["message"]
                except ValueError as refused:
                    answer = str(refused)
                assert answer.startswith("still paused") or "paused already" in answer, answer
                until = time.monotonic() + 3 * IDLE  # paused still, over the idle timeout
                while watch.take(until - time.monotonic()):
                    pass
                assert max(watch.moves) == step
                send_command(session, sid, "resume")
                summary = future.result(TIMEOUT)
        watch.close()
    assert summary.records == simulated(SEED)
    assert replay_check(tmp_path / f"{sid}.mcap").divergence is None


def test_cfbci_control_refuses_bad_input_with_a_message(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["control", "pause", "bad id", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "session id" in capsys.readouterr().err
    assert main(["control", "pause", "s"]) == 2
    assert "--connect" in capsys.readouterr().err


# The operator page (headless Chromium) ------------------------------------------------

TOKEN = "operator-test-token-0123456789"
POLL = 0.02  # seconds between two readings of a page


def _view_process(listen: str, ready: Any) -> None:
    run_view([listen], [], access=Access(TOKEN), host="127.0.0.1", port=0,
             on_ready=ready.put)


@pytest.fixture(scope="module")
def view() -> Iterator[tuple[str, str]]:
    """A view in a spawned process: its address (without the token), its Zenoh endpoint."""
    endpoint, ready = free_tcp_endpoint(), SPAWN.Queue()
    process = SPAWN.Process(target=_view_process, args=(endpoint, ready))
    process.start()
    try:
        yield ready.get(timeout=TIMEOUT), endpoint
    finally:
        process.terminate()
        process.join(TIMEOUT)
    assert process.exitcode == 0


def _shown(browser: webdriver.Chrome) -> dict[str, str]:
    """The page's #view data-* attributes and the controls' result line."""
    return browser.execute_script(
        "const view = document.getElementById('view');"
        "const result = document.getElementById('c-result');"
        "return Object.assign({result: result ? result.textContent : ''}, view.dataset)"
    )


def _wait(browser: webdriver.Chrome, condition: Any, what: str) -> dict[str, str]:
    """Poll the page until ``condition(shown)`` holds (a guard of `TIMEOUT` s of nothing
    new on the page)."""
    last: dict[str, str] = {}
    deadline = time.monotonic() + TIMEOUT
    while not condition(shown := _shown(browser)):
        if shown != last:
            last, deadline = shown, time.monotonic() + TIMEOUT
        elif time.monotonic() > deadline:
            pytest.fail(f"the page never showed {what}; last shown: {last}")
        time.sleep(POLL)
    return shown


def _click(browser: webdriver.Chrome, element_id: str) -> None:
    browser.find_element(By.ID, element_id).click()


@contextmanager
def followed(tmp_path: Path, view: tuple[str, str], browser: webdriver.Chrome,
             sid: str) -> Iterator[Future[SourceSummary]]:
    """A service connected to the view and the source of ``sid``, the operator page
    following the session from its step 3: the source's summary."""
    url, view_endpoint = view
    with service(tmp_path, (view_endpoint,)) as endpoint, source(sid, endpoint) as future:
        browser.get(f"{url}/?session={sid}&token={TOKEN}")
        _wait(browser, lambda s: s["status"] == "running" and int(s["step"]) >= 3, "step 3")
        yield future


def test_the_operator_page_pauses_marks_the_target_and_resumes_a_session(
    tmp_path: Path, view: tuple[str, str], browser: webdriver.Chrome,
) -> None:
    url = view[0]
    sid = "web-pause"
    with followed(tmp_path, view, browser, sid) as future:
        _click(browser, "c-pause")
        paused = _wait(browser, lambda s: s["status"] == "paused", "the pause")
        assert "paused by the operator at step" in _wait(
            browser, lambda s: "by the operator" in s["result"], "the answer")["result"]
        operator_tab = browser.current_window_handle
        browser.switch_to.new_window("tab")  # the subject's page shows the pause
        browser.get(f"{url}/subject?session={sid}&token={TOKEN}")
        WebDriverWait(browser, TIMEOUT).until(
            lambda b: b.find_element(By.ID, "message").text == "paused")
        browser.close()
        browser.switch_to.window(operator_tab)
        time.sleep(3 * IDLE)  # the pause itself: three idle timeouts
        still = _shown(browser)
        assert (still["status"], still["step"]) == ("paused", paused["step"])
        assert browser.find_element(By.ID, "c-pause").get_attribute("disabled") is not None
        browser.find_element(By.ID, "c-target").send_keys("4")
        _click(browser, "c-mark")
        _wait(browser, lambda s: "marked target 4" in s["result"], "the target marked")
        _click(browser, "c-resume")
        _wait(browser, lambda s: s["status"] == "ended" and s["step"] == str(STEPS), "the end")
        summary = future.result(TIMEOUT)
    assert summary.records == simulated(SEED)
    recording = read_recording(tmp_path / f"{sid}.mcap")
    step = int(paused["step"])
    logged = [(m["event"], m.get("step"), m.get("target"))
              for _, m in recording.messages["/event"] if "step" in m]
    assert logged == [("session_paused", step, None), ("target_marked", step, 4),
                      ("session_resumed", step, None)]
    assert replay_check(tmp_path / f"{sid}.mcap").divergence is None


def test_the_operator_page_ends_a_session_and_refuses_a_bad_command_inline(
    tmp_path: Path, view: tuple[str, str], browser: webdriver.Chrome,
) -> None:
    sid = "web-end"
    with followed(tmp_path, view, browser, sid) as future:
        browser.find_element(By.ID, "c-target").send_keys("99")
        _click(browser, "c-mark")  # no cell of the 3 x 3 grid: the service's error, inline
        _wait(browser, lambda s: "no task of the session's world" in s["result"], "the refusal")
        assert "refused" in browser.find_element(By.ID, "c-result").get_attribute("class")
        _click(browser, "c-end")
        WebDriverWait(browser, TIMEOUT).until(expected_conditions.alert_is_present())
        browser.switch_to.alert.accept()
        shown = _wait(browser, lambda s: s["status"] == "ended", "the end")
        summary = future.result(TIMEOUT)
    assert int(shown["step"]) < STEPS and "ended by the operator" in shown["result"]
    assert summary.records == simulated(SEED)[: summary.steps]
    last = read_recording(tmp_path / f"{sid}.mcap").messages["/event"][-1][1]
    assert (last["event"], last["step"]) == ("session_ended", int(shown["step"]))


def test_the_operator_page_starts_a_session_after_showing_the_services_refusal_inline(
    tmp_path: Path, view: tuple[str, str], browser: webdriver.Chrome,
) -> None:
    url, view_endpoint = view
    sid = "web-start"
    with service(tmp_path, (view_endpoint,)):
        browser.get(f"{url}/?token={TOKEN}")
        browser.find_element(By.CSS_SELECTOR, "#start summary").click()
        form = browser.find_element(By.ID, "start-form")
        fields = {"session": sid, "grid": str(GRID), "steps": str(STEPS), "seed": str(SEED),
                  "interval": str(INTERVAL), "learner": "eps=2"}
        for name, value in fields.items():
            field = form.find_element(By.NAME, name)
            field.clear()
            field.send_keys(value)
        _click(browser, "s-start")  # eps 2 is no learner's: the service's check, inline
        WebDriverWait(browser, TIMEOUT).until(
            lambda b: "eps" in b.find_element(By.ID, "s-result").text)
        result = browser.find_element(By.ID, "s-result")
        assert result.text.startswith("refused: bad config") and "refused" in (
            result.get_attribute("class"))
        form.find_element(By.NAME, "learner").clear()
        _click(browser, "s-start")
        WebDriverWait(browser, TIMEOUT).until(
            lambda b: b.find_element(By.ID, "s-result").text == f"started {sid}")
        _wait(browser, lambda s: s["session"] == sid and s["status"] == "ended"
              and s["step"] == str(STEPS), "the started session's end")
    moves = [m for _, m in read_recording(tmp_path / f"{sid}.mcap").messages["/move"]]
    trace = simulated(SEED)
    assert [(m["from_state"], m["action"]) for m in moves] == [(r.state, r.action)
                                                               for r in trace]
