"""Session recordings: round trips, the official mcap reader, schemas, cut files, SIGKILL."""

from __future__ import annotations

import base64
import json
import signal
import subprocess
import sys
from collections import Counter
from collections.abc import Callable
from functools import partial
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from jsonschema import Draft202012Validator
from mcap.reader import make_reader
from mcap.records import ChunkIndex

from calibration_free.world import GridWorld
from calibration_free.worlds import make_world
from replay.recording import (
    CONFIG_METADATA,
    RANKED,
    SCHEMAS,
    Recording,
    SessionRecorder,
    decode_array,
    read_recording,
    recover,
)

ROOT = Path(__file__).resolve().parents[1]
CONFIG = {
    "grid": 3, "frame": "feedback",
    "learner": {"eps": 0.1, "decoder": "lda", "goal_pull": 0.5, "resplit_labels": True,
                "first_target_shrinkage": 0.9, "shrinkage_floor": 0.01,
                "shrinkage_margin": 0.5, "calibrated_evidence": True,
                "first_target_evidence": "filter", "power_prior_kind": "evidence_then_ratio",
                "first_target_signals": 90, "ambiguous_match": "even"},
}
T0 = 1_700_000_000_123_456_789  # ns
GRID = GridWorld(3)


def schema_errors(instance: Any, schema: dict[str, Any]) -> list[str]:
    """Every JSON Schema (2020-12) validation error, as ``"<JSON path>: <message>"``."""
    return [
        f"{error.json_path}: {error.message}"
        for error in Draft202012Validator(schema).iter_errors(instance)
    ]


def write_session(path: Path) -> list[tuple[str, int, Any]]:
    """Record every topic; return what was recorded, ``(topic, log_time_ns, message or
    (header, array))``."""
    rng = np.random.default_rng(0)
    recorded: list[tuple[str, int, Any]] = []
    with SessionRecorder(path, "s01", CONFIG) as recorder:
        for seq in range(3):
            epoch = rng.normal(scale=10.0, size=(4, 32)).astype(np.float32)
            epoch[0, :5] = [np.nan, -0.0, np.inf, 1e-45, -np.inf]  # bits, not just values
            header = {"seq": seq, "t_ns": seq, "units": "uV", "ch_names": ["Fz", "FCz", "Cz", "Pz"]}
            features, stamp = rng.normal(size=7).astype(np.float32), {"seq": seq, "t_ns": seq}
            confidence = rng.dirichlet(np.ones(9))
            steps: list[tuple[str, Any, Callable[[int], None]]] = [
                (
                    "/epoch",
                    (header, epoch),
                    partial(recorder.record_array, "/epoch", header, epoch),
                ),
                (
                    "/features",
                    (stamp, features),
                    partial(recorder.record_array, "/features", stamp, features),
                ),
                ("/belief", confidence, partial(recorder.record_belief, confidence, GRID)),
                ("/log", f"step {seq}", partial(recorder.record_log, 2, f"step {seq}")),
            ]
            for topic in ("/move", "/state", "/event", "/truth"):
                message = {"seq": seq, "t_ns": seq, "topic": topic, "extra": [1, 2.5, None, "x"]}
                steps.append((topic, message, partial(recorder.record, topic, message)))
            for i, (topic, sent, call) in enumerate(steps):
                log_time = T0 + seq * 500_000_000 + i
                call(log_time)
                recorded.append((topic, log_time, sent))
    return recorded


def chunk_indexes(path: Path) -> list[ChunkIndex]:
    """The chunk indexes of a closed file's summary, as the mcap library reads them."""
    with path.open("rb") as file:
        summary = make_reader(file).get_summary()
    assert summary is not None
    return summary.chunk_indexes


@pytest.fixture
def session(tmp_path: Path) -> tuple[Path, list[tuple[str, int, Any]]]:
    path = tmp_path / "session.mcap"
    recorded = write_session(path)
    return path, recorded


def bits(array: np.ndarray) -> np.ndarray:
    return np.asarray(array, dtype=np.float32).view(np.uint32)


