"""What a recording's bytes hold: every intact record, and where the file is cut or damaged.

`scan_mcap` walks an MCAP file record by record (its own parser over the mcap
library's record classes) and checks every byte it can:

* the magic at both ends; the Header (``cfbci`` writes profile ``""``, library ``cfbci``);
* a Chunk's length fields against each other, its compression, its records' CRC (the
  ``uncompressed_crc``, which the writer always sets), the records inside (each a whole
  Schema, Channel or Message) and its message start and end times against its messages;
* a MessageIndex against the chunk before it (same channel, each entry a message of that
  chunk at that offset and log time, every message of the channel listed);
* a Metadata record (well formed, named `CONFIG_METADATA`);
* the DataEnd record, then the summary section through the Footer's summary CRC and the
  closing magic.

So one flipped bit anywhere is found, except in the few bytes no check covers (none in a
cfbci recording: every field above is checked). A record that fails a check is *damaged*:
the scan resumes at the next offset where a whole, valid Chunk (its CRC matching),
Metadata record or DataEnd record begins (a damaged length field cannot be trusted), and
the bytes in between are one `Damage` region (with the messages a damaged chunk
apparently held: their topics, read from its unverified bytes, are a guess). A file that
ends inside a record whose fields are consistent as far as they go, with no valid record
after it, is *cut* (a killed writer); one whose last bytes are not a record at all is cut
at the last intact record with the rest a damaged region (e.g. garbage appended).

Pure computation over the file's bytes: nothing is written.
"""

from __future__ import annotations

import json
import re
import struct
import zlib
from dataclasses import dataclass, field
from io import BytesIO
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Footer, Header, McapRecord, Message, Metadata, Schema

MAGIC = b"\x89MCAP0\r\n"
#: Metadata record holding ``{"session": name, "config": JSON of the configuration}``.
CONFIG_METADATA = "cfbci.config"
#: What `replay.recording.SessionRecorder` writes in the Header.
HEADER_PROFILE, HEADER_LIBRARY = "", "cfbci"

_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _MESSAGE_INDEX = 1, 2, 3, 4, 5, 6, 7
_CHUNK_INDEX, _ATTACHMENT, _ATTACHMENT_INDEX, _STATISTICS, _METADATA = 8, 9, 10, 11, 12
_METADATA_INDEX, _SUMMARY_OFFSET, _DATA_END = 13, 14, 15
#: Records of the data section (the Header only first); the others belong to the summary.
_DATA_RECORDS = {_SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _MESSAGE_INDEX, _ATTACHMENT, _METADATA}
_SUMMARY_RECORDS = {_SCHEMA, _CHANNEL, _CHUNK_INDEX, _ATTACHMENT_INDEX, _STATISTICS,
                    _METADATA_INDEX, _SUMMARY_OFFSET}
_RECORD_NAMES = {
    _HEADER: "Header", _FOOTER: "Footer", _SCHEMA: "Schema", _CHANNEL: "Channel",
    _MESSAGE: "Message", _CHUNK: "Chunk", _MESSAGE_INDEX: "MessageIndex",
    _CHUNK_INDEX: "ChunkIndex", _ATTACHMENT: "Attachment", _ATTACHMENT_INDEX: "AttachmentIndex",
    _STATISTICS: "Statistics", _METADATA: "Metadata", _METADATA_INDEX: "MetadataIndex",
    _SUMMARY_OFFSET: "SummaryOffset", _DATA_END: "DataEnd",
}
#: Where a scan may resume after damage: a Chunk, a Metadata or a DataEnd record.
_RESUME = re.compile(rb"[\x06\x0c\x0f]")
_CHUNK_FIXED = 8 + 8 + 8 + 4 + 4  # start, end, uncompressed size, crc, compression length


class NotMcap(ValueError):
    """The bytes are not an MCAP file (no magic, no Header after it)."""


class _Bad(Exception):
    """A record failed a check (the message says which)."""


