"""Session recordings: one MCAP file per live session, readable after the writer is killed.

A :class:`SessionRecorder` writes every message as its own uncompressed MCAP chunk (JSON
message encoding, a JSON Schema per channel), followed by the chunk's message index, and
flushes it to the OS before :meth:`~SessionRecorder.record` returns. A closed recording
therefore has a chunk index for every message in its summary, which indexed readers need
(``@mcap/core``'s ``McapIndexedReader``, on which Foxglove builds, reads no message of a
file without chunks), and a killed writer loses at most the message it was writing: it
leaves a file without summary, index or footer. :func:`read_recording` reads any recording,
closed or cut, in one linear pass of the mcap library's ``StreamReader`` that stops at the
first incomplete record (an indexed reader needs the footer and summary a killed writer
never wrote), and :func:`recover` rewrites what it reads as a clean, indexed MCAP file.
Flushing does not ``fsync``: what a killed process had flushed is safe, but a power cut may
lose what the OS had not yet written to the disk.

Crash safety was measured by killing (SIGKILL) a writer after it had reported ``k`` returned
messages (k = 50, 500, 2000, 3 runs each; every 7th message a 32 x 256 epoch): unchunked
records and one chunk per message, flushed after each message, kept every reported message
each time (plus, once, the message written but not yet reported); the mcap default (1 MiB
zstd chunks, file flushed) lost up to 167 messages, all of them in short sessions. The same
9 kills of this recorder (one chunk per message) lost none of the 7,716 reported messages.
A chunk costs 163 bytes per message over an unchunked record (a Chunk header, a MessageIndex
record and a ChunkIndex in the summary: +11.6 % on a 300-step synthetic session, 1,404 to
1,567 bytes a message), about 140 us more per message to write and about 500 bytes of
writer memory per message until the file is closed (the chunk indexes).

Topics are the keys of :data:`SCHEMAS`. The belief over tasks goes, with every state, to
``/belief`` in a grid world: a ``foxglove.Grid`` whose cell ``s = row * n + col`` is the
state of :class:`calibration_free.world.GridWorld` (Foxglove draws row 0 at y = 0); a world
without a grid layout (line, pick-and-place) has no ``/belief`` channel but ``/ranking``
(JSON): the :data:`RANKED` most confident tasks with their state names, best first.
``/log`` is a ``foxglove.Log``, so Foxglove Studio shows it and the grid. The continuous
world's particles go, with every state, to ``/particles``: a ``foxglove.PointCloud`` (frame
``plane``, the unit square at z = 0) of one point per particle, float32 fields ``x``, ``y``
and ``confidence`` (Foxglove's 3D panel colours the points by it); its probe points are the
``/move`` messages' ``to_state``. The exact (float64) particles are the ``/state``
messages' ``points``, which replay compares. The puddle world's belief goes, with every
state, to ``/belief``: a ``foxglove.Grid`` (frame ``plane``, 5 x 5 cells of 0.2, row 0 at
y = 0) of each goal cell's probability, the tasks' normalised likelihoods summed over
puddles (the exact 660 are the ``/state`` confidences); with every move, ``/position``
holds the agent's position: a ``foxglove.PointCloud`` (frame ``plane``) of the move's two
points ``from_state`` and ``to_state``, float32 fields ``x``, ``y`` and ``step`` (with a
decay time, Foxglove's 3D panel draws the trajectory).
"""

from __future__ import annotations

import base64
import io
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, DataEnd, Header, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from calibration_free.world import GridWorld, World
from session.config import recorded_config

_MAGIC = b"\x89MCAP0\r\n"
#: Metadata record holding ``{"session": name, "config": JSON of the configuration}``.
CONFIG_METADATA = "cfbci.config"
LOG_LEVELS = ("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL")
_NUMERIC_TYPES = tuple("UNKNOWN UINT8 INT8 UINT16 INT16 UINT32 INT32 FLOAT32 FLOAT64".split())
_FLOAT32 = _NUMERIC_TYPES.index("FLOAT32")
_COUNT = {"type": "integer", "minimum": 0}
_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": _COUNT, "nsec": {**_COUNT, "maximum": 999_999_999}},
}


def _numbers(title: str, axes: str) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": {a: {"type": "number"} for a in axes}}


