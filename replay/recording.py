"""Session recordings: one MCAP file per live session, readable after the writer is killed.

A `SessionRecorder` writes every message as its own uncompressed MCAP chunk (JSON
message encoding, a JSON Schema per channel), followed by the chunk's message index, and
flushes it to the OS before `record` returns. A closed recording
therefore has a chunk index for every message in its summary, which indexed readers need
(``@mcap/core``'s ``McapIndexedReader``, on which Foxglove builds, reads no message of a
file without chunks), and a killed writer loses at most the message it was writing: it
leaves a file without summary, index or footer. `read_recording` reads any recording,
closed or cut, in one linear pass of the mcap library's ``StreamReader`` that stops at the
first incomplete record (an indexed reader needs the footer and summary a killed writer
never wrote), and `recover` rewrites what it reads as a clean, indexed MCAP file.
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

Topics are the keys of `SCHEMAS`. The belief over tasks goes, with every state, to
``/belief`` in a grid world: a ``foxglove.Grid`` whose cell ``s = row * n + col`` is the
state of `calibration_free.world.GridWorld` (Foxglove draws row 0 at y = 0); a world
without a grid layout (line, pick-and-place) has no ``/belief`` channel but ``/ranking``
(JSON): the `RANKED` most confident tasks with their state names, best first.
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
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from calibration_free.world import GridWorld, World
from replay.damage import (
    CONFIG_METADATA,
    HEADER_LIBRARY,
    HEADER_PROFILE,
    Damage,
    NotMcap,
    Scan,
    scan_mcap,
)
from session.config import recorded_config

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
    "/prior": {
        **_stamped("cfbci.Prior", "A file of the session's prior (replay.recorded_prior)"),
        "required": ["seq", "t_ns", "sha256", "data"],
    },
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
    """The `WORLD_TOPICS` a recording of this configuration has."""
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
    ``/config``, logged at the wall-clock time) and as the metadata `CONFIG_METADATA`.

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
        unused |= set() if config.get("prior") else {"/prior"}  # a session with a prior's
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
            One of `SCHEMAS`.
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
        world, else on ``/ranking`` (`record_ranking`).

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
        """Record the `RANKED` most confident tasks on ``/ranking``, best first (ties
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
            1 debug, 2 info, 3 warning, 4 error, 5 fatal (`LOG_LEVELS`).
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
    """What `read_recording` found in a recording.

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
        Where and why reading stopped early, and where the file is damaged; None for a
        closed, undamaged file.
    path : str
        The file it was read from.
    damage : tuple of Damage
        Damaged regions (`replay.damage.Damage`), in file order; read with
        ``salvage=True``, the messages around them are kept.
    offsets : dict of str to list of int
        Per topic, the byte offset of the chunk holding each message (the order of
        ``messages``): where each message is in the file.
    order : dict of str to list of int
        Per topic, each message's rank among all the messages read, in file order.
    size : int
        File size, bytes.
    dropped : int
        Messages read whole but left out: of a channel no intact record defines, or not
        JSON.
    """

    session: str
    config: dict[str, Any]
    messages: dict[str, list[tuple[int, dict[str, Any]]]]
    truncated: bool
    end_offset: int
    warning: str | None
    path: str
    damage: tuple[Damage, ...] = ()
    offsets: dict[str, list[int]] = field(default_factory=dict)
    order: dict[str, list[int]] = field(default_factory=dict)
    size: int = 0
    dropped: int = 0

    @property
    def n_messages(self) -> int:
        """Number of messages read, all topics."""
        return sum(len(messages) for messages in self.messages.values())

    @property
    def complete(self) -> bool:
        """Closed by its writer and undamaged: the file holds what was written, whole."""
        return not self.truncated and not self.damage and not self.dropped

    def data_damage(self) -> list[Damage]:
        """The damaged regions before the summary (where messages may have been lost)."""
        return [d for d in self.damage if d.section != "summary"]

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


@dataclass
class _Read:
    """The records a recording yields: header, schemas, channels, metadata and messages
    (``(offset, record, topic)``), from `_read`."""

    scan: Scan
    header: Header
    schemas: list[Schema]
    channels: list[Channel]
    metadata: list[Metadata]
    messages: list[tuple[int, Message, str]]
    dropped: int


def _read(path: Path, salvage: bool) -> _Read:
    """Scan a recording (`replay.damage.scan_mcap`); without ``salvage``, damage
    before the summary is a ``ValueError``. Messages whose channel no intact record defines
    (the first chunk damaged) take their channel from an intact summary, else are dropped."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if not path.is_file():
        raise ValueError(f"{path}: is not a regular file (a directory?)")
    try:
        scan = scan_mcap(path.read_bytes())
    except NotMcap as error:
        raise ValueError(f"{path}: {error}") from None
    first = next((d for d in scan.damage if d.section != "summary"), None)
    if first is not None and not salvage:
        raise ValueError(f"{path}: corrupt MCAP record after byte {first.start}: "
                         f"{first.what} (`cfbci recover` salvages the rest)")
    records = [record for _, record in scan.records]
    schemas = [r for r in records if isinstance(r, Schema)]
    channels = [r for r in records if isinstance(r, Channel)]
    known = {c.id for c in channels}
    used = {r.channel_id for r in records if isinstance(r, Message)}
    for record in scan.summary:  # the first chunk damaged: the summary's definitions
        if isinstance(record, Channel) and record.id in used - known:
            channels.append(record)
            known.add(record.id)
    defined = {s.id for s in schemas}
    needed = {c.schema_id for c in channels} - defined
    schemas += [r for r in scan.summary if isinstance(r, Schema) and r.id in needed]
    topics = {c.id: c.topic for c in channels}
    messages = [(at, r, topics[r.channel_id]) for at, r in scan.records
                if isinstance(r, Message) and r.channel_id in topics]
    header = next((r for r in records if isinstance(r, Header)),
                  Header(HEADER_PROFILE, HEADER_LIBRARY))
    metadata = [r for r in records if isinstance(r, Metadata)]
    n_messages = sum(isinstance(r, Message) for r in records)
    return _Read(scan, header, schemas, channels, metadata, messages,
                 n_messages - len(messages))


def _warning(path: Path, scan: Scan, n_messages: int, dropped: int) -> str | None:
    """Where a cut file ends, and where a file is damaged; None for an intact one."""
    parts = []
    if not scan.closed:
        if scan.cut == 0:
            parts.append(f"{path}: truncated at byte 0 (in the MCAP magic); 0 complete "
                         "messages read")
        else:
            parts.append(f"{path}: truncated at byte {scan.data_end} of {scan.size} (the "
                         f"writer did not close it); {n_messages} complete messages read")
    damage = scan.damage
    if damage:
        lost = sum(d.messages for d in damage)
        first = damage[0]
        text = (f"damaged: {len(damage)} region{'s' * (len(damage) != 1)} not read, the first "
                f"{first.describe()}")
        if lost:
            text += f"; {lost} message{'s' * (lost != 1)} apparently lost in all"
        parts.append(text if parts else f"{path}: {text}; {n_messages} messages read")
    if dropped:
        parts.append(f"{dropped} messages dropped (their channel is defined only in a damaged "
                     "chunk, or they are not JSON)")
    return "; ".join(parts) or None


def read_recording(path: str | os.PathLike[str], *, salvage: bool = False) -> Recording:
    """Read a recording, complete or cut anywhere (killed writer, copy of a live file).

    Parameters
    ----------
    path : str or PathLike
        An MCAP file written by `SessionRecorder` (or `recover`).
    salvage : bool, default False
        Also read a damaged file: every intact record around the damaged regions (see
        `replay.damage`), which ``damage`` and ``warning`` then name. Without it, a
        damaged record before the summary is an error (a damaged summary, which no message
        is read from, is only said in ``damage`` and ``warning``).

    Returns
    -------
    Recording
        Every intact message (without ``salvage``: before the first incomplete record).

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    ValueError
        If it is not a regular file, not MCAP, or (without ``salvage``) a record before the
        summary is damaged.
    """
    read = _read(Path(path), salvage)
    messages: dict[str, list[tuple[int, dict[str, Any]]]] = {c.topic: [] for c in read.channels}
    offsets: dict[str, list[int]] = {c.topic: [] for c in read.channels}
    order: dict[str, list[int]] = {c.topic: [] for c in read.channels}
    undecodable = 0
    for rank, (at, record, topic) in enumerate(read.messages):
        try:
            message = json.loads(record.data)
        except ValueError:  # an intact chunk of another writer's non-JSON message
            undecodable += 1
            continue
        messages[topic].append((record.log_time, message))
        offsets[topic].append(at)
        order[topic].append(rank)
    first = messages.get("/config") or []
    session, config = ("", {}) if not first else (first[0][1]["session"], first[0][1]["config"])
    if not first and salvage and read.metadata:  # the /config chunk damaged: the metadata's
        session = read.metadata[0].metadata["session"]
        config = json.loads(read.metadata[0].metadata["config"])
    dropped = read.dropped + undecodable
    n_messages = len(read.messages) - undecodable
    return Recording(
        session=session,
        config=recorded_config(config),
        messages=messages,
        truncated=not read.scan.closed,
        end_offset=read.scan.data_end,
        warning=_warning(Path(path), read.scan, n_messages, dropped),
        path=str(path),
        damage=tuple(read.scan.damage),
        offsets=offsets,
        order=order,
        size=read.scan.size,
        dropped=dropped,
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
    """Rewrite what ``read_recording(src, salvage=True)`` reads as a clean, indexed MCAP file.

    Same header, schemas, channels, metadata and messages (data, log and publish times;
    messages in file order): every intact record of ``src``, around damaged regions too
    (`replay.damage`). ``dst`` is chunked (uncompressed), with chunk and message
    indexes and a summary, so any MCAP reader can seek in it. ``src`` is only read.

    Parameters
    ----------
    src : str or PathLike
        A possibly truncated or damaged recording.
    dst : str or PathLike
        The file to write (overwritten); not ``src``.

    Returns
    -------
    int
        Number of messages written.
    """
    source, target = Path(src), Path(dst)
    if target.exists() and source.exists() and os.path.samefile(source, target):
        raise ValueError(f"{dst} is the input file; give another path")
    read = _read(source, salvage=True)
    undecodable = {id(r) for _, r, _ in read.messages if not _is_json(r.data)}
    schema_ids, channel_ids = {0: 0}, {}
    n_messages = 0
    with open(target, "wb") as file:
        writer = Writer(file, compression=CompressionType.NONE)
        writer.start(profile=read.header.profile, library=read.header.library)
        for schema in read.schemas:
            if schema.id not in schema_ids:
                schema_ids[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data)
        for channel in read.channels:
            if channel.id not in channel_ids and channel.schema_id in schema_ids:
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_ids[channel.schema_id],
                    channel.metadata)
        for metadata in read.metadata:
            writer.add_metadata(metadata.name, metadata.metadata)
        config = _lost_config(read, channel_ids)
        if config is not None:  # the /config chunk damaged: its message from the metadata
            channel, data, log_time = config
            writer.add_message(channel, log_time, data, log_time)
            n_messages += 1
        for _, record, _ in read.messages:
            if record.channel_id in channel_ids and id(record) not in undecodable:
                writer.add_message(channel_ids[record.channel_id], record.log_time, record.data,
                                   record.publish_time, record.sequence)
                n_messages += 1
        writer.finish()
    return n_messages


def _lost_config(read: _Read, channel_ids: dict[int, int]) -> tuple[int, bytes, int] | None:
    """The ``/config`` message rebuilt from the `CONFIG_METADATA` record when the
    chunk holding it is lost (the recorder writes both with the same content): its new
    channel id, data and log time (that of the first message read); None if not lost."""
    if any(topic == "/config" for _, _, topic in read.messages) or not read.metadata:
        return None
    channel = next((c for c in read.channels if c.topic == "/config"), None)
    if channel is None or channel.id not in channel_ids:
        return None
    metadata = read.metadata[0].metadata
    message = {"session": metadata["session"], "config": json.loads(metadata["config"])}
    log_time = min((r.log_time for _, r, _ in read.messages), default=0)
    return channel_ids[channel.id], _to_json(message), log_time


def _is_json(data: bytes) -> bool:
    try:
        json.loads(data)
    except ValueError:
        return False
    return True