@dataclass(frozen=True)
class Damage:
    """A damaged region of a file: bytes ``start`` to ``end`` (excluded) were not read.

    Attributes
    ----------
    start, end : int
        Byte offsets; ``end`` is where reading resumed (the file size if it never did).
    section : str
        "magic", "header", "data" or "summary" (after the DataEnd record: the index that
        seeking readers use; no message is lost there).
    what : str
        Why: the first check the first record of the region failed.
    chunks : int
        Chunks found in the region (their records' lengths read from unverified bytes).
    messages : int
        Messages those chunks apparently held (0 when none could be read).
    topics : tuple of str
        Their topics as far as the damaged bytes tell (a guess: they failed a check).
    """

    start: int
    end: int
    section: str
    what: str
    chunks: int = 0
    messages: int = 0
    topics: tuple[str, ...] = ()

    def describe(self) -> str:
        """``bytes A-B (N bytes, <section>): <what>[; lost: ...]``."""
        text = f"bytes {self.start}-{self.end} ({self.end - self.start} bytes, {self.section}" \
               f"): {self.what}"
        if self.messages:
            topics = ", ".join(self.topics) if self.topics else "topics unknown"
            text += (f"; dropped {self.chunks} chunk{'s' * (self.chunks != 1)} apparently "
                     f"holding {self.messages} message{'s' * (self.messages != 1)} ({topics})")
        elif self.chunks:
            text += (f"; dropped {self.chunks} chunk{'s' * (self.chunks != 1)} (contents "
                     "unreadable)")
        return text

    def to_json(self) -> dict[str, Any]:
        return {"start": self.start, "end": self.end, "bytes": self.end - self.start,
                "section": self.section, "what": self.what, "chunks": self.chunks,
                "messages": self.messages, "topics": list(self.topics)}


@dataclass
class Scan:
    """What `scan_mcap` found.

    Attributes
    ----------
    size : int
        File size, bytes.
    records : list of (int, McapRecord)
        The Header, Schema, Channel, Message and Metadata records of the data section in
        file order (a chunk's records in place of the chunk), each with the offset of the
        top-level record holding it (a message's: its chunk's).
    summary : list of McapRecord
        The Schema and Channel records of an intact summary section (none otherwise).
    closed : bool
        The DataEnd record was read: the writer closed the file.
    data_end : int
        Offset just past the last intact record of the data section.
    cut : int or None
        Where the file ends inside a record (the offset of that record), or at a record
        boundary before DataEnd: a cut file (None for a closed one).
    damage : list of Damage
        Damaged regions, in file order.
    """

    size: int
    records: list[tuple[int, McapRecord]] = field(default_factory=list)
    summary: list[McapRecord] = field(default_factory=list)
    closed: bool = False
    data_end: int = 0
    cut: int | None = None
    damage: list[Damage] = field(default_factory=list)

    @property
    def intact(self) -> bool:
        """Closed and undamaged."""
        return self.closed and not self.damage


class _Whole(BytesIO):
    """Bytes where a read past the end raises ``EndOfFile`` (the mcap record readers take
    a short read for a whole one: a length field too long would go unnoticed)."""

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        if size is not None and 0 <= size != len(data):
            raise EndOfFile()
        return data


def _stream(content: bytes | memoryview) -> ReadDataStream:
    return ReadDataStream(_Whole(bytes(content)))


def _record(opcode: int, content: memoryview) -> McapRecord:
    """Parse one Header/Schema/Channel/Message/Metadata/Footer record's content; it must
    be consumed exactly."""
    stream = _stream(content)
    try:
        if opcode == _HEADER:
            record: McapRecord = Header.read(stream)
        elif opcode == _SCHEMA:
            record = Schema.read(stream)
        elif opcode == _CHANNEL:
            record = Channel.read(stream)
        elif opcode == _MESSAGE:
            record = Message.read(stream, len(content))
        elif opcode == _METADATA:
            record = Metadata.read(stream)
        elif opcode == _FOOTER:
            record = Footer.read(stream)
        else:  # pragma: no cover - callers pass only these
            raise _Bad(f"unexpected opcode {opcode:#04x}")
    except (McapError, struct.error, UnicodeDecodeError, ValueError, OverflowError,
            MemoryError) as error:
        raise _Bad(f"malformed {_RECORD_NAMES[opcode]} record ({error or type(error).__name__})"
                   ) from None
    if stream.count != len(content):
        raise _Bad(f"{_RECORD_NAMES[opcode]} record of {len(content)} bytes holds "
                   f"{stream.count}")
    return record


