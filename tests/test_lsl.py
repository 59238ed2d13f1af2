"""LSL in and out: the bridge's sample buffer, and whole sessions over LSL.

The sessions run real processes (``cfbci serve``, ``cfbci lsl-simulator`` and
``cfbci lsl-bridge``), talking over real LSL outlets and inlets kept on the loopback by
an ``lsl_api.cfg`` of the test's own (``LSLAPICFG``; a session id per test, so parallel
tests do not see each other's streams) and over loopback Zenoh; where a test must start
the service at a moment of its choosing, the service runs in this process, on the test's
Zenoh session. This process never calls liblsl's network functions.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pylsl
import pytest
import zenoh

from acquisition.lsl_epochs import Epoch, Refusal, SampleBuffer, apply_baseline
from acquisition.lsl_simulator import check_recording
from acquisition.lsl_streams import (
    eeg_stream_meta,
    loopback_config,
    move_marker,
    parse_move_marker,
    parse_onset_marker,
)
from acquisition.sources import DataSpec
from cfbci.offline.simulation import SessionConfig, run_session
from cfbci.service import PipelineService
from replay.recording import read_recording
from wire import protocol
from wire.transport import Outbox, Pump, Received
from wire.zenoh_config import free_tcp_endpoint, peer_config

SFREQ = 256.0
TIMEOUT = 300  # failure guard, seconds


def stream(n: int, start: int = 0, n_channels: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Samples whose value is their index (every channel), stamped index / SFREQ."""
    index = np.arange(start, start + n)
    samples = np.repeat(index[:, None], n_channels, axis=1).astype(np.float32)
    return samples, index / SFREQ


# -- the sample buffer ------------------------------------------------------------------


def test_cut_takes_the_nearest_onset_sample_and_waits_for_the_window() -> None:
    buffer = SampleBuffer(2, SFREQ, seconds=10)
    for start in range(0, 400, 8):  # in chunks, as an inlet delivers them
        buffer.append(*stream(8, start), arrival_ns=start)
        result = buffer.cut(100.4 / SFREQ, -51, 256)  # nearest sample: 100
        if start + 8 <= 356:  # sample 356 not there yet
            assert result is None
    assert isinstance(result, Epoch)
    assert result.data.dtype == np.float32 and result.data.shape == (2, 308)
    np.testing.assert_array_equal(result.data[0], np.arange(49, 357))
    assert result.onset_index == 100 and result.onset_time == 100 / SFREQ
    assert result.last_arrival_ns == 352  # the chunk holding sample 356 arrived at "352"


def test_dropped_samples_are_a_gap_and_no_window_spans_it() -> None:
    buffer = SampleBuffer(2, SFREQ, seconds=10)
    assert buffer.append(*stream(200), arrival_ns=0) == []
    gaps = buffer.append(*stream(300, start=230), arrival_ns=1)  # 200..229 dropped
    assert [(g.index, g.missing) for g in gaps] == [(200, 30)]
    assert gaps[0].before == 199 / SFREQ and gaps[0].after == 230 / SFREQ
    spanning = buffer.cut(150 / SFREQ, -20, 80)
    assert isinstance(spanning, Refusal) and "spans the gap" in spanning.reason
    reaching_back = buffer.cut(240 / SFREQ, -20, 80)
    assert isinstance(reaching_back, Refusal) and "starts before the gap" in reaching_back.reason
    in_gap = buffer.cut(215 / SFREQ, -20, 80)
    assert isinstance(in_gap, Refusal) and "falls in a gap" in in_gap.reason
    after = buffer.cut(300 / SFREQ, -20, 80)  # wholly after the gap: samples 280..380
    assert isinstance(after, Epoch)
    np.testing.assert_array_equal(after.data[1], np.arange(280, 381))
    before = buffer.cut(100 / SFREQ, -20, 80)  # wholly before it
    assert isinstance(before, Epoch)
    np.testing.assert_array_equal(before.data[0], np.arange(80, 181))


