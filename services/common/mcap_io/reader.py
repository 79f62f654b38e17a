"""Reading: validated messages (through the index, or a linear scan of a crashed file), metadata and
stored configs. Payloads go through :func:`proto.codec.decode`; nothing is unpickled."""

from __future__ import annotations

import io
import logging
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import IO, Literal

from mcap.data_stream import ReadDataStream
from mcap.exceptions import InvalidMagic
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Header, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import breakup_chunk

import proto  # noqa: F401 - registers every message type for decoding
from proto.codec import Message, decode
from proto.msgpack_wire import DEFAULT_LIMITS, Limits, ProtocolError
from services.common.mcap_io.layout import CONFIG_METADATA_PREFIX, MAGIC, MESSAGE_ENCODING, PathLike

log = logging.getLogger(__name__)

_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
_FOOTER_RECORD_SIZE = 1 + 8 + 8 + 8 + 4
_MAX_ERRORS_KEPT = 100
MAX_CHUNK_BYTES = 1 << 30
"""Largest uncompressed chunk a reader accepts (the recorder's are about ``chunk_size`` + one message)."""

OnError = Literal["raise", "skip"]


@dataclass
class ReadStats:
    """What a read saw; pass one to :func:`read_messages` to have it filled in."""

    messages: int = 0
    """Messages yielded."""
    skipped: int = 0
    """Records that failed to decode and were skipped (``on_error="skip"``)."""
    ignored: int = 0
    """Records on channels whose message encoding is not msgpack (not ours)."""
    indexed: bool = False
    """The file had a valid footer and summary and was read through its index."""
    truncated: bool = False
    """The file is not whole: the linear scan stopped at an incomplete or corrupt record, or the data
    was complete but the summary, footer or end magic is missing or damaged (crashed or damaged file)."""
    errors: list[str] = field(default_factory=list)
    """The first problems met, as text."""

    def note(self, problem: str) -> None:
        if len(self.errors) < _MAX_ERRORS_KEPT:
            self.errors.append(problem)


def _has_footer(f: IO[bytes], size: int) -> bool:
    if size < 2 * len(MAGIC) + _FOOTER_RECORD_SIZE:
        return False
    f.seek(size - len(MAGIC) - _FOOTER_RECORD_SIZE)
    tail = f.read(_FOOTER_RECORD_SIZE + len(MAGIC))
    return tail[0] == Opcode.FOOTER and tail.endswith(MAGIC)


def _parse_record(opcode: int, body: bytes) -> list:
    """The records in one complete top-level record (a chunk's, CRC-checked), or raise."""
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.CHUNK:
        chunk = Chunk.read(stream)
        # Chunk.read returns short data rather than failing: compare with the declared length
        (declared,) = struct.unpack_from("<Q", body, 32 + len(chunk.compression.encode()))
        if declared != len(chunk.data) or stream.count != len(body):
            raise ValueError(f"chunk data is {len(chunk.data)} bytes, declared {declared}")
        if not chunk.compression and len(chunk.data) != chunk.uncompressed_size:
            raise ValueError("uncompressed chunk size mismatch")
        if chunk.uncompressed_size > MAX_CHUNK_BYTES:
            raise ValueError(f"chunk of {chunk.uncompressed_size} bytes over cap {MAX_CHUNK_BYTES}")
        return breakup_chunk(chunk, validate_crc=True)
    if opcode == Opcode.MESSAGE:
        return [McapMessage.read(stream, len(body))]
    readers = {
        Opcode.HEADER: Header.read,
        Opcode.SCHEMA: Schema.read,
        Opcode.CHANNEL: Channel.read,
        Opcode.METADATA: Metadata.read,
    }
    reader = readers.get(opcode)
    return [] if reader is None else [reader(stream)]


def scan_records(f: IO[bytes], size: int, stats: ReadStats) -> Iterator:
    """Records of the data section in file order, stopping at the first incomplete or corrupt one.

    Each top-level record is only parsed once all of its bytes are known to be in the file, and a
    chunk only once its CRC matched, so a truncated tail never yields a partial message.
    """
    f.seek(0)
    if f.read(len(MAGIC)) != MAGIC:
        raise InvalidMagic(f"{getattr(f, 'name', '<stream>')}: not an MCAP file")
    pos = len(MAGIC)
    while True:
        head = f.read(_RECORD_HEAD.size)
        if not head:
            stats.truncated = True
            stats.note(f"file ends at byte {pos} without a footer")
            return
        if len(head) < _RECORD_HEAD.size:
            stats.truncated = True
            stats.note(f"incomplete record header at byte {pos}")
            return
        opcode, length = _RECORD_HEAD.unpack(head)
        if opcode in (Opcode.DATA_END, Opcode.FOOTER):
            # the data section is complete; the summary would repeat what we have seen. We scan only
            # when the footer or summary is missing or unreadable: the file's tail is damaged.
            stats.truncated = True
            stats.note(
                f"data section complete up to byte {pos}, but the summary, footer or end magic is missing or damaged"
            )
            return
        if length > size - pos - _RECORD_HEAD.size:
            stats.truncated = True
            stats.note(f"record (opcode {opcode}) at byte {pos} needs {length} bytes, file ends first")
            return
        body = f.read(length)
        try:
            records = _parse_record(opcode, body)
        except Exception as exc:  # noqa: BLE001 - any failure means a damaged record
            stats.truncated = True
            stats.note(f"corrupt record (opcode {opcode}) at byte {pos}: {type(exc).__name__}: {exc}"[:300])
            return
        yield from records
        pos += _RECORD_HEAD.size + length