def check_recorded(recording: Recording, recorded: list[tuple[str, int, Any]]) -> None:
    """Every recorded message, in order per topic, with its log time; arrays bit-exact."""
    assert recording.session == "s01"
    assert recording.config == CONFIG
    assert set(recording.messages) == set(SCHEMAS) - {"/ranking", "/particles", "/position",
                                                      "/prior"}  # a session with a prior's
    [(_, config)] = recording.messages["/config"]
    assert config == {"session": "s01", "config": CONFIG}
    counts = Counter(["/config", *(topic for topic, _, _ in recorded)])
    assert counts == {topic: len(messages) for topic, messages in recording.messages.items()}
    cursors = dict.fromkeys(SCHEMAS, 0)
    for topic, log_time, sent in recorded:
        got_time, got = recording.messages[topic][cursors[topic]]
        cursors[topic] += 1
        assert got_time == log_time
        if topic in ("/epoch", "/features"):
            header, array = sent
            assert {k: v for k, v in got.items() if k not in ("data", "shape", "dtype")} == header
            decoded = decode_array(got)
            assert decoded.shape == array.shape and decoded.dtype == np.float32
            np.testing.assert_array_equal(bits(decoded), bits(array))
        elif topic == "/belief":
            cells = np.frombuffer(base64.b64decode(got["data"]), dtype="<f4")
            np.testing.assert_array_equal(bits(cells), bits(sent.astype(np.float32)))
            assert got["timestamp"] == {"sec": log_time // 10**9, "nsec": log_time % 10**9}
            assert (got["column_count"], got["row_stride"], got["cell_stride"]) == (3, 12, 4)
            assert got["fields"] == [{"name": "confidence", "offset": 0, "type": 7}]
        elif topic == "/log":
            assert (got["level"], got["message"], got["name"]) == (2, sent, "cfbci")
            assert got["file"] == __file__ and got["line"] > 0
        else:
            assert got == sent


def test_round_trip_of_every_topic(session: tuple[Path, list[tuple[str, int, Any]]]) -> None:
    path, recorded = session
    recording = read_recording(path)
    assert not recording.truncated and recording.warning is None
    assert recording.end_offset < path.stat().st_size  # the summary and footer follow
    assert recording.n_messages == 1 + len(recorded)
    check_recorded(recording, recorded)


def test_a_closed_recording_has_a_chunk_index_for_every_message(
    session: tuple[Path, list[tuple[str, int, Any]]],
) -> None:
    path, recorded = session
    indexes = chunk_indexes(path)
    assert len(indexes) == 1 + len(recorded)
    log_times = [index.message_start_time for index in indexes][1:]
    assert log_times == [log_time for _, log_time, _ in recorded]
    for index in indexes:  # one message, of one channel, with its message index
        assert index.message_start_time == index.message_end_time
        assert len(index.message_index_offsets) == 1 and index.message_index_length > 0
        assert index.compression == "" and index.compressed_size == index.uncompressed_size


def test_the_official_reader_reads_a_closed_recording_through_its_index(
    session: tuple[Path, list[tuple[str, int, Any]]],
) -> None:
    path, recorded = session
    with path.open("rb") as file:
        reader = make_reader(file)
        assert reader.get_header().library == "cfbci" and reader.get_header().profile == ""
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 1 + len(recorded)
        assert summary.chunk_indexes  # the seeking path reads the chunks it indexes
        topics = [channel.topic for _, channel, _ in reader.iter_messages(log_time_order=False)]
        [metadata] = list(reader.iter_metadata())
    assert topics[0] == "/config"
    assert topics[1:] == [topic for topic, _, _ in recorded]
    assert metadata.name == CONFIG_METADATA
    assert metadata.metadata["session"] == "s01"
    assert json.loads(metadata.metadata["config"]) == CONFIG


def test_messages_validate_against_the_schemas_in_the_file(
    session: tuple[Path, list[tuple[str, int, Any]]],
) -> None:
    path, _ = session
    with path.open("rb") as file:
        for schema, channel, message in make_reader(file).iter_messages():
            assert schema is not None and schema.encoding == "jsonschema"
            assert channel.message_encoding == "json"
            stored = json.loads(schema.data)
            assert stored == SCHEMAS[channel.topic] and schema.name == stored["title"]
            Draft202012Validator.check_schema(stored)  # a valid schema in the first place
            assert schema_errors(json.loads(message.data), stored) == []
    assert SCHEMAS["/belief"]["title"] == "foxglove.Grid"
    assert SCHEMAS["/log"]["title"] == "foxglove.Log"


@pytest.mark.parametrize(
    ("topic", "message", "problem"),
    [
        ("/move", {"t_ns": 1}, "$: 'seq' is a required property"),
        ("/move", {"seq": -1, "t_ns": 1}, "$.seq: -1 is less than the minimum of 0"),
        ("/move", {"seq": True, "t_ns": 1}, "$.seq: True is not of type 'integer'"),
        (
            "/epoch",
            {"seq": 0, "t_ns": 1, "data": "", "shape": [2], "dtype": "<f8"},
            "$.dtype: '<f4' was expected",
        ),
        ("/log", {"level": 9}, "$.level: 9 is not valid under any of the given schemas"),
        ("/belief", {"fields": [{"type": 7.5}]}, "$.fields[0].type"),
    ],
)
def test_the_validator_catches_bad_messages(
    topic: str, message: dict[str, Any], problem: str
) -> None:
    assert any(problem in error for error in schema_errors(message, SCHEMAS[topic]))


def test_the_recorder_rejects_bad_messages(tmp_path: Path) -> None:
    with SessionRecorder(tmp_path / "bad.mcap", "bad", {}) as recorder:
        with pytest.raises(ValueError, match="unknown topic"):
            recorder.record("/nope", {"seq": 0, "t_ns": 0}, 0)
        with pytest.raises(ValueError, match=r"needs the fields \['t_ns'\]"):
            recorder.record("/move", {"seq": 0}, 0)
        with pytest.raises(ValueError, match="arrays go to"):
            recorder.record_array("/move", {"seq": 0, "t_ns": 0}, np.zeros(2), 0)
        with pytest.raises(ValueError, match="shape"):
            recorder.record_belief(np.zeros(8), GRID, 0)
        with pytest.raises(ValueError, match="unknown topic '/ranking'"):  # a grid world's
            recorder.record_ranking(np.zeros(9), GRID, 0)
        with pytest.raises(ValueError, match="log level"):
            recorder.record_log(0, "x", 0)
        with pytest.raises(ValueError, match="JSON compliant"):
            recorder.record("/state", {"seq": 0, "t_ns": 0, "p": float("nan")}, 0)
    assert read_recording(tmp_path / "bad.mcap").n_messages == 1  # the /config message


def test_a_world_without_a_grid_layout_records_a_ranking_instead(tmp_path: Path) -> None:
    path = tmp_path / "pick.mcap"
    world = make_world("pick-and-place")
    confidence = np.random.default_rng(1).dirichlet(np.ones(world.n_tasks))
    confidence[[7, 3]] = 0.5  # a tie: listed in task order
    with SessionRecorder(path, "pick", {"world": "pick-and-place"}) as recorder:
        recorder.record_belief(confidence, world, T0)
        with pytest.raises(ValueError, match="unknown topic '/belief'"):
            recorder.record("/belief", {}, T0)
    recording = read_recording(path)
    assert set(recording.messages) == set(SCHEMAS) - {"/belief", "/particles", "/position",
                                                      "/prior"}
    [(log_time, ranking)] = recording.messages["/ranking"]
    assert log_time == T0 and schema_errors(ranking, SCHEMAS["/ranking"]) == []
    expected = sorted(range(world.n_tasks), key=lambda t: (-confidence[t], t))[:RANKED]
    assert [t["task"] for t in ranking["tasks"]] == expected and expected[:2] == [3, 7]
    assert ranking["tasks"][0] == {"task": 3, "state": 3, "name": world.state_name(3),
                                   "confidence": 0.5}


def test_a_cut_file_gives_every_complete_message_before_the_cut(tmp_path: Path) -> None:
    """Cut anywhere (in the magic, a chunk, a message index after a chunk, at every record
    boundary): every message whose chunk is whole is read, and nothing of the others."""
    path = tmp_path / "session.mcap"
    write_session(path)
    data = path.read_bytes()
    closed = read_recording(path)
    indexes = chunk_indexes(path)
    starts = [index.chunk_start_offset for index in indexes]
    ends = [index.chunk_start_offset + index.chunk_length for index in indexes]
    near = [at + d for at in (*starts, *ends) for d in (-1, 0, 1)]
    inside = [(a + b) // 2 for a, b in pairwise(ends)]
    cuts = sorted({0, 5, 8, 20, *near, *inside, ends[-1] + 3})
    cut = tmp_path / "cut.mcap"
    for at in cuts:
        cut.write_bytes(data[:at])
        recording = read_recording(cut)
        complete = sum(end <= at for end in ends)  # one message per chunk
        assert recording.truncated
        assert recording.n_messages == complete, at
        if complete:
            assert ends[complete - 1] <= recording.end_offset
        assert recording.end_offset <= at
        assert f"byte {recording.end_offset}" in recording.warning
        assert f"{complete} complete messages" in recording.warning
        for topic, messages in recording.messages.items():
            assert messages == closed.messages[topic][: len(messages)]


def test_a_corrupt_chunk_is_an_error_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "session.mcap"
    write_session(path)
    data = bytearray(path.read_bytes())
    third = chunk_indexes(path)[2]
    data[third.chunk_start_offset + third.chunk_length - 5] ^= 0xFF  # in its message's bytes
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=rf"{path}: corrupt MCAP record after byte \d+: crc"):
        read_recording(path)


def test_read_recording_rejects_a_file_that_is_not_mcap(tmp_path: Path) -> None:
    path = tmp_path / "not.mcap"
    path.write_bytes(b"PK\x03\x04 not an mcap file")
    with pytest.raises(ValueError, match="not an MCAP file"):
        read_recording(path)


CHILD = """
import itertools, sys
import numpy as np
from replay.recording import SessionRecorder

recorder = SessionRecorder(sys.argv[1], "killed", {"grid": 5})
epoch = np.arange(64 * 128, dtype=np.float32).reshape(64, 128)
for seq in itertools.count():
    if seq % 3 == 0:
        recorder.record_array("/epoch", {"seq": seq, "t_ns": seq}, epoch + seq, seq)
    else:
        recorder.record("/move", {"seq": seq, "t_ns": seq, "action": "up"}, seq)
    print(seq, flush=True)  # after record() returned
"""


def test_a_killed_writer_loses_at_most_the_message_being_written(tmp_path: Path) -> None:
    path, clean = tmp_path / "killed.mcap", tmp_path / "recovered.mcap"
    k = 300
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, text=True, cwd=ROOT
    )
    try:
        reported = [child.stdout.readline() for _ in range(k)]
    finally:
        child.kill()
    reported += child.stdout.readlines()  # reports already in the pipe when it died
    assert child.wait() == -signal.SIGKILL
    assert [int(line) for line in reported] == list(range(len(reported))) and len(reported) >= k

    recording = read_recording(path)
    written = recording.n_messages - 1  # without /config
    assert len(reported) <= written <= len(reported) + 1
    assert recording.truncated and "the writer did not close it" in recording.warning
    assert recording.config == {"grid": 5}
    seqs = sorted(m["seq"] for topic in ("/epoch", "/move") for _, m in recording.messages[topic])
    assert seqs == list(range(written))
    for _, message in recording.messages["/epoch"]:
        expected = np.arange(64 * 128, dtype=np.float32).reshape(64, 128) + message["seq"]
        np.testing.assert_array_equal(decode_array(message), expected)

    assert recover(path, clean) == recording.n_messages
    with clean.open("rb") as file:
        reader = make_reader(file)
        assert reader.get_summary().chunk_indexes  # indexed: the seeking path, not a scan
        assert sum(1 for _ in reader.iter_messages()) == recording.n_messages
        assert [m.name for m in reader.iter_metadata()] == [CONFIG_METADATA]
    recovered = read_recording(clean)
    assert not recovered.truncated and recovered.messages == recording.messages


