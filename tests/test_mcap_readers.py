"""Recordings read by the standard MCAP readers: @mcap/core's indexed reader (node, what
Foxglove builds on) and the Python mcap library's seeking reader, on a live session.

The node reader is pinned by ``tests/js/package-lock.json``; when ``tests/js/node_modules``
does not hold the locked version, the fixture runs ``npm ci`` there first (npm registry), so
``make test`` needs nothing more than node and npm on the machine. Without them the test
skips, naming the packages (fails under ``CFBCI_REQUIRE_SYSTEM_DEPS=1``, as in CI).
"""

from __future__ import annotations

import fcntl
import json
import subprocess
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from live import TIMEOUT, service_process
from mcap.reader import make_reader
from system_deps import require

from acquisition.simulated_source import SourceSettings, run_source
from replay.recording import read_recording, recover
from wire.zenoh_config import free_tcp_endpoint

JS = Path(__file__).resolve().parent / "js"
STEPS = 120
NodeReader = Callable[[Path], subprocess.CompletedProcess[str]]


def _installed_version() -> str | None:
    package = JS / "node_modules" / "@mcap" / "core" / "package.json"
    return json.loads(package.read_text())["version"] if package.exists() else None


@pytest.fixture(scope="session")
def node_reader() -> NodeReader:
    """Runs ``tests/js/count_messages.mjs`` on a file (after ``npm ci`` if needed)."""
    node, npm = require("node", "nodejs"), require("npm", "npm")
    locked = json.loads((JS / "package-lock.json").read_text())
    version = locked["packages"]["node_modules/@mcap/core"]["version"]
    with (JS / ".install.lock").open("w") as lock:  # xdist workers install once
        fcntl.flock(lock, fcntl.LOCK_EX)
        if _installed_version() != version:
            subprocess.run(
                [npm, "ci", "--no-audit", "--no-fund"], cwd=JS, check=True, timeout=600
            )
    assert _installed_version() == version

    def read(path: Path) -> subprocess.CompletedProcess[str]:
        command = [node, str(JS / "count_messages.mjs"), str(path)]
        return subprocess.run(command, capture_output=True, text=True, timeout=TIMEOUT)

    return read


def _python_indexed(path: Path) -> dict[str, Any]:
    """Messages and message bytes per topic, through the Python reader's chunk indexes."""
    topics: Counter[str] = Counter()
    size: Counter[str] = Counter()
    with path.open("rb") as file:
        reader = make_reader(file)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes  # else it falls back to a scan
        for _, channel, message in reader.iter_messages(log_time_order=False):
            topics[channel.topic] += 1
            size[channel.topic] += len(message.data)
    return {"topics": dict(topics), "bytes": dict(size), "chunks": len(summary.chunk_indexes)}


@pytest.fixture(scope="module")
def live_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A live session's recording: a real service process and a real source over Zenoh."""
    directory = tmp_path_factory.mktemp("standard-readers")
    endpoint = free_tcp_endpoint()
    with service_process(endpoint, directory):
        summary = run_source(SourceSettings("readers", seed=2, steps=STEPS), [], [endpoint])
    assert summary.steps == STEPS
    return directory / "readers.mcap"


def test_node_reads_every_message_of_a_live_recording(
    live_recording: Path, node_reader: NodeReader
) -> None:
    recording = read_recording(live_recording)
    assert not recording.truncated
    counts = {topic: len(messages) for topic, messages in recording.messages.items()}
    assert counts["/move"] == counts["/epoch"] == counts["/truth"] == STEPS
    assert counts["/state"] == counts["/belief"] == STEPS + 1

    result = node_reader(live_recording)
    assert result.returncode == 0, result.stderr
    node = json.loads(result.stdout)
    assert node["topics"] == counts  # every message, on its topic
    assert node["statistics_message_count"] == recording.n_messages
    assert node["chunk_indexes"] == recording.n_messages  # one chunk a message

    python = _python_indexed(live_recording)
    assert python["topics"] == {topic: n for topic, n in counts.items() if n}
    assert {topic: n for topic, n in node["bytes"].items() if n} == python["bytes"]
    assert python["chunks"] == recording.n_messages


def test_a_cut_recording_is_read_by_node_once_recovered(
    live_recording: Path, node_reader: NodeReader, tmp_path: Path
) -> None:
    """A file cut mid-session (what a killed writer leaves) has no index: node's indexed
    reader refuses it; ``recover``'s copy it reads in full."""
    data = live_recording.read_bytes()
    cut, clean = tmp_path / "cut.mcap", tmp_path / "clean.mcap"
    cut.write_bytes(data[: len(data) // 2])
    recording = read_recording(cut)
    assert recording.truncated and 0 < recording.n_messages

    refused = node_reader(cut)
    assert refused.returncode != 0 and "Error" in refused.stderr

    assert recover(cut, clean) == recording.n_messages
    result = node_reader(clean)
    assert result.returncode == 0, result.stderr
    counts = {topic: len(messages) for topic, messages in recording.messages.items()}
    assert json.loads(result.stdout)["topics"] == counts
