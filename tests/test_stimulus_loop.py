"""The whole lab loop on one machine, the subject's screen a real headless Chromium:

    cfbci serve <- lsl-bridge <- EEG (LSL) <- lsl-simulator --onsets (amplifier and brain)
         |             | moves (LSL)                 ^ onset markers (LSL)
         +-- moves --> +--> cfbci view --stimulus --> subject page (frames) --+

Every part is a real process (the page in Chromium driven by Selenium), talking over
real LSL outlets kept on the loopback by an ``lsl_api.cfg`` of the test's own and over
loopback Zenoh. The session completes, ``cfbci lsl-check`` finds every recorded epoch
equal to what the simulator wrote at the page's onsets, and the moves are those of
``cfbci simulate`` for the seed. The page's main thread is stalled once, in the frame that
shows step 2 (a test's wrapper of ``performance.mark``): that onset is reported invalid,
and the move is shown again. Without Chromium or its driver the test skips (fails under
``CFBCI_REQUIRE_SYSTEM_DEPS=1``), as the view's browser tests do.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
from selenium.webdriver.support.ui import WebDriverWait
from test_lsl import SFREQ, TIMEOUT, LslSession, _start, _stop, assert_session_is_the_simulation
from test_view import browser

from acquisition.lsl_streams import loopback_config
from wire.zenoh_config import free_tcp_endpoint

__all__ = ["browser"]  # the fixture, shared with tests/test_view.py

STEPS, SEED = 8, 4
INTERVAL = 0.3  # s between onsets, at least
TOKEN = "stimulus-test-token-0123456789"
#: Stall the page's main thread for 0.2 s in the frame that first shows step 2.
STALL = """
const mark = performance.mark.bind(performance);
window.stalled = false;
performance.mark = (name, options) => {
  const entry = mark(name, options);
  if (name === "onset 2" && !window.stalled) {
    window.stalled = true;
    const end = performance.now() + 200;
    while (performance.now() < end) {}
  }
  return entry;
};
"""


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


def _page(browser: object, script: str) -> object:
    return browser.execute_script(script)  # type: ignore[attr-defined]


def test_the_subject_page_is_the_stimulus_of_a_whole_session(tmp_path: Path, browser) -> None:
    name = tmp_path.name[-40:]
    (tmp_path / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{name}"))
    endpoint = free_tcp_endpoint()
    names = {kind: f"{kind}-{name}" for kind in ("moves", "onsets", "eeg")}
    common = ["--session", name, "--seed", str(SEED), "--connect", endpoint,
              "--timeout", "60", "--eeg", names["eeg"]]
    with ExitStack() as running:
        serve = _start(tmp_path, "serve", "serve", "--listen", endpoint, "--record-dir",
                       str(tmp_path))
        running.callback(_stop, serve)
        views = _view(tmp_path, endpoint, names)
        running.callback(views.close)
        browser.get(next(views))
        WebDriverWait(browser, TIMEOUT).until(
            lambda b: _page(b, "return document.getElementById('view').dataset.stimulus")
            == "on"
        )
        _page(browser, STALL)
        simulator = _start(tmp_path, "simulator", "lsl-simulator", *common, "--onsets",
                           names["onsets"], "--marker-latency", "1",
                           "--written", str(tmp_path / "written.npz"))
        running.callback(_stop, simulator)
        bridge = _start(tmp_path, "bridge", "lsl-bridge", *common, "--markers",
                        names["onsets"], "--moves", names["moves"], "--steps", str(STEPS),
                        "--json", str(tmp_path / "bridge.json"))
        running.callback(_stop, bridge)
        logs = {role: tmp_path / f"{role}.log" for role in ("simulator", "bridge", "view")}
        assert bridge.wait(TIMEOUT) == 0, logs["bridge"].read_text()
        assert simulator.wait(TIMEOUT) == 0, logs["simulator"].read_text()
        marks = _page(browser, "return performance.getEntriesByType('mark').map(m => m.name)")
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
    # The stalled frame's onset was invalid (a dropped frame), and step 2 shown again.
    stalled = [o for o in onsets if o["step"] == 2 and not o["valid"]]
    assert stalled and stalled[0]["reason"] == "dropped-frame"
    assert stalled[0]["after_ms"] > 100 and stalled[0]["show"] < valid[1]["show"]
    assert marks.count("onset 2") == 1 + len(stalled)
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
