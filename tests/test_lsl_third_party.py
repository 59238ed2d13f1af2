"""A session on an LSL stream the project did not write: mne-lsl's ``PlayerLSL``.

The amplifier is mne-lsl's ``PlayerLSL`` playing a continuous raw ``.fif``
(`acquisition.fif_stream`): the synthetic epochs a simulated user answers the seed's
moves with, laid out in time, each onset an annotation ``onset <step>``. The player is the
stimulus program too: its annotation stream (``<name>-annotations``, strings) is the
bridge's ``--markers``, and ``onset 1``, ``onset 2``, ... come in the order the bridge
awaits them. The bridge pairs an onset with the step whose move it forwarded last and
ignores an onset stamped before that move, so the file is laid out for the loop: a
lead-in before the first onset (the bridge finds the streams, the session starts, move 1
is forwarded) and onsets ``GAP`` s apart, more than ``tmax`` plus the loop's latency (move
k + 1 is forwarded once epoch k is cut and answered). The player's process subscribes to
the bridge's move stream (as a stimulus program does) and records the three streams into
an XDF file, as LabRecorder would.

Processes: ``cfbci serve``, ``cfbci lsl-bridge`` and the player (``python -m
acquisition.fif_stream``), on an LSL of the test's own (``LSLAPICFG``) and loopback Zenoh.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pylsl
import pytest
from system_deps import REQUIRE
from test_lsl import TIMEOUT, _start, _stop

from acquisition.fif_stream import session_raw, user_epochs
from acquisition.lab_formats import read_xdf_session
from acquisition.lsl_epochs import microvolts_per_unit, player_annotation_shift
from acquisition.lsl_streams import eeg_stream_meta, loopback_config, parse_move_marker
from acquisition.sources import DataSpec
from cfbci.offline.simulation import SessionConfig, run_session
from replay.recording import decode_array, read_recording
from wire.zenoh_config import free_tcp_endpoint

STEPS, SEED = 16, 3
LEAD_IN, GAP = 8.0, 1.7  # s
TMIN, TMAX = -0.2, 1.0  # s


#: The player process: the file played on LSL and the session recorded to XDF.
PLAYER = (
    "import logging, sys; from pathlib import Path; "
    "from acquisition.fif_stream import play_and_record; "
    "logging.basicConfig(level=logging.INFO); "
    "play_and_record(Path(sys.argv[1]), sys.argv[2], sys.argv[3], Path(sys.argv[4]))"
)

def require_mne_lsl() -> None:
    """Skip when mne-lsl is not installed (``pip install -e '.[dev]'`` installs it), or
    fail under ``CFBCI_REQUIRE_SYSTEM_DEPS=1``."""
    if importlib.util.find_spec("mne_lsl") is not None:
        return
    message = "needs mne-lsl: pip install -e '.[dev]'"
    if os.environ.get(REQUIRE) == "1":
        pytest.fail(f"{message} ({REQUIRE}=1: every test must run)")
    pytest.skip(message)


def test_mne_units_and_the_players_annotation_stream_are_recognised() -> None:
    assert [microvolts_per_unit(u) for u in ("0", "-3", "-6", "uV", None, "")] == [
        1e6, 1e3, 1.0, 1.0, 1.0, 1.0]
    assert microvolts_per_unit("none") is None and microvolts_per_unit("celsius") is None
    info = pylsl.StreamInfo("player", "eeg", 2, 256, pylsl.cf_double64, "MNE-LSL")
    info.set_channel_labels(["Fz", "Cz"])
    info.set_channel_units(["0", "0"])  # what mne-lsl writes for EEG in volts
    assert eeg_stream_meta(info).scale == 1e6
    info.set_channel_units(["0", "-6"])
    with pytest.raises(ValueError, match="the same voltage for every channel"):
        eeg_stream_meta(info)
    player = ("annotations", "string", ["description"], ["annotations"])
    assert player_annotation_shift(*player) == 1
    assert player_annotation_shift("Markers", "string", ["description"], ["annotations"]) == 0
    assert player_annotation_shift("annotations", "string", None, None) == 0


def _mne_epochs(fif: Path) -> np.ndarray:
    """MNE's epochs of the file's annotations (``tmin``, ``tmax``, no baseline), in
    annotation order, float32 µV, shape (n, n_channels, n_times)."""
    import mne

    raw = mne.io.read_raw_fif(fif, preload=True, verbose="error")
    events, event_id = mne.events_from_annotations(raw, verbose="error")
    epochs = mne.Epochs(raw, events, event_id, tmin=TMIN, tmax=TMAX, baseline=None,
                        preload=True, verbose="error")
    steps = {code: int(name.split()[1]) for name, code in event_id.items()}
    order = np.argsort([steps[code] for code in epochs.events[:, 2]])
    return (epochs.get_data()[order] * 1e6).astype(np.float32)


def test_a_session_on_mne_lsls_player_cuts_mnes_epochs_and_reads_back_from_xdf(
    tmp_path: Path,
) -> None:
    require_mne_lsl()
    trace = []
    run_session(SEED, SessionConfig(steps=STEPS), DataSpec().resolve("feedback"), trace.append)
    moves = [(r.state, r.action, r.event in ("correct_target", "wrong_target")) for r in trace]
    signals, answers = user_epochs(SEED, moves)
    written = signals.epochs[answers]
    raw = session_raw(written, signals.ch_names, signals.sfreq, signals.tmin, LEAD_IN, GAP)
    fif = tmp_path / "session_raw.fif"
    raw.save(fif, fmt="double", verbose="error")
    expected = _mne_epochs(fif)
    # The raw file keeps the user's float32 µV epochs exactly: the decisions can match.
    np.testing.assert_array_equal(expected, written)

    name = tmp_path.name[-40:]
    (tmp_path / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{name}"))
    endpoint = free_tcp_endpoint()
    processes = [_start(tmp_path, "serve", "serve", "--listen", endpoint, "--record-dir",
                        str(tmp_path))]
    try:
        processes.append(_start(
            tmp_path, "bridge", "lsl-bridge", "--session", name, "--seed", str(SEED),
            "--connect", endpoint, "--eeg", f"amp-{name}", "--markers",
            f"amp-{name}-annotations", "--moves", f"moves-{name}", "--steps", str(STEPS),
            "--tmin", str(TMIN), "--tmax", str(TMAX), "--timeout", "60", "--json",
            str(tmp_path / "bridge.json"),
        ))
        with (tmp_path / "player.log").open("w") as log:
            player = subprocess.Popen(
                [sys.executable, "-c", PLAYER, str(fif), f"amp-{name}", f"moves-{name}",
                 str(tmp_path / "session.xdf")],
                env=os.environ | {"LSLAPICFG": str(tmp_path / "lsl_api.cfg")},
                stdout=log, stderr=subprocess.STDOUT,
            )
        processes.append(player)
        bridge_log = tmp_path / "bridge.log"
        assert processes[1].wait(TIMEOUT) == 0, bridge_log.read_text()
        assert player.wait(TIMEOUT) == 0, (tmp_path / "player.log").read_text()
    finally:
        for process in processes:
            _stop(process)
    bridge = json.loads((tmp_path / "bridge.json").read_text())
    assert (bridge["ignored_markers"], bridge["refused"], bridge["gaps"]) == ([], [], [])

    # The bridge's epochs are MNE's, sample for sample, and the decisions the simulation's.
    recording = read_recording(tmp_path / f"{name}.mcap")
    epochs = recording.accepted_epochs()
    assert [m["step"] for m in epochs] == list(range(1, STEPS + 1))
    assert epochs[0]["ch_names"] == list(signals.ch_names)
    np.testing.assert_array_equal(np.stack([decode_array(m) for m in epochs]), expected)
    assert "mne-lsl's PlayerLSL annotations" in bridge_log.read_text()  # (one sample late)
    recorded_moves = [(m["from_state"], m["action"], m["to_state"])
                      for _, m in recording.messages["/move"]]
    assert recorded_moves == [(r.state, r.action, r.next_state) for r in trace]

    # The XDF read back: its onsets are the recording's steps, its epochs the recorded
    # ones, its onset samples the bridge's; every move came before its onset.
    session = read_xdf_session(tmp_path / "session.xdf", f"amp-{name}",
                               f"amp-{name}-annotations", (TMIN, TMAX))
    assert session["marker_shift"] == 1
    assert session["steps"].tolist() == list(range(1, STEPS + 1))
    assert session["cut"].tolist() == list(range(STEPS))
    np.testing.assert_array_equal(session["epochs"], expected)
    onsets = np.array([e["onset"] for e in bridge["epochs"]])
    np.testing.assert_allclose(session["onsets"], onsets, atol=0.25 / signals.sfreq, rtol=0)
    import pyxdf

    streams, _ = pyxdf.load_xdf(str(tmp_path / "session.xdf"))
    (move_stream,) = [s for s in streams if s["info"]["name"][0] == f"moves-{name}"]
    forwarded = {}
    for stamp, value in zip(move_stream["time_stamps"], move_stream["time_series"],
                            strict=True):
        forwarded.setdefault(parse_move_marker(value[0])["step"], stamp)
    assert sorted(forwarded) == list(range(1, STEPS + 1))
    assert all(forwarded[k] < session["onsets"][k - 1] for k in forwarded)