def _chunk_records(content: memoryview, verify: bool) -> tuple[list[tuple[int, McapRecord]],
                                                               int, int]:
    """The records of a Chunk's content, each with its offset in the chunk's records, and
    the chunk's message start and end times. ``verify``: check the lengths, compression,
    CRC and times (else read what can be read, for a damaged chunk's description)."""
    if len(content) < _CHUNK_FIXED:
        raise _Bad("Chunk record too short")
    start, end, size, crc, n_compression = struct.unpack_from("<QQQII", content)
    compression = bytes(content[_CHUNK_FIXED:_CHUNK_FIXED + n_compression])
    at = _CHUNK_FIXED + n_compression
    if at + 8 > len(content):
        raise _Bad("Chunk lengths inconsistent (compression name runs past the record)")
    (n_records,) = struct.unpack_from("<Q", content, at)
    records = content[at + 8:]
    if verify:
        if n_records != len(records):
            raise _Bad(f"Chunk lengths inconsistent (records of {n_records} bytes in a record "
                       f"leaving {len(records)})")
        if compression != b"":
            raise _Bad(f"Chunk compression {compression!r}: cfbci writes uncompressed chunks")
        if size != n_records:
            raise _Bad(f"Chunk uncompressed size {size} differs from its {n_records} bytes")
        if crc != 0 and zlib.crc32(records) != crc:
            raise _Bad("crc mismatch in a Chunk's records")
    else:
        records = records[:n_records]
    found: list[tuple[int, McapRecord]] = []
    at = 0
    while at < len(records):
        if at + 9 > len(records):
            raise _Bad("Chunk records cut")
        opcode = records[at]
        (length,) = struct.unpack_from("<Q", records, at + 1)
        if at + 9 + length > len(records):
            raise _Bad("Chunk record runs past the chunk")
        if opcode in (_SCHEMA, _CHANNEL, _MESSAGE):
            found.append((at, _record(opcode, records[at + 9:at + 9 + length])))
        elif verify:
            raise _Bad(f"Chunk holds a record of opcode {opcode:#04x}")
        at += 9 + length
    if verify:
        times = [r.log_time for _, r in found if isinstance(r, Message)]
        if times and (start, end) != (min(times), max(times)):
            raise _Bad("Chunk message start/end times differ from its messages'")
    return found, start, end