def _enum(title: str, names: tuple[str, ...]) -> dict[str, Any]:
    return {"title": title, "oneOf": [{"title": name, "const": i} for i, name in enumerate(names)]}


_ARRAY = {
    "data": {"type": "string", "contentEncoding": "base64"},
    "shape": {"type": "array", "items": _COUNT},
    "dtype": {"const": "<f4"},
    "units": {"type": "string"},
    "ch_names": {"type": "array", "items": {"type": "string"}},
}


def _stamped(title: str, description: str, array: bool = False) -> dict[str, Any]:
    """A permissive object schema requiring ``seq`` and ``t_ns`` (and an array's fields)."""
    return {
        "title": title,
        "description": description,
        "type": "object",
        "properties": {"seq": _COUNT, "t_ns": {"type": "integer"}, **(_ARRAY if array else {})},
        "required": ["seq", "t_ns", *(("data", "shape", "dtype") if array else ())],
    }


#: JSON Schema of every topic, in channel registration order.
_POSE = {
    "title": "foxglove.Pose",
    "type": "object",
    "properties": {
        "position": _numbers("foxglove.Vector3", "xyz"),
        "orientation": _numbers("foxglove.Quaternion", "xyzw"),
    },
}
_PACKED_FIELDS = {
    "type": "array",
    "items": {
        "title": "foxglove.PackedElementField",
        "type": "object",
        "properties": {
            "name": {"type": "string"},
            "offset": _COUNT,
            "type": _enum("foxglove.NumericType", _NUMERIC_TYPES),
        },
    },
}
_IDENTITY_POSE = {
    "position": {"x": 0.0, "y": 0.0, "z": 0.0},
    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
}
#: Where each kind of world puts the belief accompanying a state.
BELIEF_TOPICS = ("/belief", "/ranking", "/particles")
#: Topics of one world only: the beliefs', and the puddle world's ``/position``.
WORLD_TOPICS = (*BELIEF_TOPICS, "/position")

#: foxglove.PointCloud, the schema of the plane worlds' point topics.
_POINT_CLOUD = {
    "title": "foxglove.PointCloud",
    "description": "A collection of N-dimensional points",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": _POSE,
        "point_stride": _COUNT,
        "fields": _PACKED_FIELDS,
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}

SCHEMAS: dict[str, dict[str, Any]] = {
    "/config": {
        "title": "cfbci.Config",
        "description": "The session name and configuration",
        "type": "object",
        "properties": {"session": {"type": "string"}, "config": {"type": "object"}},
        "required": ["session", "config"],
    },
    "/epoch": _stamped("cfbci.Epoch", "An epoch as received, little-endian float32", True),
    "/features": _stamped("cfbci.Features", "A feature vector, little-endian float32", True),
    "/move": _stamped(
        "cfbci.Move",
        "A move of the cursor; update_ms (recording only): the learner's time, ms, from the "
        "epoch that led to it (observe) to this move (propose)",
    ),
    "/state": _stamped("cfbci.State", "A state of the session"),
    "/event": _stamped("cfbci.Event", "A session event"),
    "/truth": _stamped("cfbci.Truth", "Ground truth, never shown to the learner"),
    "/belief": {
        "title": "foxglove.Grid",
        "description": "A 2D grid of data",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": _POSE,
            "column_count": _COUNT,
            "cell_size": _numbers("foxglove.Vector2", "xy"),
            "row_stride": _COUNT,
            "cell_stride": _COUNT,
            "fields": _PACKED_FIELDS,
            "data": {"type": "string", "contentEncoding": "base64"},
        },
    },
    "/particles": _POINT_CLOUD,
    "/position": _POINT_CLOUD,
    "/ranking": {
        "title": "cfbci.Ranking",
        "description": "The most confident tasks, best first (a world without a grid layout)",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "tasks": {
                "type": "array",
                "items": {
                    "type": "object",
                    "properties": {
                        "task": _COUNT,
                        "state": _COUNT,
                        "name": {"type": "string"},
                        "confidence": {"type": "number"},
                    },
                    "required": ["task", "state", "name", "confidence"],
                },
            },
        },
        "required": ["timestamp", "tasks"],
    },
    "/log": {
        "title": "foxglove.Log",
        "description": "A log message",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "level": _enum("foxglove.LogLevel", LOG_LEVELS),
            "message": {"type": "string"},
            "name": {"type": "string"},
            "file": {"type": "string"},
            "line": _COUNT,
        },
    },
}
_ARRAY_TOPICS = ("/epoch", "/features")
#: Tasks listed on ``/ranking``.
RANKED = 10