def test_an_older_recording_reads_back_with_the_settings_it_ran_with(tmp_path: Path) -> None:
    # Made before goal_pull, resplit_labels, first_target_shrinkage, the shrinkage
    # choice's floor and margin, calibrated_evidence, first_target_evidence,
    # power_prior_kind, first_target_signals and ambiguous_match existed: its learner ran
    # without any, whatever today's defaults say, so that it replays as it ran (one shrinkage
    # throughout: its own, or the default of the time). A plane world's settings are not
    # the grid learner's and are left alone.
    from calibration_free.config import LearnerConfig

    older = {"grid": 3, "frame": "feedback", "learner": {"eps": 0.1}}
    with SessionRecorder(tmp_path / "old.mcap", "old", older):
        pass
    learner = read_recording(tmp_path / "old.mcap").config["learner"]
    assert learner == {
        "eps": 0.1, "goal_pull": 0.0, "resplit_labels": False, "first_target_shrinkage": 0.5,
        "shrinkage_floor": 0.05, "shrinkage_margin": 1.0,  # the "cv" rule of its first day
        "calibrated_evidence": False, "first_target_evidence": "filter",
        "power_prior_kind": "ratio",  # method.md's bounded ratio, the only form then
        "first_target_signals": 0,  # the threshold from the first signal
        "ambiguous_match": "resolved",  # the seed code's match of ambiguous labels
    }
    assert LearnerConfig().resplit_labels  # the defaults today differ
    assert LearnerConfig().uses_calibrated_evidence
    assert LearnerConfig().power_prior_kind == "evidence_then_ratio"
    assert LearnerConfig().frame_first_target_signals > 0
    assert (LearnerConfig().shrinkage_floor, LearnerConfig().shrinkage_margin) != (0.05, 1.0)
    assert LearnerConfig().shrinkage_before_first_target != 0.5
    oas = {"grid": 3, "frame": "feedback", "learner": {"shrinkage": "oas"}}
    with SessionRecorder(tmp_path / "oas.mcap", "oas", oas):
        pass
    assert read_recording(tmp_path / "oas.mcap").config["learner"]["first_target_shrinkage"] \
        == "oas"
    plane = {"world": "continuous", "frame": "cardinal", "learner": {"hypotheses": 50}}
    with SessionRecorder(tmp_path / "plane.mcap", "plane", plane):
        pass
    assert read_recording(tmp_path / "plane.mcap").config == plane