def _message_index(content: memoryview, chunk: list[tuple[int, McapRecord]] | None) -> None:
    """Check a MessageIndex against the chunk before it."""
    if len(content) < 6:
        raise _Bad("MessageIndex record too short")
    channel_id, n_bytes = struct.unpack_from("<HI", content)
    if n_bytes != len(content) - 6 or n_bytes % 16:
        raise _Bad("MessageIndex lengths inconsistent")
    entries = {struct.unpack_from("<QQ", content, 6 + 16 * k) for k in range(n_bytes // 16)}
    if chunk is None:
        raise _Bad("MessageIndex without a chunk before it")
    messages = {(r.log_time, at) for at, r in chunk
                if isinstance(r, Message) and r.channel_id == channel_id}
    if entries != messages or not entries:
        raise _Bad("MessageIndex does not match the chunk before it")


def _metadata(content: memoryview) -> Metadata:
    record = _record(_METADATA, content)
    assert isinstance(record, Metadata)
    if record.name != CONFIG_METADATA:
        raise _Bad(f"Metadata record named {record.name!r} (cfbci writes {CONFIG_METADATA!r})")
    try:
        json.loads(record.metadata["config"])
        str(record.metadata["session"])
    except (KeyError, ValueError) as error:
        raise _Bad(f"Metadata {CONFIG_METADATA!r} without a JSON config ({error})") from None
    return record


def _header(length: int, data: bytes, size: int) -> Header:
    if 8 + 9 + length > size:
        raise _Bad("Header record runs past the end of the file")
    record = _record(_HEADER, memoryview(data)[17:17 + length])
    assert isinstance(record, Header)
    if (record.profile, record.library) != (HEADER_PROFILE, HEADER_LIBRARY):
        raise _Bad(f"Header names profile {record.profile!r}, library {record.library!r} "
                   f"(cfbci writes {HEADER_PROFILE!r}, {HEADER_LIBRARY!r})")
    return record


def _data_crc_ok(data: bytes, at: int, content: memoryview) -> bool:
    """A DataEnd record's data section CRC: 0 (not computed, as cfbci's writer leaves it)
    or the CRC of the bytes before it."""
    (crc,) = struct.unpack_from("<I", content)
    return crc == 0 or crc == zlib.crc32(data[:at])


def _valid_at(data: bytes, at: int, size: int) -> bool:
    """A whole valid Chunk, Metadata or DataEnd record begins at ``at``."""
    if at + 9 > size:
        return False
    opcode = data[at]
    (length,) = struct.unpack_from("<Q", data, at + 1)
    if at + 9 + length > size:
        return False
    content = memoryview(data)[at + 9:at + 9 + length]
    try:
        if opcode == _CHUNK:
            if length < _CHUNK_FIXED + 8:
                return False
            _chunk_records(content, verify=True)
        elif opcode == _METADATA:
            _metadata(content)
        elif opcode == _DATA_END:
            return length == 4 and _data_crc_ok(data, at, content)
        else:
            return False
    except _Bad:
        return False
    return True


def _resume(data: bytes, start: int, size: int) -> int | None:
    """The first offset at or after ``start`` where a valid record begins (see
    `_valid_at`), or None."""
    for match in _RESUME.finditer(data, start):
        if _valid_at(data, match.start(), size):
            return match.start()
    return None


def _plausible_cut(data: bytes, at: int, opcode: int, length: int, size: int) -> bool:
    """The file ends inside a record starting at ``at``: is it what a killed writer
    leaves (a data record whose fields agree as far as they go)?"""
    content = memoryview(data)[at + 9:size]
    if opcode == _CHUNK:
        if len(content) < _CHUNK_FIXED:
            return True
        _, _, usize, _, n_compression = struct.unpack_from("<QQQII", content)
        fixed = _CHUNK_FIXED + n_compression + 8
        if n_compression != 0 or usize != length - fixed:
            return False
        if len(content) >= fixed:
            (n_records,) = struct.unpack_from("<Q", content, _CHUNK_FIXED)
            return n_records == usize
        return True
    if opcode == _MESSAGE_INDEX:
        if len(content) >= 6:
            return struct.unpack_from("<I", content, 2)[0] == length - 6
        return True
    return opcode in (_METADATA, _SCHEMA, _CHANNEL, _MESSAGE, _ATTACHMENT)


def _region(data: bytes, start: int, end: int, section: str, what: str,
            channels: dict[int, str]) -> Damage:
    """A damaged region, with the chunks and messages it apparently held (unverified)."""
    chunks = messages = 0
    topics: list[str] = []
    at = start
    view = memoryview(data)
    while at + 9 <= end:
        opcode = data[at]
        (length,) = struct.unpack_from("<Q", data, at + 1)
        if opcode == _CHUNK and at + 9 + length <= end:
            try:
                found, _, _ = _chunk_records(view[at + 9:at + 9 + length], verify=False)
            except _Bad:
                found = []
            chunks += 1
            for _, record in found:
                if isinstance(record, Message):
                    messages += 1
                    topic = channels.get(record.channel_id)
                    if topic is not None and topic not in topics:
                        topics.append(topic)
            at += 9 + length
        elif opcode == _MESSAGE_INDEX and at + 9 + length <= end:
            at += 9 + length
        else:
            break
    if chunks == 0 and section == "data" and data[start] == _CHUNK:
        chunks = 1  # its length was damaged: at least that chunk, contents unknown
    return Damage(start, end, section, what, chunks, messages, tuple(topics))


def scan_mcap(data: bytes) -> Scan:
    """Scan an MCAP file's bytes (see the module docstring).

    Raises
    ------
    NotMcap
        If the bytes are neither an MCAP magic nor a Header record after eight bytes.
    """
    scan = Scan(size=len(data))
    _data(data, scan)
    _check_metadata(data, scan)
    channels = {r.id: r.topic for r in scan.summary if isinstance(r, Channel)}
    channels.update({r.id: r.topic for _, r in scan.records if isinstance(r, Channel)})
    scan.damage = [  # the topics of chunks lost before their channels were known
        _region(data, d.start, d.end, d.section, d.what, channels)
        if d.messages and not d.topics else d for d in scan.damage
    ]
    return scan


def _check_metadata(data: bytes, scan: Scan) -> None:
    """The `CONFIG_METADATA` record must say what the ``/config`` message says (the
    metadata record has no CRC: this is its check, when both were read)."""
    topics = {r.id: r.topic for _, r in scan.records if isinstance(r, Channel)}
    config = next((r for _, r in scan.records if isinstance(r, Message)
                   and topics.get(r.channel_id) == "/config"), None)
    for index, (at, record) in enumerate(scan.records):
        if not isinstance(record, Metadata) or config is None:
            continue
        try:
            message = json.loads(config.data)
            agrees = (record.metadata["session"] == message["session"]
                      and json.loads(record.metadata["config"]) == message["config"])
        except (KeyError, TypeError, ValueError):
            agrees = False
        if not agrees:
            (length,) = struct.unpack_from("<Q", data, at + 1)
            scan.damage.append(Damage(at, at + 9 + length, "data", f"Metadata "
                                      f"{CONFIG_METADATA!r} differs from the /config message"))
            scan.damage.sort(key=lambda d: d.start)
            del scan.records[index]
            return


def _data(data: bytes, scan: Scan) -> None:
    """Scan the magic, Header and data section (and the summary, if the file is closed)."""
    size = len(data)
    channels: dict[int, str] = {}
    if data[:8] != MAGIC:
        if size < 8 and MAGIC.startswith(data):
            scan.cut = 0
            return
        header_follows = size >= 17 and data[8] == _HEADER
        differing = sum(bin(a ^ b).count("1") for a, b in zip(data[:8], MAGIC, strict=False))
        if not header_follows or differing > 8:
            raise NotMcap("not an MCAP file (bad magic)")
        scan.damage.append(Damage(0, 8, "magic", "the MCAP magic is damaged"))
    at = 8
    scan.data_end = 8
    previous_chunk: list[tuple[int, McapRecord]] | None = None

    def damaged(start: int, what: str, section: str = "data") -> int | None:
        """Record a damaged region from ``start`` to the next valid record; return it."""
        resumed = _resume(data, start + 1, size)
        scan.damage.append(_region(data, start, size if resumed is None else resumed,
                                   section, what, channels))
        return resumed

    if size >= 17:
        (length,) = struct.unpack_from("<Q", data, 9)
        if data[8] == _HEADER and 17 + length > size and length < 4096 and _resume(
                data, 9, size) is None:
            scan.cut = 8  # the file ends inside the Header
            return
        try:
            if data[8] != _HEADER:
                raise _Bad(f"the first record has opcode {data[8]:#04x}, not a Header")
            scan.records.append((8, _header(length, data, size)))
            at = scan.data_end = 17 + length
        except _Bad as error:
            resumed = damaged(8, f"Header: {error}", "header")
            if resumed is None:
                return
            at = resumed
    elif size > 8:
        scan.cut = 8
        return
    while True:
        if at == size:
            scan.cut = at
            return
        if at + 9 > size:
            if _resume(data, at + 1, size) is None and data[at] in _DATA_RECORDS | {_DATA_END}:
                scan.cut = at
                return
            resumed = damaged(at, "a record header runs past the end of the file")
            if resumed is None:
                return
            at = resumed
            continue
        opcode = data[at]
        (length,) = struct.unpack_from("<Q", data, at + 1)
        end = at + 9 + length
        try:
            if opcode not in _DATA_RECORDS | {_DATA_END}:
                raise _Bad(f"unknown or misplaced record opcode {opcode:#04x}")
            if end > size:
                if _plausible_cut(data, at, opcode, length, size) and _resume(
                        data, at + 1, size) is None:
                    scan.cut = at
                    return
                raise _Bad(f"{_RECORD_NAMES[opcode]} record of {length} bytes runs past the "
                           "end of the file")
            content = memoryview(data)[at + 9:end]
            if opcode == _CHUNK:
                found, _, _ = _chunk_records(content, verify=True)
                for _, record in found:
                    if isinstance(record, Channel):
                        channels[record.id] = record.topic
                scan.records.extend((at, record) for _, record in found)
                previous_chunk = found
            elif opcode == _MESSAGE_INDEX:
                _message_index(content, previous_chunk)
            elif opcode == _METADATA:
                scan.records.append((at, _metadata(content)))
                previous_chunk = None
            elif opcode == _DATA_END:
                if length != 4 or not _data_crc_ok(data, at, content):
                    raise _Bad("DataEnd record damaged")
                scan.closed = True
                scan.data_end = end
                _summary(data, end, scan)
                return
            else:  # Schema, Channel, Message, Attachment outside chunks: cfbci writes none
                raise _Bad(f"a {_RECORD_NAMES[opcode]} record outside a chunk (cfbci writes "
                           "every message, schema and channel in a chunk)")
        except _Bad as error:
            resumed = damaged(at, str(error))
            previous_chunk = None
            if resumed is None:
                return
            at = resumed
            continue
        at = scan.data_end = end


def _summary(data: bytes, start: int, scan: Scan) -> None:
    """Check the summary section from ``start`` (just past DataEnd) to the closing magic;
    keep its Schema and Channel records if it is intact, else record its damage."""
    size = len(data)
    if size - start < 9 + 20 + 8:
        scan.damage.append(Damage(start, size, "summary", "the summary section is cut (the "
                                  "data section is whole)"))
        return
    footer_at = size - 8 - 29
    found: list[McapRecord] = []
    try:
        if data[-8:] != MAGIC:
            raise _Bad("the closing MCAP magic is damaged")
        if data[footer_at] != _FOOTER or struct.unpack_from("<Q", data, footer_at + 1)[0] != 20:
            raise _Bad("the Footer record is damaged")
        footer = _record(_FOOTER, memoryview(data)[footer_at + 9:footer_at + 29])
        assert isinstance(footer, Footer)
        if footer.summary_start not in (0, start):
            raise _Bad("the Footer's summary offset is damaged")
        if footer.summary_crc != 0 and zlib.crc32(data[start:footer_at + 9 + 16]) != (
                footer.summary_crc):
            raise _Bad("summary CRC mismatch")
        at = start
        while at < footer_at:
            opcode = data[at]
            (length,) = struct.unpack_from("<Q", data, at + 1)
            if opcode not in _SUMMARY_RECORDS or at + 9 + length > footer_at:
                raise _Bad(f"summary record at byte {at} damaged")
            if opcode in (_SCHEMA, _CHANNEL):
                found.append(_record(opcode, memoryview(data)[at + 9:at + 9 + length]))
            at += 9 + length
    except (_Bad, struct.error) as error:
        scan.damage.append(Damage(start, size, "summary", f"{error} (the data section is "
                                  "whole; seeking readers need `cfbci recover`)"))
        return
    scan.summary = found
