"""Reading: validated messages (through the index, or a linear scan of a crashed file), metadata and
stored configs. Payloads go through :func:`proto.codec.decode`; nothing is unpickled."""

from __future__ import annotations

import io
import logging
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import IO, Literal

from mcap.exceptions import EndOfFile, InvalidMagic, RecordLengthLimitExceeded
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk

import proto  # noqa: F401 - registers every message type for decoding
from proto.codec import Message, decode
from proto.msgpack_wire import DEFAULT_LIMITS, Limits, ProtocolError
from services.common.mcap_io.layout import CONFIG_METADATA_PREFIX, MAGIC, MESSAGE_ENCODING, PathLike

log = logging.getLogger(__name__)

_FOOTER_RECORD_SIZE = 1 + 8 + 8 + 8 + 4
_MAX_ERRORS_KEPT = 100
MAX_CHUNK_BYTES = 1 << 30
"""Largest uncompressed chunk a reader accepts (the recorder's are about ``chunk_size`` + one message)."""

OnError = Literal["raise", "skip"]


@dataclass(frozen=True)
class Damage:
    """Where a recording stops being readable: every whole record before ``offset`` was read."""

    path: str
    offset: int
    """Byte offset of the first record that is cut off or corrupt (the end of the last whole one)."""
    size: int
    """The file's size in bytes."""
    recovered: int
    """Messages read from the file before ``offset``."""
    problem: str

    def describe(self) -> str:
        lost = self.size - self.offset
        return (
            f"damaged recording {self.path}: {self.problem}; {self.recovered} messages recovered before "
            f"byte {self.offset}, {lost} bytes after it unread"
        )


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
    damage: list[Damage] = field(default_factory=list)
    """Each damaged file read: where its readable part ends and how many messages it held up to there."""

    def note(self, problem: str) -> None:
        if len(self.errors) < _MAX_ERRORS_KEPT:
            self.errors.append(problem)


def _has_footer(f: IO[bytes], size: int) -> bool:
    if size < 2 * len(MAGIC) + _FOOTER_RECORD_SIZE:
        return False
    f.seek(size - len(MAGIC) - _FOOTER_RECORD_SIZE)
    tail = f.read(_FOOTER_RECORD_SIZE + len(MAGIC))
    return tail[0] == Opcode.FOOTER and tail.endswith(MAGIC)


def _summary_readable(f: IO[bytes], size: int) -> bool:
    if not _has_footer(f, size):
        return False
    f.seek(0)
    try:
        make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - any failure means a damaged summary
        return False
    return True


class _Bounded:
    """The file as the stream reader sees it: a read never asks for more than the file holds, so a
    damaged length field cannot make it allocate more than the file's size."""

    def __init__(self, f: IO[bytes], size: int) -> None:
        self.f, self.size = f, size

    def read(self, n: int = -1) -> bytes:
        left = max(0, self.size - self.f.tell())
        return self.f.read(left if n < 0 else min(n, left))


def _chunk_records(chunk: Chunk) -> list:
    """The records of one chunk, CRC-checked, or raise."""
    if chunk.uncompressed_size > MAX_CHUNK_BYTES:
        raise ValueError(f"chunk of {chunk.uncompressed_size} bytes over cap {MAX_CHUNK_BYTES}")
    if not chunk.compression and len(chunk.data) != chunk.uncompressed_size:
        raise ValueError("uncompressed chunk size mismatch")
    return breakup_chunk(chunk, validate_crc=True)


def _damaged(f: IO[bytes], stats: ReadStats, offset: int, size: int, recovered: int, problem: str) -> None:
    name = str(getattr(f, "name", "<stream>"))
    damage = Damage(name, offset, size, recovered, problem)
    stats.truncated = True
    stats.note(problem)
    stats.damage.append(damage)
    log.warning(damage.describe(), extra={"path": name, "offset": offset, "recovered": recovered})


def scan_records(f: IO[bytes], size: int, stats: ReadStats) -> Iterator:
    """Records of the data section in file order (mcap's non-seeking ``StreamReader``), stopping at
    the first incomplete or corrupt one, which is logged and recorded in ``stats.damage``.

    The stream reader yields a record only once all of its bytes were read, and a chunk's records are
    used only once its CRC matched, so a truncated tail never yields a partial message.
    """
    f.seek(0)
    head = f.read(len(MAGIC))
    if head != MAGIC:
        if len(head) == len(MAGIC) or not MAGIC.startswith(head):
            raise InvalidMagic(f"{getattr(f, 'name', '<stream>')}: not an MCAP file")
        _damaged(f, stats, 0, size, 0, f"file ends at byte {size}, inside the leading magic")
        return
    f.seek(0)
    records = StreamReader(_Bounded(f, size), emit_chunks=True, record_size_limit=size).records  # type: ignore[arg-type]
    pos, messages = len(MAGIC), 0
    while True:
        try:
            record = next(records)
            if isinstance(record, (DataEnd, Footer)):
                # the data section is complete; the summary would repeat what we have seen. A reader
                # scans when the footer or summary is missing or unreadable (the tail is damaged);
                # recover() scans whole files too.
                if not _summary_readable(f, size):
                    problem = (
                        "data section complete, but the summary, footer or end magic is missing or damaged"
                    )
                    _damaged(f, stats, pos, size, messages, problem)
                return
            found = _chunk_records(record) if isinstance(record, Chunk) else [record]
        except (EndOfFile, RecordLengthLimitExceeded, struct.error):
            problem = (
                f"file ends at byte {size} without a footer"
                if pos == size
                else f"record at byte {pos} is cut off (the file ends at byte {size})"
            )
            _damaged(f, stats, pos, size, messages, problem)
            return
        except Exception as exc:  # noqa: BLE001 - any other failure means a damaged record
            problem = f"corrupt record at byte {pos}: {type(exc).__name__}: {exc}"[:300]
            _damaged(f, stats, pos, size, messages, problem)
            return
        for rec in found:
            if isinstance(rec, (Header, Schema, Channel, Metadata, McapMessage)):
                messages += isinstance(rec, McapMessage)
                yield rec
        pos = f.tell()


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
            reader = make_reader(f, validate_crcs=True)  # a damaged chunk is an error, not altered data
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
    yielded = 0
    try:
        for item in reader.iter_messages(topics=topics, log_time_order=False):  # file order
            yield item
            yielded += 1
    except Exception as exc:  # noqa: BLE001 - a damaged chunk in a finished file
        # scan again from the start: it stops at the damaged record and says where; the messages the
        # index already gave (the first ``yielded`` on ``topics``, in the same order) are not repeated
        stats.indexed = False
        stats.note(f"indexed read failed ({type(exc).__name__}: {exc}); scanned instead"[:300])
        for schema, channel, rec in _scanned_messages(f, size, stats):
            if yielded and (topics is None or channel.topic in topics):
                yielded -= 1
                continue
            yield schema, channel, rec


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
    ``stats.truncated``; damage to the MCAP container itself ends the scan the same way. Either is
    logged as a warning naming the file, the byte offset and the messages recovered, and recorded
    in ``stats.damage``.
    """
    if on_error not in ("raise", "skip"):
        raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    stats = stats if stats is not None else ReadStats()
    for channel, _, msg in decoded_records(path, types, limits, on_error, stats):
        yield channel.topic, msg


def decoded_records(
    path: PathLike, types: set[str] | None, limits: Limits, on_error: OnError, stats: ReadStats
) -> Iterator[tuple[Channel, McapMessage, Message]]:
    """:func:`read_messages` with each message's channel and MCAP record (times, sequence)."""
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
            yield channel, rec, msg


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
