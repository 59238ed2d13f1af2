"""The listening simulator writes an epoch for an onset as early as its EEG stream exists.

A stimulus program may show the first move as soon as the bridge has started the session,
which it does once it has found the amplifier's EEG stream: an onset can come right after
that stream appeared, and its epoch starts ``|tmin|`` before it. ``cfbci lsl-simulator
--onsets`` therefore opens that stream only once it listens to the onset markers (an LSL
inlet gets only what is pushed after it connected), and stamps its first sample ``|tmin|``
before, as an amplifier that was already running, so that such an onset's window is whole.

The test plays the stimulus program and the service's moves itself, in a process on the
test's LSL (``STIMULUS``): as soon as it has found the simulator's EEG stream it sends the
move and step 1's onset, stamped at the very moment the stream was created (``created_at``),
and checks the simulator wrote the whole epoch there.
"""

from __future__ import annotations

import os
import subprocess
import sys
from contextlib import ExitStack
from pathlib import Path

import numpy as np
from test_lsl import SFREQ, TIMEOUT, _start, _stop

from acquisition.lsl_streams import loopback_config
from wire.zenoh_config import free_tcp_endpoint

#: --marker-latency, s: the stimulus process pushes its marker once it has found the
#: simulator's stream and sent the move, within a few seconds on a loaded machine.
BUDGET = 6.0
TMAX = 1.0  # s, the synthetic epochs' end

STIMULUS = """
import queue, sys, time
import zenoh
from acquisition.lsl_streams import marker_outlet, resolve_inlet
from wire import protocol
from wire.transport import Outbox, Pump, wait_for_subscribers
from wire.zenoh_config import peer_config

session, eeg, onsets, endpoint, tmax = sys.argv[1:6]
with zenoh.open(peer_config([endpoint], [])) as link:
    # the truth's subscriber, which the simulator waits for (its truths are not read)
    pump = Pump(link, protocol.key(session, "truth"), "truth", queue.SimpleQueue())
    print("listening", flush=True)  # the simulator is started now, and connects at once
    outlet = marker_outlet(onsets, "test-stimulus")
    inlet = resolve_inlet(eeg, 60)
    opened = inlet.info().created_at()  # this machine's LSL clock when the stream appeared
    outbox = Outbox(link)
    assert wait_for_subscribers(outbox.publisher(protocol.key(session, "move")), 60)
    outbox.send("move", session, {"step": 1, "from_state": 12, "action": "up",
                                  "to_state": 7, "target_reached": False})
    outlet.push_sample(["onset 1"], opened)
    print("onset", repr(opened), flush=True)
    while True:  # until the simulator has streamed past the epoch's end
        _, stamps = inlet.pull_chunk(timeout=1.0)
        if stamps and stamps[-1] > opened + float(tmax):
            break
    assert wait_for_subscribers(outbox.publisher(protocol.key(session, "event")), 60)
    outbox.send("event", session, {"event": "session_ended", "message": "test",
                                   "config_t_ns": None})
    while outlet.have_consumers():  # the simulator leaves: no broken stream in its log
        time.sleep(0.05)
    pump.close()
    outbox.close()
"""


def test_an_onset_at_the_moment_the_eeg_stream_appeared_is_written_whole(
    tmp_path: Path,
) -> None:
    name = tmp_path.name[-40:]
    (tmp_path / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{name}"))
    endpoint = free_tcp_endpoint()
    eeg, onsets = f"eeg-{name}", f"onsets-{name}"
    with ExitStack() as running:
        stimulus = subprocess.Popen(
            [sys.executable, "-c", STIMULUS, name, eeg, onsets, endpoint, str(TMAX)],
            env=os.environ | {"LSLAPICFG": str(tmp_path / "lsl_api.cfg")},
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        running.callback(_stop, stimulus)
        assert stimulus.stdout is not None
        assert stimulus.stdout.readline() == "listening\n"
        simulator = _start(tmp_path, "simulator", "lsl-simulator", "--session", name,
                           "--connect", endpoint, "--timeout", "60", "--eeg", eeg,
                           "--onsets", onsets, "--marker-latency", str(BUDGET),
                           "--written", str(tmp_path / "written.npz"))
        running.callback(_stop, simulator)
        output, _ = stimulus.communicate(timeout=TIMEOUT)
        assert stimulus.returncode == 0, output
        assert simulator.wait(TIMEOUT) == 0, (tmp_path / "simulator.log").read_text()
    opened = float(output.split("onset ")[1].split()[0])
    with np.load(tmp_path / "written.npz", allow_pickle=False) as arrays:
        written = dict(arrays)
    simulator_log = (tmp_path / "simulator.log").read_text()
    assert list(written["steps"]) == [1], simulator_log
    onset = int(written["onsets"][0])
    assert onset == round((opened - float(written["t0"])) * SFREQ)
    # The whole window is in the stream: it starts at or after sample 0.
    assert int(written["starts"][0]) >= 0
    assert "late" not in simulator_log and "ERR" not in simulator_log
