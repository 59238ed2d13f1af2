"""Onset markers that arrive after their timestamp, in the listening simulator.

``cfbci lsl-simulator --onsets`` runs its EEG ``|tmin| + --marker-latency`` behind real
time, so that a marker arriving late, within that budget, still finds its epoch's samples
unsent: the epoch is written at the marker's own timestamp, and the bridge cuts exactly
what was written. A marker later than the budget finds the epoch's first samples sent:
nothing is written, and the simulator says so (a warning per marker, and its summary).

One whole session: ``cfbci serve``, ``lsl-simulator --onsets`` and ``lsl-bridge`` as
processes (`tests/test_lsl.py`'s), and a stimulus program of the test's own, a process
with a real LSL marker outlet: it takes each move from the bridge's move stream and pushes
``onset <step>`` stamped `LATE` seconds before the moment it pushes it (after the move:
the bridge ignores an onset that precedes its move).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from test_lsl import SFREQ, TIMEOUT, _stop, listening_clients, listening_loop

STEPS, SEED = 6, 4
#: --marker-latency, s: ample for the markers that are not made late, which a loaded
#: machine can deliver half a second after their timestamp.
BUDGET = 2.0
#: Seconds between an onset's timestamp and its marker's push, by step (others: none):
#: step 2 late within the budget, step 4 beyond it.
LATE = {2: 1.0, 4: 4.0}

STIMULUS = """
import json, sys, time
import pylsl
from pylsl.util import LostError
from acquisition.lsl_streams import marker_outlet, parse_move_marker, resolve_inlet

moves, onsets, late, log = sys.argv[1], sys.argv[2], json.loads(sys.argv[3]), sys.argv[4]
outlet = marker_outlet(onsets, "test-stimulus")
inlet = resolve_inlet(moves, 60)
with open(log, "w") as pushed:
    while True:
        try:
            values, _ = inlet.pull_chunk(timeout=0.2)
        except LostError:
            break
        for value in values:
            move = parse_move_marker(value[0])
            step = move["step"]
            delay = late.get(str(step), 0.0) if move["repeat"] == 0 else 0.0
            time.sleep(delay + 0.05)  # the onset, stamped 0.05 s after the move came
            stamp = pylsl.local_clock() - delay
            outlet.push_sample([f"onset {step}"], stamp)
            pushed.write(json.dumps({"step": step, "stamp": stamp}) + "\\n")
            pushed.flush()
"""


@dataclass(frozen=True)
class Session:
    written: dict[str, np.ndarray]
    stamps: dict[int, float]  # step -> its (first) onset marker's timestamp
    simulator_log: str
    bridge: dict
    check: subprocess.CompletedProcess[str]


def _stimulus(tmp_path: Path, names: dict[str, str], pushed: Path) -> subprocess.Popen:
    """`STIMULUS` as a process on the test's LSL, its output in ``stimulus.log``."""
    env = os.environ | {"LSLAPICFG": str(tmp_path / "lsl_api.cfg")}
    with (tmp_path / "stimulus.log").open("w") as log:
        return subprocess.Popen(
            [sys.executable, "-c", STIMULUS, names["moves"], names["onsets"], json.dumps(LATE),
             str(pushed)], env=env, stdout=log, stderr=subprocess.STDOUT)


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Session]:
    tmp_path = tmp_path_factory.mktemp("late-onsets")
    with ExitStack() as running:
        name, _, names, common = listening_loop(tmp_path, SEED, running)
        simulator, bridge = listening_clients(tmp_path, running, names, common, STEPS, BUDGET)
        stimulus = _stimulus(tmp_path, names, tmp_path / "pushed.jsonl")
        running.callback(_stop, stimulus)
        logs = {role: tmp_path / f"{role}.log" for role in ("simulator", "bridge", "stimulus")}
        assert bridge.wait(TIMEOUT) == 0, logs["bridge"].read_text()
        assert simulator.wait(TIMEOUT) == 0, logs["simulator"].read_text()
        assert stimulus.wait(TIMEOUT) == 0, logs["stimulus"].read_text()
    check = subprocess.run(
        [sys.executable, "-m", "cfbci.cli", "lsl-check", str(tmp_path / "written.npz"),
         str(tmp_path / f"{name}.mcap")], capture_output=True, text=True, timeout=TIMEOUT,
    )
    with np.load(tmp_path / "written.npz", allow_pickle=False) as arrays:
        written = dict(arrays)
    stamps: dict[int, float] = {}
    for line in (tmp_path / "pushed.jsonl").read_text().splitlines():
        pushed = json.loads(line)
        stamps.setdefault(pushed["step"], pushed["stamp"])
    yield Session(written, stamps, logs["simulator"].read_text(),
                  json.loads((tmp_path / "bridge.json").read_text()), check)


def test_a_marker_late_within_the_budget_is_written_at_its_own_timestamp(
    session: Session,
) -> None:
    written = session.written
    assert list(session.stamps) == list(range(1, STEPS + 1))
    assert 2 in written["steps"]
    for step, onset in zip(written["steps"], written["onsets"], strict=True):
        # The onset sample is the marker's timestamp's, late or not (the sample stamps are
        # t0 + n / sfreq; the marker stream is this machine's).
        assert onset == round((session.stamps[int(step)] - written["t0"]) * SFREQ), step
    # The bridge cut what was written (lsl-check: equal sample for sample), the late
    # marker's epoch included.
    assert "step 2:" not in session.check.stdout
    assert [e["step"] for e in session.bridge["epochs"]] == list(range(1, STEPS + 1))
    assert session.bridge["refused"] == [] and session.bridge["gaps"] == []
    assert "onset of step 2 came" not in session.simulator_log


def test_a_marker_later_than_the_budget_is_reported_and_nothing_is_written(
    session: Session,
) -> None:
    assert sorted(int(s) for s in session.written["steps"]) == [1, 2, 3, 5, 6]
    log = session.simulator_log
    assert "onset of step 4 came" in log and "nothing written" in log
    assert "1 onset markers came too late to be written (steps [4])" in log
    # lsl-check finds the bridge's epoch of step 4 (the background there) not written,
    # and every other one equal; it exits 1.
    assert session.check.returncode == 1, session.check.stdout + session.check.stderr
    assert "step 4: recorded, never written" in session.check.stdout
    assert f"{STEPS - 1} of {STEPS} recorded epochs equal" in session.check.stdout
    # The bridge used the late markers (their windows were whole) and reported them (more
    # than its --late-marker, 0.5 s, late; on a loaded machine an on-time one may be too).
    assert {2, 4} <= {m["step"] for m in session.bridge["late_markers"]}