def test_jitter_within_tolerance_is_no_gap_but_backwards_timestamps_are() -> None:
    buffer = SampleBuffer(1, SFREQ, seconds=10)
    samples, times = stream(100, n_channels=1)
    jitter = np.random.default_rng(0).uniform(-0.2, 0.2, 100) / SFREQ
    assert buffer.append(samples, times + jitter, arrival_ns=0) == []
    samples, times = stream(10, start=100, n_channels=1)
    gaps = buffer.append(samples, times - 50 / SFREQ, arrival_ns=0)  # the clock went back
    assert [(g.index, g.missing) for g in gaps] == [(100, -50)]
    assert "out of order" in gaps[0].describe()


def test_an_onset_older_than_the_buffer_is_refused() -> None:
    buffer = SampleBuffer(2, SFREQ, seconds=1)  # 256 samples
    buffer.append(*stream(1000), arrival_ns=0)
    old = buffer.cut(700 / SFREQ, -10, 10)
    assert isinstance(old, Refusal) and "before the oldest buffered sample" in old.reason
    edge = buffer.cut(750 / SFREQ, -10, 10)  # the oldest sample kept is 744
    assert isinstance(edge, Refusal) and "starts before the oldest" in edge.reason
    recent = buffer.cut(900 / SFREQ, -10, 10)
    assert isinstance(recent, Epoch)
    np.testing.assert_array_equal(recent.data[0], np.arange(890, 911))


def test_baseline_subtracts_the_interval_mean_as_mne() -> None:
    epoch = np.random.default_rng(1).normal(size=(3, 308)).astype(np.float32)
    times = np.arange(-51, 257) / SFREQ
    assert apply_baseline(epoch, times, None) is epoch
    corrected = apply_baseline(epoch, times, (None, 0.0))
    mean = epoch[:, :52].astype(np.float64).mean(axis=1, keepdims=True)  # -51..0 included
    np.testing.assert_array_equal(corrected, (epoch - mean).astype(np.float32))
    with pytest.raises(ValueError, match="holds no sample"):
        apply_baseline(epoch, times, (2.0, 3.0))


def test_markers_and_metadata() -> None:
    move = {"step": 3, "action": "up", "from_state": 7, "to_state": 2, "target_reached": False}
    assert parse_move_marker(move_marker(move, 1)) == move | {"repeat": 1}
    with pytest.raises(ValueError, match="exactly"):
        parse_move_marker('{"step": 3}')
    assert parse_onset_marker("onset 12", "onset") == (True, 12)
    assert parse_onset_marker("onset", "onset") == (True, None)
    assert parse_onset_marker("onsets 12", "onset") == (False, None)
    info = pylsl.StreamInfo("amp", "EEG", 2, 500, pylsl.cf_float32, "amp-1")
    with pytest.raises(ValueError, match="'amp' does not name every channel"):
        eeg_stream_meta(info)
    info.set_channel_labels(["Fz", "Cz"])
    info.set_channel_units("volts")
    meta = eeg_stream_meta(info)
    assert (meta.sfreq, meta.ch_names, meta.scale) == (500.0, ("Fz", "Cz"), 1e6)


# -- whole sessions over LSL --------------------------------------------------------------


def test_a_missing_stream_is_an_error_naming_it(tmp_path: Path) -> None:
    config = tmp_path / "lsl_api.cfg"
    config.write_text(loopback_config(f"cfbci-test-{tmp_path.name[-40:]}"))
    result = subprocess.run(
        [sys.executable, "-m", "cfbci.cli", "lsl-bridge", "--eeg", "no-such-amplifier",
         "--markers", "m", "--session", "s", "--connect", free_tcp_endpoint(),
         "--timeout", "1"],
        env=os.environ | {"LSLAPICFG": str(config)}, capture_output=True, text=True,
        timeout=TIMEOUT,
    )
    assert result.returncode == 1
    assert "no LSL stream named 'no-such-amplifier' found within 1 s" in result.stderr


@dataclass(frozen=True)
class LslSession:
    bridge: dict
    recording: Path
    written_path: Path
    written: dict[str, np.ndarray]
    logs: dict[str, str]


