"""Onsets from a photodiode channel (``acquisition.photodiode``): the crossing rule on
known samples, and a whole session where ``cfbci lsl-simulator --photodiode 0.04`` writes
a pulse 40 ms after each marker (a display's delay) and ``cfbci lsl-bridge --photodiode``
takes the onsets from it. Real processes on a loopback LSL of the test's own, as in
tests/test_lsl.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
from test_lsl import SFREQ, TIMEOUT, LslSession, _start, _stop, assert_session_is_the_simulation
from test_view import browser

from acquisition.lsl_epochs import Refusal, SampleBuffer
from acquisition.lsl_streams import loopback_config
from acquisition.photodiode import (
    PHOTODIODE_CHANNEL,
    PULSE_LEVEL,
    PhotodiodeRule,
    crossings_after,
)
from replay.recording import read_recording
from wire.zenoh_config import free_tcp_endpoint

__all__ = ["browser"]  # the fixture, shared with tests/test_view.py
DELAY = 0.04  # s, the simulated display's delay
DELAY_SAMPLES = round(DELAY * SFREQ)


def _buffer(photodiode: np.ndarray) -> SampleBuffer:
    """Two channels, EEG (the index) and the photodiode, stamped index / SFREQ."""
    buffer = SampleBuffer(2, SFREQ, 10.0)
    index = np.arange(len(photodiode))
    buffer.append(np.column_stack([index, photodiode]).astype(np.float32), index / SFREQ, 0)
    return buffer


def test_the_onset_is_the_one_crossing_after_the_marker() -> None:
    light = np.zeros(400)
    light[110:123] = 800.0  # lit from sample 110; the marker at sample 100
    photodiode = PhotodiodeRule("PD").bind(["Cz", "PD"], SFREQ)
    assert photodiode.locate(_buffer(light), 100 / SFREQ) == 110 / SFREQ
    assert photodiode.locate(_buffer(light[:120]), 100 / SFREQ) is None  # window not whole
    # A falling pulse is found too, and an explicit threshold is the level crossed.
    assert photodiode.locate(_buffer(-light), 100 / SFREQ) == 110 / SFREQ
    ramp = np.concatenate([np.zeros(100), np.arange(300.0)])
    assert crossings_after(ramp, 100, 50.0) == [50 + 100]
    # The epoch drops the photodiode's row.
    assert photodiode.strip(np.arange(6.0).reshape(2, 3)).tolist() == [[0.0, 1.0, 2.0]]
    assert photodiode.eeg_names(["Cz", "PD"]) == ["Cz"]


@pytest.mark.parametrize(
    ("lit", "why"),
    [([], "no photodiode crossing"), ([(105, 108), (112, 120)], "2 photodiode crossings"),
     ([(100 + 30, 140)], "no photodiode crossing")],  # after the 0.1 s window
)
def test_no_crossing_or_two_refuse_the_window(lit: list[tuple[int, int]], why: str) -> None:
    rng = np.random.default_rng(0)
    light = rng.normal(0, 2.0, 400)  # noise: no pulse is 10 robust spreads above it
    for start, stop in lit:
        light[start:stop] = PULSE_LEVEL
    found = PhotodiodeRule("PD").bind(["Cz", "PD"], SFREQ).locate(_buffer(light), 100 / SFREQ)
    assert isinstance(found, Refusal) and why in found.reason
    assert "'PD' within 0.1 s after the marker" in found.reason


def test_a_missing_channel_is_named() -> None:
    with pytest.raises(ValueError, match=r"--photodiode 'PD'.*no such channel.*Cz, Pz"):
        PhotodiodeRule("PD").bind(["Cz", "Pz"], SFREQ)
    with pytest.raises(ValueError, match="--photodiode-window"):
        PhotodiodeRule("PD", window=0.0)


def test_a_session_takes_its_onsets_from_the_photodiode(tmp_path: Path) -> None:
    steps, seed = 12, 4
    name = tmp_path.name[-40:]
    (tmp_path / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{name}"))
    endpoint = free_tcp_endpoint()
    common = ["--session", name, "--seed", str(seed), "--connect", endpoint,
              "--moves", f"moves-{name}", "--timeout", "60", "--eeg", f"eeg-{name}",
              "--markers", f"markers-{name}"]
    with ExitStack() as running:
        serve = _start(tmp_path, "serve", "serve", "--listen", endpoint, "--record-dir",
                       str(tmp_path))
        running.callback(_stop, serve)
        simulator = _start(tmp_path, "simulator", "lsl-simulator", *common, "--onset-delay",
                           "0.3", "--photodiode", str(DELAY), "--written",
                           str(tmp_path / "written.npz"))
        running.callback(_stop, simulator)
        bridge = _start(tmp_path, "bridge", "lsl-bridge", *common, "--steps", str(steps),
                        "--photodiode", PHOTODIODE_CHANNEL, "--json",
                        str(tmp_path / "bridge.json"))
        running.callback(_stop, bridge)
        logs = {role: tmp_path / f"{role}.log" for role in ("simulator", "bridge")}
        assert bridge.wait(TIMEOUT) == 0, logs["bridge"].read_text()
        assert simulator.wait(TIMEOUT) == 0, logs["simulator"].read_text()
    with np.load(tmp_path / "written.npz", allow_pickle=False) as arrays:
        written = dict(arrays)
    report = json.loads((tmp_path / "bridge.json").read_text())
    session = LslSession(report, tmp_path / f"{name}.mcap", tmp_path / "written.npz", written,
                         {role: path.read_text() for role, path in logs.items()})
    # Every recorded epoch equals the one written around the pulse, the session's moves
    # are those of cfbci simulate for the seed.
    assert_session_is_the_simulation(session, steps, seed)
    assert report["refused"] == []
    # The bridge's onsets are the pulses' first samples, 40 ms (10 samples) after the
    # markers' samples.
    onsets = np.array([e["onset"] for e in report["epochs"]])
    markers = np.array([e["marker"] for e in report["epochs"]])
    np.testing.assert_array_equal(np.round((onsets - written["t0"]) * SFREQ), written["onsets"])
    np.testing.assert_array_equal(np.round((onsets - markers) * SFREQ), DELAY_SAMPLES)
    assert "photodiode onsets after their markers: median 39.1 ms" in session.logs["bridge"]
    # The photodiode is no channel of the session: not in its config, not in its epochs.
    recording = read_recording(session.recording)
    (_, message), = recording.messages["/config"]
    names = message["config"]["ch_names"]
    assert names == ["Fz", "FCz", "Cz", "Pz"]  # the simulator's EEG, without "Photodiode"
    for _, epoch in recording.messages["/epoch"]:
        assert epoch["ch_names"] == names and epoch["shape"][0] == len(names)


#: A bridge's move stream in a process of its own: one move, pushed once the view reads the
#: stream; the outlet stays until stdin closes.
_ONE_MOVE = """
import sys
from acquisition.lsl_streams import marker_outlet, move_marker
outlet = marker_outlet(sys.argv[1], "test-moves")
assert outlet.wait_for_consumers(60)
move = {"step": 1, "from_state": 0, "action": "right", "to_state": 1, "target_reached": False}
outlet.push_sample([move_marker(move, 0)])
sys.stdin.read()
"""
#: Each frame's timestamp and the patch's colour after the page's own frame callback
#: (registered earlier, it runs first in every frame).
_PATCH_LOG = """
window.patchLog = [];
const patch = document.getElementById("photodiode-patch");
const log = (t) => { window.patchLog.push([t, patch.style.background]);
                     requestAnimationFrame(log); };
