"""The whole lab loop on one machine, the subject's screen a real headless Chromium:

    cfbci serve <- lsl-bridge <- EEG (LSL) <- lsl-simulator --onsets (amplifier and brain)
         |             | moves (LSL)                 ^ onset markers (LSL)
         +-- moves --> +--> cfbci view --stimulus --> subject page (frames) --+

Every part is a real process (the page in Chromium driven by Selenium), talking over
real LSL outlets kept on the loopback by an ``lsl_api.cfg`` of the test's own and over
loopback Zenoh. The session completes, ``cfbci lsl-check`` finds every recorded epoch
equal to what the simulator wrote at the page's onsets, and the moves are those of
``cfbci simulate`` for the seed. Two faults are made in the frames that show a step (a
test's wrapper of ``performance.mark``): the page's main thread stalled at step 2, the
page hidden at step 4 (a tab opened in front of it through Chrome's DevTools protocol):
both onsets are reported invalid, and the moves shown again. Without Chromium or its
driver the test skips (fails under ``CFBCI_REQUIRE_SYSTEM_DEPS=1``), as the view's
browser tests do.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
from selenium.webdriver.support.ui import WebDriverWait
from test_lsl import (
    SFREQ,
    TIMEOUT,
    LslSession,
    _stop,
    assert_session_is_the_simulation,
    listening_clients,
    listening_loop,
)
from test_view import browser

__all__ = ["browser"]  # the fixture, shared with tests/test_view.py

STEPS, SEED = 8, 4
INTERVAL = 0.3  # s between onsets, at least
TOKEN = "stimulus-test-token-0123456789"
#: Faults in the frames that first show a step: the main thread stalled for 0.2 s at
#: step 2; at step 4, the page hidden (another tab opened and closed by the test's hiding
#: server, which the frame calls synchronously: arguments[0]).
FAULTS = """
const hide = arguments[0];
const mark = performance.mark.bind(performance);
const done = new Set();
performance.mark = (name, options) => {
  const entry = mark(name, options);
  if (name === "onset 2" && !done.has(name)) {
    done.add(name);
    const end = performance.now() + 200;
    while (performance.now() < end) {}
  } else if (name === "onset 4" && !done.has(name)) {
    done.add(name);
    const request = new XMLHttpRequest();
    request.open("GET", hide, false);
    request.send();
  }
  return entry;
};
"""


async def _devtools(address: str, commands: list[tuple[str, dict[str, Any]]]) -> None:
    """Send commands to the browser itself over Chrome's DevTools protocol (not through
    chromedriver, which waits for a page that is busy), each after the last one's answer;
    the first one's ``targetId`` fills the ones after it."""
    async with aiohttp.ClientSession() as client:
        async with client.get(f"http://{address}/json/version") as answer:
            url = (await answer.json())["webSocketDebuggerUrl"]
        async with client.ws_connect(url) as socket:
            target = None
            for number, (method, params) in enumerate(commands, 1):
                await socket.send_json({"id": number, "method": method,
                                        "params": params | ({"targetId": target} if target
                                                            else {})})
                while (answer := await socket.receive_json(timeout=TIMEOUT)).get("id") != number:
                    pass  # events
                target = target or answer["result"].get("targetId")


class _Hider(BaseHTTPRequestHandler):
    """Answers a page's request after opening a tab in front of it and closing it again:
    the page goes hidden, then visible, while its frame waits for the answer."""

    devtools = ""  # the browser's DevTools address, host:port

    def do_GET(self) -> None:
        asyncio.run(_devtools(self.devtools, [("Target.createTarget", {"url": "about:blank"}),
                                              ("Target.closeTarget", {})]))
        self.send_response(204)
        self.send_header("Access-Control-Allow-Origin", "*")
        self.end_headers()

    def log_message(self, *_: Any) -> None:  # quiet
        pass


@contextmanager
def _hiding_server(browser: Any) -> Iterator[str]:
    """A `_Hider` on a free loopback port for ``browser``: its address."""
    address = browser.capabilities["goog:chromeOptions"]["debuggerAddress"]
    handler = type("Hider", (_Hider,), {"devtools": address})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/hide"
    finally:
        server.shutdown()
        thread.join()
        server.server_close()