def _start(tmp_path: Path, role: str, *args: str) -> subprocess.Popen:
    """``cfbci ARGS`` as a process on this test's LSL, its output in ``<role>.log``."""
    env = os.environ | {"LSLAPICFG": str(tmp_path / "lsl_api.cfg")}
    with (tmp_path / f"{role}.log").open("w") as log:
        return subprocess.Popen([sys.executable, "-m", "cfbci.cli", *args], env=env,
                                stdout=log, stderr=subprocess.STDOUT)


def _stop(process: subprocess.Popen) -> None:
    """SIGTERM to a process still running, and wait for it."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        process.wait(TIMEOUT)


def listening_loop(
    tmp_path: Path, seed: int, running: ExitStack
) -> tuple[str, str, dict[str, str], list[str]]:
    """A whole-loop session's setting (the simulator listening for a stimulus program's
    onsets): this test's loopback LSL config, a ``cfbci serve`` recording to ``tmp_path``
    (stopped with ``running``); returns the session's name, the service's endpoint, the
    streams' names (``moves``, ``onsets``, ``eeg``) and the options every client shares."""
    name = tmp_path.name[-40:]
    # A module's fixture may run in each pytest-xdist worker, under the same folder name:
    # the process id keeps their LSL apart.
    (tmp_path / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{name}-{os.getpid()}"))
    endpoint = free_tcp_endpoint()
    names = {kind: f"{kind}-{name}" for kind in ("moves", "onsets", "eeg")}
    common = ["--session", name, "--seed", str(seed), "--connect", endpoint,
              "--timeout", "60", "--eeg", names["eeg"]]
    serve = _start(tmp_path, "serve", "serve", "--listen", endpoint, "--record-dir",
                   str(tmp_path))
    running.callback(_stop, serve)
    return name, endpoint, names, common


def listening_clients(
    tmp_path: Path, running: ExitStack, names: dict[str, str], common: list[str], steps: int,
    marker_latency: float,
) -> tuple[subprocess.Popen, subprocess.Popen]:
    """``lsl-simulator --onsets`` (its writes in ``written.npz``) and ``lsl-bridge`` (its
    summary in ``bridge.json``) of a `listening_loop` session, stopped with ``running``."""
    simulator = _start(tmp_path, "simulator", "lsl-simulator", *common, "--onsets",
                       names["onsets"], "--marker-latency", str(marker_latency),
                       "--written", str(tmp_path / "written.npz"))
    running.callback(_stop, simulator)
    bridge = _start(tmp_path, "bridge", "lsl-bridge", *common, "--markers", names["onsets"],
                    "--moves", names["moves"], "--steps", str(steps),
                    "--json", str(tmp_path / "bridge.json"))
    running.callback(_stop, bridge)
    return simulator, bridge


@contextmanager
def lsl_clients(
    tmp_path: Path, steps: int, seed: int, endpoint: str, simulator_options: list[str],
    bridge_options: Sequence[str] = (),
) -> Iterator[Callable[[], LslSession]]:
    """``lsl-simulator`` and ``lsl-bridge`` (with ``bridge_options``) as processes
    connecting to ``endpoint``, for a service recording to ``tmp_path``; yields the
    function that waits for both to exit (status 0) and returns the session."""
    name = tmp_path.name[-40:]
    (tmp_path / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{name}"))
    common = ["--session", name, "--seed", str(seed), "--connect", endpoint,
              "--moves", f"moves-{name}", "--timeout", "60", "--eeg", f"eeg-{name}",
              "--markers", f"markers-{name}"]
    with ExitStack() as running:
        simulator = _start(tmp_path, "simulator", "lsl-simulator", *common, "--written",
                           str(tmp_path / "written.npz"), *simulator_options)
        running.callback(_stop, simulator)
        bridge = _start(tmp_path, "bridge", "lsl-bridge", *common, "--steps", str(steps),
                        "--json", str(tmp_path / "bridge.json"), *bridge_options)
        running.callback(_stop, bridge)
        logs = {role: tmp_path / f"{role}.log" for role in ("simulator", "bridge")}

        def finish() -> LslSession:
            assert bridge.wait(TIMEOUT) == 0, logs["bridge"].read_text()
            assert simulator.wait(TIMEOUT) == 0, logs["simulator"].read_text()
            with np.load(tmp_path / "written.npz", allow_pickle=False) as arrays:
                written = dict(arrays)
            return LslSession(
                json.loads((tmp_path / "bridge.json").read_text()), tmp_path / f"{name}.mcap",
                tmp_path / "written.npz", written,
                {role: path.read_text() for role, path in logs.items()},
            )

        yield finish


def lsl_session(
    tmp_path: Path, steps: int, seed: int, simulator_options: list[str]
) -> LslSession:
    """``cfbci serve``, ``lsl-simulator`` and ``lsl-bridge`` as processes, to the end."""
    endpoint = free_tcp_endpoint()
    serve = _start(tmp_path, "serve", "serve", "--listen", endpoint, "--record-dir",
                   str(tmp_path))
    try:
        with lsl_clients(tmp_path, steps, seed, endpoint, simulator_options) as finish:
            session = finish()
    finally:
        _stop(serve)
    assert serve.returncode == 0, (tmp_path / "serve.log").read_text()
    return session


def assert_session_is_the_simulation(session: LslSession, steps: int, seed: int) -> None:
    """The recording: every epoch the simulator's, the truth, the moves of ``cfbci
    simulate`` for the seed."""
    comparison = check_recording(session.written_path, session.recording)
    assert (comparison.recorded, comparison.equal, comparison.mismatches) == (steps, steps, [])
    recording = read_recording(session.recording)
    assert [m["step"] for m in recording.accepted_epochs()] == list(range(1, steps + 1))
    assert [m["step"] for _, m in recording.messages["/truth"]] == list(range(1, steps + 1))
    trace = []
    run_session(seed, SessionConfig(steps=steps), DataSpec().resolve("feedback"), trace.append)
    moves = [(m["from_state"], m["action"], m["to_state"]) for _, m in recording.messages["/move"]]
    assert moves == [(r.state, r.action, r.next_state) for r in trace]


def test_lsl_session_epochs_equal_what_the_simulator_wrote(tmp_path: Path) -> None:
    steps, seed = 20, 4
    session = lsl_session(tmp_path, steps, seed, ["--onset-delay", "0.3"])
    assert_session_is_the_simulation(session, steps, seed)
    # A normal end is quiet: liblsl's "Stream transmission broke off" is no error to show.
    for role, log in session.logs.items():
        assert "ERR|" not in log and "broke off" not in log, (role, log)
    bridge = session.bridge
    assert [e["step"] for e in bridge["epochs"]] == list(range(1, steps + 1))
    assert bridge["gaps"] == [] and bridge["refused"] == [] and bridge["reconnects"] == []
    assert len(bridge["latency_ns"]) == len(bridge["age_s"]) == steps
    assert bridge["latency_ms"]["p99"] > 0
    # The bridge's onset sample is the simulator's: onset timestamps are sample stamps.
    onsets = np.round((np.array([e["onset"] for e in bridge["epochs"]]) - session.written["t0"])
                      * SFREQ).astype(np.int64)
    np.testing.assert_array_equal(onsets, session.written["onsets"])


def test_dropped_samples_and_a_vanished_stream_are_reported_and_never_cut_across(
    tmp_path: Path,
) -> None:
    steps, seed = 12, 5
    session = lsl_session(
        tmp_path, steps, seed,
        ["--onset-delay", "0.3", "--drop", "5:100:20", "--late-onset", "3:0.8",
         "--restart-after", "8", "--outage", "1"],
    )
    written, bridge = session.written, session.bridge
    # The simulator wrote step 5 twice: the first time with 20 samples left out.
    (write, first, count), = written["dropped"].tolist()
    assert written["steps"][write] == 5 and written["repeats"][write] == 0 and count == 20
    assert first == written["onsets"][write] + 100
    drop, outage = bridge["gaps"]
    assert drop["missing"] == 20
    assert round((drop["before"] - written["t0"]) * SFREQ) == first - 1
    assert round((drop["after"] - written["t0"]) * SFREQ) == first + count
    assert outage["missing"] >= SFREQ  # the EEG outlet was closed for 1 s
    assert bridge["reconnects"] == [f"eeg-{tmp_path.name[-40:]}"]
    assert bridge["refused"][0]["step"] == 5
    assert "spans the gap" in bridge["refused"][0]["reason"]
    assert "LSL stream" in session.logs["bridge"] and "lost" in session.logs["bridge"]
    # A late marker is reported, and its epoch cut all the same (its samples are buffered).
    # (On a loaded machine another marker may be reported late too: only step 3's is made.)
    (late,) = [m for m in bridge["late_markers"] if m["step"] == 3]
    assert late["delay"] >= 0.8
    assert (bridge["epochs"][2]["step"], bridge["epochs"][2]["repeat"]) == (3, 0)
    # No published epoch holds a dropped sample or the outage.
    sample = np.round((np.array([e["onset"] for e in bridge["epochs"]]) - written["t0"]) * SFREQ)
    missing = [(first, first + count)] + [
        (round((g["before"] - written["t0"]) * SFREQ) + 1,
         round((g["after"] - written["t0"]) * SFREQ)) for g in bridge["gaps"]
    ]
    for onset in sample:
        for low, high in missing:
            assert onset + 256 < low or onset - 51 >= high
    # The repeated step got its epoch, the same the user gave: the session is unchanged.
    assert_session_is_the_simulation(session, steps, seed)


def test_a_config_lost_before_the_service_subscribed_is_resent_and_answered(
    tmp_path: Path,
) -> None:
    """The bridge's config reaches only an observer: the service is not there yet, so the
    config is lost for it. An ``error`` event and the rejection of another config on the
    session's id come next; the bridge ends on neither (docs/protocol.md), re-sends its
    config unchanged, and the service started afterwards (in this process, on the
    observer's Zenoh session) answers it: the session runs to its end as the simulation."""
    steps, seed = 6, 2
    sid, endpoint = tmp_path.name[-40:], free_tcp_endpoint()
    heard: queue.SimpleQueue[Received] = queue.SimpleQueue()
    with zenoh.open(peer_config([endpoint], ())) as network:
        pumps = [Pump(network, protocol.key(sid, kind), kind, heard)  # truth: the simulator's
                 for kind in ("config", "truth")]
        with lsl_clients(tmp_path, steps, seed, endpoint, ["--onset-delay", "0.3"]) as finish:
            first = heard.get(timeout=TIMEOUT)  # no truth comes before a move: the config
            outbox = Outbox(network)
            outbox.send("event", sid, {"event": "error", "message": "garbage on the keys",
                                       "config_t_ns": None})
            outbox.send("event", sid, {"event": "session_rejected", "message": "not yours",
                                       "config_t_ns": protocol.decode(first.data).t_ns + 1})
            service = PipelineService(network, tmp_path)
            serving = threading.Thread(target=service.run)
            serving.start()
            try:
                while (again := heard.get(timeout=TIMEOUT)).tag != "config":
                    pass
                session = finish()
            finally:
                service.stop()
                serving.join(TIMEOUT)
                outbox.close()
        for pump in pumps:
            pump.close()
    assert (first.tag, again.data) == ("config", first.data)  # re-sent unchanged
    assert "error: garbage on the keys" in session.logs["bridge"]
    assert "session_rejected: not yours" in session.logs["bridge"]
    assert [e["step"] for e in session.bridge["epochs"]] == list(range(1, steps + 1))
    assert_session_is_the_simulation(session, steps, seed)


@pytest.mark.parametrize("content", [b"MCAP0\r\n not written epochs", b""])
def test_lsl_check_names_a_file_that_is_not_the_simulators_written_epochs(
    tmp_path: Path, content: bytes
) -> None:
    """Arguments swapped (a recording given as the written file) or an empty file: one
    line that names the file and what was expected, exit 2, no traceback."""
    written, recording = tmp_path / "run.mcap", tmp_path / "written.npz"
    written.write_bytes(content)
    np.savez(recording, steps=np.arange(2), epochs=np.zeros((2, 4, 8), np.float32))
    checked = subprocess.run([sys.executable, "-m", "cfbci.cli", "lsl-check", str(written),
                              str(recording)], capture_output=True, text=True, timeout=TIMEOUT)
    assert checked.returncode == 2
    assert f"{written}: not the simulator's written epochs" in checked.stderr
    assert "Traceback" not in checked.stderr