requestAnimationFrame(log);
"""


def test_the_subject_page_lights_its_photodiode_patch_in_the_onset_frame(
    tmp_path: Path, browser
) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    name = tmp_path.name[-40:]
    (tmp_path / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{name}"))
    env = os.environ | {"LSLAPICFG": str(tmp_path / "lsl_api.cfg"),
                        "CFBCI_VIEW_TOKEN": "photodiode-test-token-0123456789"}
    with ExitStack() as running, (tmp_path / "view.log").open("w") as log:
        view = subprocess.Popen(
            [sys.executable, "-m", "cfbci.cli", "view", "--connect", free_tcp_endpoint(),
             "--port", "0", "--stimulus", "--moves", f"moves-{name}", "--onsets",
             f"onsets-{name}", "--interval", "0.2", "--photodiode-patch"],
            env=env, stdout=subprocess.PIPE, stderr=log, text=True)
        running.callback(_stop, view)
        assert view.stdout is not None
        address = next(line for line in view.stdout if line.startswith("subject view: "))
        browser.get(address.removeprefix("subject view: ").strip().replace("session=ID&", ""))
        WebDriverWait(browser, TIMEOUT).until(lambda b: b.execute_script(
            "return document.getElementById('view').dataset.stimulus") == "on")
        browser.execute_script(_PATCH_LOG)
        bridge = subprocess.Popen([sys.executable, "-c", _ONE_MOVE, f"moves-{name}"], env=env,
                                  stdin=subprocess.PIPE, text=True)
        running.callback(bridge.wait, TIMEOUT)
        running.callback(bridge.communicate, "")
        onset = WebDriverWait(browser, TIMEOUT).until(lambda b: b.execute_script(
            "const m = performance.getEntriesByName('onset 1');"
            "return m.length && window.patchLog.filter(([t]) => t > m[0].startTime).length >= 5"
            " ? m[0].startTime : null"))
        frames = browser.execute_script("return window.patchLog")
    colours = {t: colour for t, colour in frames}
    after = sorted(t for t in colours if t >= onset)
    assert after[0] == onset  # the patch's frame is the onset's
    assert [colours[t] for t in after[:5]] == ["white"] * 3 + ["black"] * 2
    assert {colours[t] for t in colours if t < onset} == {"black"}