def _view(tmp_path: Path, endpoint: str, names: dict[str, str]) -> Iterator[str]:
    """``cfbci view --stimulus`` as a process; yields the subject page's address."""
    env = os.environ | {"LSLAPICFG": str(tmp_path / "lsl_api.cfg"), "CFBCI_VIEW_TOKEN": TOKEN}
    with (tmp_path / "view.log").open("w") as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "cfbci.cli", "view", "--connect", endpoint, "--port", "0",
             "--stimulus", "--moves", names["moves"], "--onsets", names["onsets"],
             "--interval", str(INTERVAL), "--onset-log", str(tmp_path / "onsets.jsonl")],
            env=env, stdout=subprocess.PIPE, stderr=log, text=True,
        )
    try:
        assert process.stdout is not None
        for line in process.stdout:  # the addresses, once it serves
            if line.startswith("subject view: "):
                yield line.removeprefix("subject view: ").strip().replace("session=ID&", "")
                break
        else:
            pytest.fail(f"cfbci view did not start: {(tmp_path / 'view.log').read_text()}")
    finally:
        _stop(process)


def test_the_subject_page_is_the_stimulus_of_a_whole_session(tmp_path: Path, browser) -> None:
    with ExitStack() as running:
        name, endpoint, names, common = listening_loop(tmp_path, SEED, running)
        views = _view(tmp_path, endpoint, names)
        running.callback(views.close)
        browser.get(next(views))
        WebDriverWait(browser, TIMEOUT).until(
            lambda b: b.execute_script("return document.getElementById('view').dataset.stimulus")
            == "on"
        )
        browser.execute_script(FAULTS, running.enter_context(_hiding_server(browser)))
        simulator, bridge = listening_clients(tmp_path, running, names, common, STEPS, 1)
        logs = {role: tmp_path / f"{role}.log" for role in ("simulator", "bridge", "view")}
        assert bridge.wait(TIMEOUT) == 0, logs["bridge"].read_text()
        assert simulator.wait(TIMEOUT) == 0, logs["simulator"].read_text()
        marks = browser.execute_script(
            "return performance.getEntriesByType('mark').map(m => m.name)"
        )
    check = subprocess.run(
        [sys.executable, "-m", "cfbci.cli", "lsl-check", str(tmp_path / "written.npz"),
         str(tmp_path / f"{name}.mcap")], capture_output=True, text=True, timeout=TIMEOUT,
    )
    assert check.returncode == 0, check.stdout + check.stderr
    assert f"{STEPS} of {STEPS} recorded epochs equal" in check.stdout
    with np.load(tmp_path / "written.npz", allow_pickle=False) as arrays:
        written = dict(arrays)
    session = LslSession(json.loads((tmp_path / "bridge.json").read_text()),
                         tmp_path / f"{name}.mcap", tmp_path / "written.npz", written,
                         {role: path.read_text() for role, path in logs.items()})
    assert_session_is_the_simulation(session, STEPS, SEED)
    assert "too late" not in session.logs["simulator"]

    onsets = [json.loads(line) for line in (tmp_path / "onsets.jsonl").read_text().splitlines()]
    valid = [o for o in onsets if o["valid"]]
    assert [o["step"] for o in valid] == list(range(1, STEPS + 1))
    # The stalled frame's onset was invalid (a dropped frame), the hidden page's too, and
    # both steps were shown again.
    stalled = [o for o in onsets if o["step"] == 2 and not o["valid"]]
    assert stalled and stalled[0]["reason"] == "dropped-frame"
    assert stalled[0]["after_ms"] > 100 and stalled[0]["show"] < valid[1]["show"]
    assert marks.count("onset 2") == 1 + len(stalled)
    hidden = [o for o in onsets if o["step"] == 4 and not o["valid"]]
    assert hidden and hidden[0]["reason"] == "hidden"
    assert hidden[0]["show"] < valid[3]["show"]
    assert marks.count("onset 4") == 1 + len(hidden)
    assert {f"onset {step}" for step in range(1, STEPS + 1)} <= set(marks)
    for onset in onsets:
        assert 0 < onset["uncertainty_ms"] and 0 < onset["period_ms"]
    # The bridge cut each epoch around the sample nearest the page's onset, and the
    # simulator wrote it around the same sample.
    bridge = session.bridge
    assert [e["step"] for e in bridge["epochs"]] == list(range(1, STEPS + 1))
    cut = np.array([e["onset"] for e in bridge["epochs"]])
    assert np.all(np.abs(cut - [o["onset"] for o in valid]) <= 0.5 / SFREQ)
    np.testing.assert_array_equal(np.round((cut - written["t0"]) * SFREQ), written["onsets"])