def _scanned_messages(
    f: IO[bytes], size: int, stats: ReadStats
) -> Iterator[tuple[Schema | None, Channel, McapMessage]]:
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    for rec in scan_records(f, size, stats):
        if isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
        elif isinstance(rec, McapMessage):
            channel = channels.get(rec.channel_id)
            if channel is None:
                raise ProtocolError("<mcap>", f"message on unknown channel {rec.channel_id}")
            yield schemas.get(channel.schema_id), channel, rec


def _raw_messages(
    f: IO[bytes], types: set[str] | None, stats: ReadStats
) -> Iterator[tuple[Schema | None, Channel, McapMessage]]:
    size = f.seek(0, io.SEEK_END)
    summary = None
    if _has_footer(f, size):
        f.seek(0)
        try:
            reader = make_reader(f)
            summary = reader.get_summary()
        except Exception as exc:  # noqa: BLE001 - a damaged summary: fall back to scanning
            log.warning("MCAP summary of %s unreadable (%s); scanning linearly", getattr(f, "name", "?"), exc)
            summary = None
    if summary is None:
        yield from _scanned_messages(f, size, stats)
        return
    stats.indexed = True
    for index in summary.chunk_indexes:
        if index.uncompressed_size > MAX_CHUNK_BYTES:
            raise ProtocolError(
                "<mcap>", f"chunk of {index.uncompressed_size} bytes over cap {MAX_CHUNK_BYTES}"
            )
    topics = None
    if types is not None:
        topics = [
            ch.topic
            for ch in summary.channels.values()
            if ch.schema_id in summary.schemas and summary.schemas[ch.schema_id].name in types
        ]
        topics += [ch.topic for ch in summary.channels.values() if ch.schema_id not in summary.schemas]
    yield from reader.iter_messages(topics=topics, log_time_order=False)


def read_messages(
    path: PathLike,
    *,
    types: set[str] | None = None,
    limits: Limits = DEFAULT_LIMITS,
    on_error: OnError = "raise",
    stats: ReadStats | None = None,
) -> Iterator[tuple[str, Message]]:
    """Yield ``(topic, message)`` for each recorded message, in file order, decoded and validated.

    ``types``: only these message type names. A record that fails to decode (or whose type differs
    from its channel's schema) raises :class:`ProtocolError` naming the field (``on_error="raise"``)
    or is skipped, logged and counted in ``stats.skipped`` (``on_error="skip"``). A file without a
    valid footer (crashed recording, ``.tmp``) is scanned up to its last complete chunk, setting
    ``stats.truncated``; damage to the MCAP container itself ends the scan the same way.
    """
    if on_error not in ("raise", "skip"):
        raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    stats = stats if stats is not None else ReadStats()
    with open(path, "rb") as f:
        for schema, channel, rec in _raw_messages(f, types, stats):
            if channel.message_encoding != MESSAGE_ENCODING:
                stats.ignored += 1
                continue
            schema_name = schema.name if schema is not None else None
            if types is not None and schema_name is not None and schema_name not in types:
                continue
            try:
                msg = decode(rec.data, limits)
                if schema_name not in (None, msg.TYPE):
                    raise ProtocolError("_type", f"{msg.TYPE} on a channel of {schema_name}")
            except ProtocolError as exc:
                where = f"{channel.topic} #{rec.sequence} (log_time {rec.log_time})"
                if on_error == "raise":
                    raise ProtocolError(exc.field, f"{exc.problem} [record {where} in {path}]") from None
                stats.skipped += 1
                stats.note(f"{where}: {exc}")
                log.warning("skipping bad record %s in %s: %s", where, path, exc)
                continue
            if types is not None and msg.TYPE not in types:
                continue
            stats.messages += 1
            yield channel.topic, msg


def read_metadata(path: PathLike) -> dict[str, dict[str, str]]:
    """All metadata records by name (a later record of the same name wins)."""
    out: dict[str, dict[str, str]] = {}
    with open(path, "rb") as f:
        size = f.seek(0, io.SEEK_END)
        records = None
        if _has_footer(f, size):
            f.seek(0)
            try:
                records = list(make_reader(f).iter_metadata())
            except Exception as exc:  # noqa: BLE001 - damaged summary: scan instead
                log.warning("MCAP metadata index of %s unreadable (%s); scanning linearly", path, exc)
        if records is None:
            records = [r for r in scan_records(f, size, ReadStats()) if isinstance(r, Metadata)]
        for rec in records:
            out[rec.name] = dict(rec.metadata)
    return out


def read_config(path: PathLike, name: str) -> str | None:
    """The JSON text stored by :meth:`McapRecorder.write_config` under ``name``, or None."""
    entry = read_metadata(path).get(CONFIG_METADATA_PREFIX + name)
    return None if entry is None else entry.get("json")
