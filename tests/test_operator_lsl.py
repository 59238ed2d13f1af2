"""Sessions of LSL streams started from the operator page: real ``cfbci serve``, ``cfbci
view`` and ``cfbci lsl-simulator`` processes on an ``lsl_api.cfg`` of the test's own
(``LSLAPICFG``), the ``cfbci lsl-bridge`` the view starts, loopback Zenoh, the page in
headless Chromium or its HTTP endpoints. This process never calls liblsl's network
functions (as in tests/test_lsl.py).
"""

from __future__ import annotations

import json
import os
import queue
import shlex
import signal
import socket
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import pytest
import zenoh
from selenium import webdriver
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select, WebDriverWait
from test_lsl import TIMEOUT, _start, _stop
from test_operator_controls import TOKEN, Watch, _wait
from test_view import browser

from acquisition.lsl_simulator import check_recording
from acquisition.lsl_streams import loopback_config
from cfbci.service.router import READY
from replay.recording import read_recording
from wire.zenoh_config import free_tcp_endpoint, peer_config

__all__ = ["browser"]  # the fixture, shared with tests/test_view.py

STEPS, SEED = 12, 4


@dataclass
class View:
    """A ``cfbci view`` process: its address (without the token), its process and its
    output (with its bridges'), line by line."""

    url: str
    process: subprocess.Popen[str]
    lines: queue.SimpleQueue[str | None]

    def request(self, path: str, body: dict[str, Any] | None = None) -> tuple[int, Any]:
        """``GET`` (or ``POST`` ``body``) ``path``: the status and the JSON answer."""
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(f"{self.url}{path}?token={TOKEN}", data=data,
                                         headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(request, timeout=TIMEOUT) as response:
                return response.status, json.load(response)
        except urllib.error.HTTPError as error:
            return error.code, json.load(error)

    def children(self) -> list[int]:
        """The process ids of the view's child processes."""
        children = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            with suppress(OSError):  # a process that ended meanwhile
                fields = stat.read_text().rpartition(")")[2].split()
                if int(fields[1]) == self.process.pid:  # its parent
                    children.append(int(stat.parent.name))
        return children

    def streams(self, *names: str) -> list[dict[str, Any]]:
        """``GET /lsl-streams`` once it lists ``names`` (their programs may still be
        opening them)."""
        while True:
            status, answer = self.request("/lsl-streams")
            assert status == 200, answer
            if set(names) <= {stream["name"] for stream in answer["streams"]}:
                return answer["streams"]

    def until(self, text: str) -> str:
        """The next line of its output holding ``text``."""
        while (line := self.lines.get(timeout=TIMEOUT)) is not None:
            if text in line:
                return line
        pytest.fail(f"the view's output ended without {text!r}")

    def rest(self) -> str:
        """The rest of its output, once it has ended."""
        return "".join(iter(partial(self.lines.get, timeout=TIMEOUT), None))


def _lines(stream: Any, into: queue.SimpleQueue[str | None]) -> None:
    for line in stream:
        into.put(line)
    into.put(None)  # the end of the output


@contextmanager
def view_process(tmp_path: Path, *args: str) -> Iterator[View]:
    """``cfbci view ARGS`` on the test's LSL, once it serves; stopped with SIGTERM, which
    must end it cleanly."""
    env = os.environ | {"LSLAPICFG": str(tmp_path / "lsl_api.cfg"), "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen(
        [sys.executable, "-m", "cfbci.cli", "view", "--port", "0", "--token", TOKEN, *args],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: queue.SimpleQueue[str | None] = queue.SimpleQueue()
    threading.Thread(target=_lines, args=(process.stdout, lines), daemon=True).start()
    try:
        address = View("", process, lines).until("operator view: ").split()[-1]
        yield View(address.partition("/?")[0], process, lines)
    finally:
        _stop(process)
    assert process.returncode == 0


@dataclass
class Lab:
    """The test's LSL configuration, service and view."""

    tmp_path: Path
    service: str  # the service's Zenoh endpoint
    view: View


@contextmanager
def lab(tmp_path: Path) -> Iterator[Lab]:
    """``cfbci serve`` recording to ``tmp_path`` and a view connected to it."""
    (tmp_path / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{tmp_path.name[-40:]}"))
    endpoint = free_tcp_endpoint()
    with ExitStack() as running:
        serve = _start(tmp_path, "serve", "serve", "--listen", endpoint, "--record-dir",
                       str(tmp_path))
        running.callback(_stop, serve)
        view = running.enter_context(view_process(
            tmp_path, "--connect", endpoint, "--listen", free_tcp_endpoint()))
        yield Lab(tmp_path, endpoint, view)


@contextmanager
def simulator(place: Lab, name: str) -> Iterator[subprocess.Popen[bytes]]:
    """``cfbci lsl-simulator`` of session ``name``: streams ``eeg-NAME`` and
    ``markers-NAME``, answering the move stream ``moves-NAME``."""
    process = _start(place.tmp_path, f"simulator-{name}", "lsl-simulator", "--session", name,
                     "--seed", str(SEED), "--connect", place.service, "--moves",
                     f"moves-{name}", "--eeg", f"eeg-{name}", "--markers", f"markers-{name}",
                     "--onset-delay", "0.3", "--timeout", "120", "--written",
                     str(place.tmp_path / f"{name}.npz"))
    try:
        yield process
    finally:
        _stop(process)


def _choices(name: str, **more: Any) -> dict[str, Any]:
    return {"source": "lsl", "session": name, "eeg": f"eeg-{name}",
            "markers": f"markers-{name}", "moves": f"moves-{name}", "steps": STEPS,
            "seed": SEED, **more}


def _fill(browser: webdriver.Chrome, name: str, value: str) -> None:
    field = browser.find_element(By.ID, "start-form").find_element(By.NAME, name)
    field.clear()
    field.send_keys(value)


def _text(browser: webdriver.Chrome, element_id: str) -> str:
    return browser.find_element(By.ID, element_id).text


def test_the_page_lists_the_streams_and_starts_an_lsl_session_that_runs(
    tmp_path: Path, browser: webdriver.Chrome,
) -> None:
    name = "page-lsl"
    with lab(tmp_path) as place, simulator(place, name):
        place.view.streams(f"eeg-{name}", f"markers-{name}")  # the simulator's are up
        browser.get(f"{place.view.url}/?token={TOKEN}")
        browser.find_element(By.CSS_SELECTOR, "#start summary").click()
        Select(browser.find_element(By.NAME, "source")).select_by_value("lsl")
        rows = "#s-streams tbody tr"
        WebDriverWait(browser, TIMEOUT).until(lambda b: len(b.find_elements(
            By.CSS_SELECTOR, rows)) >= 2)
        table = {row.find_elements(By.TAG_NAME, "td")[0].text: [
            cell.text for cell in row.find_elements(By.TAG_NAME, "td")[1:]]
            for row in browser.find_elements(By.CSS_SELECTOR, rows)}
        host = socket.gethostname()
        eeg_type, channels, rate, eeg_host = table[f"eeg-{name}"]
        assert (eeg_type, rate, eeg_host) == ("EEG", "256", host) and int(channels) > 1
        assert table[f"markers-{name}"] == ["Markers", "1", "irregular", host]
        for field, value in (("session", name), ("steps", str(STEPS)), ("seed", str(SEED)),
                             ("eeg", "no-such-amplifier"), ("moves", f"moves-{name}")):
            _fill(browser, field, value)
        browser.find_element(By.XPATH, f"//td[text()='markers-{name}']").click()
        browser.find_element(By.ID, "s-start").click()  # no such stream: refused, inline
        WebDriverWait(browser, TIMEOUT).until(lambda b: "refused" in _text(b, "s-result"))
        assert _text(browser, "s-result").startswith(
            "refused: no LSL stream named 'no-such-amplifier' (the EEG stream) on the network")
        assert f"eeg-{name}" in _text(browser, "s-result")  # the streams it found
        browser.find_element(By.XPATH, f"//td[text()='eeg-{name}']").click()
        browser.find_element(By.ID, "s-start").click()
        WebDriverWait(browser, TIMEOUT).until(
            lambda b: _text(b, "s-result") == f"started {name}")
        shown = _text(browser, "s-command").removeprefix("the same from a terminal: ")
        command = shlex.split(shown)
        assert command[:8] == ["cfbci", "lsl-bridge", "--eeg", f"eeg-{name}", "--markers",
                               f"markers-{name}", "--session", name]
        # The view runs that very command line (the CLI), connected to its endpoints.
        (bridge,) = place.view.children()
        ran = Path(f"/proc/{bridge}/cmdline").read_text().split("\0")[:-1]
        assert ran == [sys.executable, "-m", "cfbci.cli", *command[1:]]
        _wait(browser, lambda s: s["session"] == name and s["status"] == "ended"
              and s["step"] == str(STEPS), "the session's end")
        place.view.until(f"session {name!r}: {STEPS} epochs published")  # the bridge ended
    recording = tmp_path / f"{name}.mcap"
    assert [m["step"] for m in read_recording(recording).accepted_epochs()] == list(
        range(1, STEPS + 1))
    comparison = check_recording(tmp_path / f"{name}.npz", recording)
    assert (comparison.recorded, comparison.equal) == (STEPS, STEPS)
    assert int(channels) == len(read_recording(recording).config["ch_names"])


def test_bad_choices_are_refused_saying_what(tmp_path: Path) -> None:
    name = "bad-lsl"
    with lab(tmp_path) as place:
        with simulator(place, name):
            listed = place.view.streams(f"eeg-{name}", f"markers-{name}")
            roles = {s["name"]: s["role"] for s in listed}
            assert roles == {f"eeg-{name}": "eeg", f"markers-{name}": "markers"}
            for choices, refusal in [
                (_choices(name, eeg="nothing"), "no LSL stream named 'nothing' (the EEG stream)"),
                (_choices(name, eeg=f"markers-{name}"),
                 f"LSL stream 'markers-{name}' has an irregular rate; EEG needs a nominal"),
                (_choices(name, markers=f"eeg-{name}"),
                 f"LSL stream 'eeg-{name}' (type 'EEG') does not carry strings"),
                (_choices(name, moves=f"markers-{name}"),
                 f"an LSL stream named 'markers-{name}' is on the network already"),
                (_choices(name, photodiode="AUX9"),
                 "--photodiode 'AUX9': the EEG stream has no such channel"),
                (_choices(name, tmin=1.0), "--tmax (1.0 s) must be after --tmin (1.0 s)"),
                (_choices(name, steps=0), "field 'steps' must be in 1.."),
                (_choices(name, learner={"eps": 2}), "bad config"),
                (_choices(name, session="a b"), "session"),
                (_choices(name, eeg=None), "choose the EEG stream"),
                (_choices(name, amplifier="x"), "unknown setting(s) amplifier"),
                ({**_choices(name), "source": "xdf"}, "setting 'source' must be"),
            ]:
                status, answer = place.view.request("/start", choices)
                assert status == 400 and refusal in answer["error"], (choices, answer)
        status, answer = place.view.request("/start", _choices(name))  # its program ended
        assert status == 400 and answer["error"] == (
            f"the EEG stream 'eeg-{name}' is gone: it was listed, and no longer answers (has "
            "its program stopped?)")
        assert place.view.request("/start") == (200, {"disabled": None, "started": []})


def test_the_bridge_a_view_started_stops_with_the_view(tmp_path: Path) -> None:
    name = "stop-lsl"
    with lab(tmp_path) as place, simulator(place, name) as simulated:
        place.view.streams(f"eeg-{name}", f"markers-{name}")
        status, answer = place.view.request("/start", _choices(name, steps=500))
        assert status == 200 and answer["started"] == name, answer
        assert answer["command"].startswith(f"cfbci lsl-bridge --eeg eeg-{name} ")
        (bridge,) = place.view.children()
        with zenoh.open(peer_config((), [place.service])) as session:
            watch = Watch(session, name)
            watch.until_move(3)  # the session runs
            watch.close()
        assert place.view.request("/start")[1]["started"] == [
            {"session": name, "command": answer["command"], "exit": None}]
        place.view.process.send_signal(signal.SIGTERM)
        assert place.view.process.wait(TIMEOUT) == 0
        assert not Path(f"/proc/{bridge}").exists()  # ended, and waited for
        assert f"session {name!r}: " in place.view.rest()  # its summary: it ended cleanly
        assert simulated.wait(TIMEOUT) == 0  # its move stream ended with the bridge
    events = [m["event"] for _, m in read_recording(tmp_path / f"{name}.mcap").messages["/event"]]
    assert "session_started" in events


def test_a_view_that_is_a_router_client_starts_nothing_and_says_why(
    tmp_path: Path, browser: webdriver.Chrome,
) -> None:
    (tmp_path / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{tmp_path.name[-40:]}"))
    endpoint = free_tcp_endpoint()
    (tmp_path / "client.json5").write_text(
        json.dumps({"mode": "client", "connect": {"endpoints": [endpoint]}}))
    router = subprocess.Popen([sys.executable, "-m", "cfbci.cli", "router", "--listen",
                               endpoint], stdout=subprocess.PIPE, text=True)
    try:
        assert router.stdout is not None and READY in router.stdout.readline()
        with view_process(tmp_path, "--zenoh-config", str(tmp_path / "client.json5")) as view:
            status, answer = view.request("/start")
            reason = answer["disabled"]
            assert status == 200 and reason.startswith(
                "Starting sessions here is off: this view logs in to Zenoh in client mode")
            assert view.request("/start", _choices("s")) == (400, {"error": reason})
            browser.get(f"{view.url}/?token={TOKEN}")
            browser.find_element(By.CSS_SELECTOR, "#start summary").click()
            WebDriverWait(browser, TIMEOUT).until(lambda b: _text(b, "s-disabled") == reason)
            assert browser.find_element(By.ID, "s-start").is_enabled() is False
    finally:
        _stop(router)