def belief_topic(config: dict[str, Any]) -> str:
    """Where a recording of this configuration puts the belief over tasks: ``/belief`` (a
    grid world, or a configuration of protocol version 2) or ``/ranking``."""
    world = config.get("world", "grid")
    return {"grid": "/belief", "continuous": "/particles", "puddle": "/belief"}.get(
        world, "/ranking")


def world_topics(config: dict[str, Any]) -> tuple[str, ...]:
    """The :data:`WORLD_TOPICS` a recording of this configuration has."""
    return (belief_topic(config), *(("/position",) if config.get("world") == "puddle" else ()))


def _to_json(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode()


def _base64_float32(array: np.ndarray) -> tuple[str, np.ndarray]:
    payload = np.ascontiguousarray(array, dtype="<f4")
    return base64.b64encode(payload.tobytes()).decode("ascii"), payload


def _timestamp(log_time_ns: int) -> dict[str, int]:
    sec, nsec = divmod(log_time_ns, 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def _plane_points(packed: np.ndarray, third: str, log_time_ns: int) -> dict[str, Any]:
    """A ``foxglove.PointCloud`` in frame ``plane`` of ``packed`` (shape (n, 3): x, y and
    the field named ``third``), as float32."""
    data, _ = _base64_float32(packed)
    return {
        "timestamp": _timestamp(log_time_ns),
        "frame_id": "plane",
        "pose": _IDENTITY_POSE,
        "point_stride": 12,
        "fields": [
            {"name": name, "offset": 4 * k, "type": _FLOAT32}
            for k, name in enumerate(("x", "y", third))
        ],
        "data": data,
    }


class SessionRecorder:
    """Record one session to an MCAP file, flushing every message to the OS.

    Use as a context manager; leaving it writes the summary and index and closes the file.
    The session name and configuration are written at once, as the first message (on
    ``/config``, logged at the wall-clock time) and as the metadata :data:`CONFIG_METADATA`.

    Parameters
    ----------
    path : str or PathLike
        The ``.mcap`` file to create (overwritten if it exists).
    session : str
        Name of the session.
    config : dict
        The session configuration; must be JSON-serialisable.
    """

    def __init__(self, path: str | os.PathLike[str], session: str, config: dict[str, Any]):
        config_json = _to_json(config).decode()
        self.path = Path(path)
        self._file = open(self.path, "wb")
        # chunk_size=0: every message closes its chunk (schemas and channels go into the first)
        self._writer = Writer(self._file, chunk_size=0, compression=CompressionType.NONE)
        self._writer.start(profile="", library="cfbci")
        unused = set(WORLD_TOPICS) - set(world_topics(config))
        self._channels = {
            topic: self._writer.register_channel(
                topic, "json", self._writer.register_schema(s["title"], "jsonschema", _to_json(s))
            )
            for topic, s in SCHEMAS.items()
            if topic not in unused
        }
        self._writer.add_metadata(CONFIG_METADATA, {"session": session, "config": config_json})
        self.record("/config", {"session": session, "config": config}, time.time_ns())

    def __enter__(self) -> SessionRecorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Write the summary and index, and close the file (once; later calls do nothing)."""
        if not self._file.closed:
            self._writer.finish()
            self._file.close()

    def record(self, topic: str, message: dict[str, Any], log_time_ns: int) -> None:
        """Write one JSON message and flush it to the OS.

        Parameters
        ----------
        topic : str
            One of :data:`SCHEMAS`.
        message : dict
            JSON-serialisable (no NaN or infinity); must hold the schema's required fields
            (``seq`` and ``t_ns`` on the session topics).
        log_time_ns : int
            Log time of the message, ns (uint64).

        Raises
        ------
        ValueError
            On an unknown topic, a missing required field or a NaN.
        """
        if topic not in self._channels:
            raise ValueError(
                f"unknown topic {topic!r}; the topics are {', '.join(self._channels)}"
            )
        missing = [key for key in SCHEMAS[topic].get("required", ()) if key not in message]
        if missing:
            raise ValueError(f"a {topic} message needs the fields {missing}")
        data = _to_json(message)
        self._writer.add_message(self._channels[topic], log_time_ns, data, log_time_ns)
        self._file.flush()

    def record_array(
        self, topic: str, header: dict[str, Any], array: np.ndarray, log_time_ns: int
    ) -> None:
        """Record an epoch or a feature vector: ``header`` plus the array, base64 float32.

        Parameters
        ----------
        topic : {"/epoch", "/features"}
        header : dict
            The fields received with the array (``seq``, ``t_ns``, and optionally ``units``,
            ``ch_names``, ...).
        array : ndarray, any shape
            The samples (an epoch: n_channels x n_times, in ``units``); cast to little-endian
            float32, which is bit-exact for float32 input.
        log_time_ns : int
            Log time, ns.
        """
        if topic not in _ARRAY_TOPICS:
            raise ValueError(f"arrays go to {' or '.join(_ARRAY_TOPICS)}, not {topic!r}")
        data, payload = _base64_float32(array)
        message = {**header, "data": data, "shape": list(payload.shape), "dtype": "<f4"}
        self.record(topic, message, log_time_ns)

    def record_belief(self, confidence: np.ndarray, world: World, log_time_ns: int) -> None:
        """Record the belief over tasks: on ``/belief`` as a ``foxglove.Grid`` in a grid
        world, else on ``/ranking`` (:meth:`record_ranking`).

        Parameters
        ----------
        confidence : ndarray, shape (n_tasks,)
            Confidence of each task (a grid's: of each cell ``s = row * side + col``);
            stored as float32 in the Grid's field ``confidence``, one cell of 4 bytes,
            ``side`` cells a row.
        world : World
            The session's world (the configuration's).
        log_time_ns : int
            Log time and time stamp, ns.
        """
        if np.shape(confidence) != (world.n_tasks,):
            raise ValueError(
                f"confidence must have shape ({world.n_tasks},); got {np.shape(confidence)}"
            )
        if not isinstance(world, GridWorld):
            self.record_ranking(confidence, world, log_time_ns)
            return
        self.record_grid(confidence, world.size, 1.0, "grid", log_time_ns)

    def record_grid(
        self, values: np.ndarray, side: int, cell_size: float, frame_id: str, log_time_ns: int
    ) -> None:
        """Record ``side`` x ``side`` values (cell ``row * side + col``, row 0 at y = 0) on
        ``/belief`` as a ``foxglove.Grid`` of cells ``cell_size`` wide in ``frame_id``,
        float32 field ``confidence``."""
        if np.shape(values) != (side * side,):
            raise ValueError(f"values must have shape ({side * side},); got {np.shape(values)}")
        data, _ = _base64_float32(values)
        grid = {
            "timestamp": _timestamp(log_time_ns),
            "frame_id": frame_id,
            "pose": _IDENTITY_POSE,
            "column_count": side,
            "cell_size": {"x": cell_size, "y": cell_size},
            "row_stride": 4 * side,
            "cell_stride": 4,
            "fields": [{"name": "confidence", "offset": 0, "type": _FLOAT32}],
            "data": data,
        }
        self.record("/belief", grid, log_time_ns)

    def record_position(
        self, from_state: list[float], to_state: list[float], step: int, log_time_ns: int
    ) -> None:
        """Record a puddle move's two points on ``/position`` as a ``foxglove.PointCloud``
        (frame ``plane``; float32 fields ``x``, ``y`` and ``step``)."""
        packed = np.array([[*from_state, step], [*to_state, step]], dtype=np.float64)
        self.record("/position", _plane_points(packed, "step", log_time_ns), log_time_ns)

    def record_particles(
        self, points: list[list[float]], confidence: np.ndarray, log_time_ns: int
    ) -> None:
        """Record the continuous world's particles on ``/particles`` as a
        ``foxglove.PointCloud``.

        Parameters
        ----------
        points : list of [x, y]
            The particles, in [0, 1]^2.
        confidence : ndarray, shape (n_particles,)
            Their confidences, in [0, 1].
        log_time_ns : int
            Log time and time stamp, ns.
        """
        if np.shape(confidence) != (len(points),):
            raise ValueError(
                f"confidence must have shape ({len(points)},); got {np.shape(confidence)}"
            )
        packed = np.column_stack([np.reshape(points, (-1, 2)), confidence])
        self.record("/particles", _plane_points(packed, "confidence", log_time_ns), log_time_ns)

    def record_ranking(self, confidence: np.ndarray, world: World, log_time_ns: int) -> None:
        """Record the :data:`RANKED` most confident tasks on ``/ranking``, best first (ties
        in task order), each with its state and the state's name."""
        order = np.argsort(-np.asarray(confidence, dtype=np.float64), kind="stable")[:RANKED]
        tasks = [
            {
                "task": int(t),
                "state": int(world.task_states[t]),
                "name": world.task_name(int(t)),
                "confidence": float(confidence[t]),
            }
            for t in order
        ]
        self.record("/ranking", {"timestamp": _timestamp(log_time_ns), "tasks": tasks},
                    log_time_ns)

    def record_log(self, level: int, message: str, log_time_ns: int) -> None:
        """Record a ``foxglove.Log`` on ``/log``, naming the caller's file and line.

        Parameters
        ----------
        level : int
            1 debug, 2 info, 3 warning, 4 error, 5 fatal (:data:`LOG_LEVELS`).
        message : str
            The text.
        log_time_ns : int
            Log time and time stamp, ns.
        """
        if not 1 <= level < len(LOG_LEVELS):
            raise ValueError(f"log level must be 1..{len(LOG_LEVELS) - 1}; got {level!r}")
        caller = sys._getframe(1)
        log = {
            "timestamp": _timestamp(log_time_ns),
            "level": level,
            "message": message,
            "name": "cfbci",
            "file": caller.f_code.co_filename,
            "line": caller.f_lineno,
        }
        self.record("/log", log, log_time_ns)


@dataclass
class Recording:
    """What :func:`read_recording` found in a recording.

    Attributes
    ----------
    session : str
        Session name ("" if the file ends before the ``/config`` message).
    config : dict
        Session configuration ({} if the file ends before the ``/config`` message).
    messages : dict of str to list of (int, dict)
        Per topic (every channel of the file, possibly empty), ``(log_time_ns, message)``
        in file order.
    truncated : bool
        The file was not closed (no DataEnd record): the writer was killed or is running.
    end_offset : int
        Byte offset just past the last complete record read.
    warning : str or None
        Where and why reading stopped early; None for a closed file.
    path : str
        The file it was read from.
    """

    session: str
    config: dict[str, Any]
    messages: dict[str, list[tuple[int, dict[str, Any]]]]
    truncated: bool
    end_offset: int
    warning: str | None
    path: str

    @property
    def n_messages(self) -> int:
        """Number of messages read, all topics."""
        return sum(len(messages) for messages in self.messages.values())

    def accepted_epochs(self) -> list[dict[str, Any]]:
        """The ``/epoch`` messages the service accepted (and its learner observed), in order.

        ``/epoch`` holds every epoch as received, rejected ones too; the service records the
        ``/features`` of an accepted epoch under the same ``seq``, so when the recording has
        ``/features`` only the epochs whose ``seq`` appears there are kept.
        """
        epochs = [message for _, message in self.messages.get("/epoch", [])]
        features = self.messages.get("/features", [])
        if not features:
            return epochs
        accepted = {message["seq"] for _, message in features}
        return [message for message in epochs if message["seq"] in accepted]


_KEPT = (Header, Schema, Channel, Message, Metadata)


class _WholeReads(io.BytesIO):
    """A file's bytes in memory where a read past the end raises ``EndOfFile``.

    The mcap library reads a record field by field and takes a short read for the data
    itself (a cut field fails to unpack, a cut payload is padded over); refusing short reads
    turns every cut record into ``EndOfFile`` before any part of it is parsed.
    """

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        if size is not None and 0 <= size != len(data):
            raise EndOfFile()
        return data


def _scan(path: Path) -> tuple[list[McapRecord], int, str | None]:
    """Linear pass over an MCAP data section with the mcap library's :class:`StreamReader`.

    The reader yields a record only once all its bytes are read (the messages of a chunk
    once the whole chunk is, its CRC checked); over :class:`_WholeReads` it raises
    ``EndOfFile`` at the first incomplete record, so stopping there keeps every complete
    record of a cut file.

    Returns the Header, Schema, Channel, Message and Metadata records in file order
    (messages of chunks in place of the chunks), the offset past the last complete record,
    and a warning if the file ends before its DataEnd record.
    """
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if not path.is_file():
        raise ValueError(f"{path}: is not a regular file (a directory?)")
    stream = _WholeReads(path.read_bytes())
    magic = stream.read1(len(_MAGIC))
    if magic != _MAGIC:
        if _MAGIC.startswith(magic):
            warning = f"{path}: truncated at byte 0 (in the MCAP magic); 0 complete messages read"
            return [], 0, warning
        raise ValueError(f"{path}: not an MCAP file (bad magic)")
    records: list[McapRecord] = []
    offset = stream.tell()
    try:
        for record in StreamReader(stream, skip_magic=True, validate_crcs=True).records:
            if isinstance(record, DataEnd):
                return records, stream.tell(), None
            if isinstance(record, _KEPT):
                records.append(record)
            offset = stream.tell()  # past the record (past its chunk, for a chunk's records)
    except EndOfFile:
        pass
    except (McapError, ValueError) as error:  # a CRC mismatch, an impossible length
        raise ValueError(f"{path}: corrupt MCAP record after byte {offset}: {error}") from error
    n_messages = sum(isinstance(record, Message) for record in records)
    size = stream.getbuffer().nbytes
    warning = (
        f"{path}: truncated at byte {offset} of {size} (the writer did not close it); "
        f"{n_messages} complete messages read"
    )
    return records, offset, warning


def read_recording(path: str | os.PathLike[str]) -> Recording:
    """Read a recording, complete or cut anywhere (killed writer, copy of a live file).

    Parameters
    ----------
    path : str or PathLike
        An MCAP file written by :class:`SessionRecorder` (or :func:`recover`).

    Returns
    -------
    Recording
        Every complete message before the first incomplete record.

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    ValueError
        If it is not a regular file, not MCAP, or a complete record is corrupt.
    """
    records, end_offset, warning = _scan(Path(path))
    topics: dict[int, str] = {}
    messages: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    for record in records:
        if isinstance(record, Channel):
            topics[record.id] = record.topic
            messages.setdefault(record.topic, [])
        elif isinstance(record, Message):
            messages[topics[record.channel_id]].append((record.log_time, json.loads(record.data)))
    first = messages.get("/config") or [(0, {"session": "", "config": {}})]
    return Recording(
        session=first[0][1]["session"],
        config=recorded_config(first[0][1]["config"]),
        messages=messages,
        truncated=warning is not None,
        end_offset=end_offset,
        warning=warning,
        path=str(path),
    )


def decode_array(message: dict[str, Any]) -> np.ndarray:
    """The array of an ``/epoch`` or ``/features`` message, bit-exact.

    Parameters
    ----------
    message : dict
        A message with ``data`` (base64), ``dtype`` and ``shape``.

    Returns
    -------
    ndarray, shape ``message["shape"]``, dtype ``message["dtype"]`` (little-endian float32)
        A read-only view of the decoded bytes.
    """
    raw = base64.b64decode(message["data"], validate=True)
    return np.frombuffer(raw, dtype=np.dtype(message["dtype"])).reshape(message["shape"])


def recover(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> int:
    """Rewrite what :func:`read_recording` reads of ``src`` as a clean, indexed MCAP file.

    Same header, schemas, channels, metadata and messages (data, log and publish times;
    messages in file order). ``dst`` is chunked (uncompressed), with chunk and message
    indexes and a summary, so any MCAP reader can seek in it.

    Parameters
    ----------
    src : str or PathLike
        A possibly truncated recording.
    dst : str or PathLike
        The file to write (overwritten).

    Returns
    -------
    int
        Number of messages written.
    """
    records, _, _ = _scan(Path(src))
    header = next((r for r in records if isinstance(r, Header)), Header("", "cfbci"))
    schema_ids, channel_ids = {0: 0}, {}
    n_messages = 0
    with open(dst, "wb") as file:
        writer = Writer(file, compression=CompressionType.NONE)
        writer.start(profile=header.profile, library=header.library)
        for record in records:
            if isinstance(record, Schema) and record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data
                )
            elif isinstance(record, Channel) and record.id not in channel_ids:
                schema_id = schema_ids[record.schema_id]
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_id, record.metadata
                )
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Message):
                channel_id = channel_ids[record.channel_id]
                writer.add_message(
                    channel_id, record.log_time, record.data, record.publish_time, record.sequence
                )
                n_messages += 1
        writer.finish()
    return n_messages
