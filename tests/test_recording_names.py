"""Nothing is ever overwritten: a reused session id is recorded under a new name, never
over an earlier recording or through a link, and a resumed session continues its own file
(real service process, real Zenoh over loopback, real MCAP files)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import zenoh
from live import TIMEOUT, service_process
from test_pipeline import GRID, source_process

from acquisition.simulated_source import SourceSettings
from cfbci.service import PipelineService, unfinished
from cfbci.service.recordings import is_recording_name, recording_path
from replay.recording import read_recording
from replay.rerun import replay_check
from wire.zenoh_config import free_tcp_endpoint, peer_config


def test_a_new_recording_takes_the_first_free_name_and_never_a_link(tmp_path: Path) -> None:
    assert recording_path(tmp_path, "s") == tmp_path / "s.mcap"
    (tmp_path / "s.mcap").write_bytes(b"earlier")
    assert recording_path(tmp_path, "s") == tmp_path / "s.2.mcap"
    os.symlink(tmp_path / "elsewhere.mcap", tmp_path / "s.2.mcap")  # dangling
    assert recording_path(tmp_path, "s") == tmp_path / "s.3.mcap"


def test_recording_names_are_told_apart_from_other_sessions() -> None:
    assert is_recording_name("s.mcap", "s")
    assert is_recording_name("s.2.mcap", "s")
    assert is_recording_name("s.12.mcap", "s")
    assert not is_recording_name("s.1.mcap", "s")
    assert not is_recording_name("s.x.mcap", "s")
    assert is_recording_name("s.2.mcap", "s.2")  # its own first recording: the file says
    assert not is_recording_name("s-x.mcap", "s")
    assert not is_recording_name("s.mcap.resuming", "s")


def test_a_reused_session_id_is_recorded_beside_the_earlier_recording(tmp_path: Path) -> None:
    """Two sessions with the same id, one after the other: the first recording is kept
    byte for byte, the second goes to ``<id>.2.mcap``; both replay identically."""
    endpoint = free_tcp_endpoint()
    first = SourceSettings("dup", seed=1, steps=30, grid=GRID)
    second = SourceSettings("dup", seed=2, steps=10, grid=GRID)
    with service_process(endpoint, tmp_path):
        with source_process(first, endpoint) as future:
            future.result(TIMEOUT)
        earlier = hashlib.sha256((tmp_path / "dup.mcap").read_bytes()).hexdigest()
        with source_process(second, endpoint) as future:
            future.result(TIMEOUT)
    assert hashlib.sha256((tmp_path / "dup.mcap").read_bytes()).hexdigest() == earlier
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dup.2.mcap", "dup.mcap"]
    for name, steps in (("dup.mcap", 30), ("dup.2.mcap", 10)):
        recording = read_recording(tmp_path / name)
        assert len(recording.messages["/move"]) == steps
        check = replay_check(tmp_path / name)
        assert check.divergence is None and check.moves == steps


def test_a_resumed_session_continues_its_own_recording(tmp_path: Path) -> None:
    """A finished ``s.mcap`` and an unfinished ``s.2.mcap`` (the same id reused, then the
    service killed): the restarted service resumes ``s.2.mcap`` in place and leaves
    ``s.mcap`` byte for byte as it was."""
    endpoint = free_tcp_endpoint()
    with service_process(endpoint, tmp_path), source_process(
        SourceSettings("s", seed=1, steps=30, grid=GRID), endpoint
    ) as future:
        future.result(TIMEOUT)
    finished = (tmp_path / "s.mcap").read_bytes()
    cut = finished[: len(finished) // 2]  # what a kill mid-session leaves
    (tmp_path / "s.2.mcap").write_bytes(cut)
    assert unfinished(read_recording(tmp_path / "s.2.mcap"))
    with zenoh.open(peer_config([free_tcp_endpoint()], [])) as network:
        service = PipelineService(network, tmp_path)  # resumes what it finds there
        assert service.sessions == ("s",)
        service.close()  # closes the resumed recording
    assert (tmp_path / "s.mcap").read_bytes() == finished
    resumed = read_recording(tmp_path / "s.2.mcap")
    assert not resumed.truncated
    assert any("resumed at step" in m["message"] for _, m in resumed.messages["/event"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.2.mcap", "s.mcap"]
