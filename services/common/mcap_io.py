"""MCAP recordings of wire messages: a crash-tolerant recorder and validating readers.

Layout of a recording (profile ``mea``, library ``mea-rl``):

* one channel per message type, registered on first write: topic ``/mea/<TypeName>`` (or the
  topic passed to :meth:`McapRecorder.write`), message encoding ``msgpack``; its schema is named
  after the type, with encoding ``jsonschema`` and :func:`proto.jsonschema.json_schema_text` as data.
  Message records hold exactly ``msg.encode()`` (the bytes that travel on the bus);
* metadata records: ``run`` (the recorder's ``metadata=``), ``config/<name>`` (``{"json": ...}``,
  see :meth:`McapRecorder.write_config`), any added with :meth:`McapRecorder.add_metadata`, and
  ``recording`` written on close: ``status`` (``complete`` or ``aborted``), ``messages``, times and,
  when aborted, ``error``. A file without ``recording`` was never closed (crash or kill).

Atomicity and crashes: the recorder writes ``<path>.tmp`` and renames it to ``<path>`` only once the
file is finished (summary, indexes, footer) and fsynced, so ``<path>`` is always a complete MCAP.
If the ``with`` block raises, the file is still finished and renamed (``recording.status =
aborted``, logged). A killed process leaves ``<path>.tmp``: every *chunk* already written is
readable (:func:`read_messages` falls back to a linear scan that stops at the first incomplete or
corrupt record) and :func:`recover` counts them or rewrites them into a proper file. Messages in the
chunk still open are lost; a chunk is closed when it exceeds ``chunk_size`` bytes, when a write
comes ``flush_interval_s`` after the last flush, and on :meth:`McapRecorder.flush`. Written chunks
reach the OS at once (a process crash loses nothing written); only ``close`` fsyncs.

Reading never unpickles anything: payloads go through :func:`proto.codec.decode`, which validates
every field against its spec under the given :class:`~proto.msgpack_wire.Limits`.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal

from mcap.data_stream import ReadDataStream
from mcap.exceptions import InvalidMagic
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Header, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

import proto  # noqa: F401 - registers every message type for decoding
from proto.codec import Message, decode
from proto.jsonschema import json_schema_text
from proto.msgpack_wire import DEFAULT_LIMITS, Limits, ProtocolError

log = logging.getLogger(__name__)

PROFILE = "mea"
LIBRARY = "mea-rl"
MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
TOPIC_PREFIX = "/mea/"
RUN_METADATA = "run"
RECORDING_METADATA = "recording"
CONFIG_METADATA_PREFIX = "config/"
TMP_SUFFIX = ".tmp"

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
_FOOTER_RECORD_SIZE = 1 + 8 + 8 + 8 + 4
_COMPRESSIONS = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "none": CompressionType.NONE}
_MAX_ERRORS_KEPT = 100
MAX_CHUNK_BYTES = 1 << 30
"""Largest uncompressed chunk a reader accepts (the recorder's are about ``chunk_size`` + one message)."""

OnError = Literal["raise", "skip"]
PathLike = str | os.PathLike[str]


def default_topic(type_name: str) -> str:
    """The topic a message type is recorded on unless told otherwise: ``/mea/<TypeName>``."""
    return TOPIC_PREFIX + type_name


def tmp_path_for(path: PathLike) -> Path:
    """Where a recording of ``path`` lives until it is closed: ``<path>.tmp``."""
    p = Path(path)
    return p.with_name(p.name + TMP_SUFFIX)


def _check_str_map(name: str, data: dict[str, str]) -> dict[str, str]:
    if not isinstance(name, str) or not name:
        raise ValueError("metadata name must be a non-empty str")
    if not isinstance(data, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in data.items()
    ):
        raise TypeError(f"metadata {name!r} must be a dict[str, str]")
    return dict(data)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


class McapRecorder:
    """Record wire messages into an MCAP file, atomically published at ``path`` on close.

    ``McapRecorder(path, metadata={...}, compression="lz4"|"zstd"|"none")``, used as a context
    manager (or call :meth:`close`). Refuses to clobber an existing ``path`` or ``<path>.tmp``
    (the latter may hold a crashed recording worth :func:`recover`-ing) unless ``overwrite=True``.
    Thread-safe: writes from several threads are serialised.
    """

    def __init__(
        self,
        path: PathLike,
        *,
        metadata: dict[str, str] | None = None,
        compression: str = "lz4",
        chunk_size: int = 1024 * 1024,
        flush_interval_s: float | None = 5.0,
        overwrite: bool = False,
    ) -> None:
        if compression not in _COMPRESSIONS:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSIONS)}, got {compression!r}")
        if chunk_size < 1:
            raise ValueError("chunk_size must be >= 1")
        self.path = Path(path)
        self.tmp_path = tmp_path_for(self.path)
        run_meta = _check_str_map(RUN_METADATA, metadata) if metadata is not None else None
        if not overwrite:
            for p in (self.path, self.tmp_path):
                if p.exists():
                    raise FileExistsError(f"{p} exists (pass overwrite=True; a .tmp may be worth recover())")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: IO[bytes] = open(self.tmp_path, "wb" if overwrite else "xb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=_COMPRESSIONS[compression])
        self._lock = threading.RLock()
        self._schemas: dict[str, int] = {}  # type name -> schema id
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, type name)
        self._sequences: dict[int, int] = {}
        self._metadata_names: set[str] = set()
        self._flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()
        self._started_ns = time.time_ns()
        self._count = 0
        self._closed = False
        try:
            self._writer.start(profile=PROFILE, library=LIBRARY)
            if run_meta is not None:
                self.add_metadata(RUN_METADATA, run_meta)
            self._file.flush()
        except BaseException:
            self._file.close()
            raise

    # -- context manager ----------------------------------------------------------------------

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._finish(exc)

    # -- state --------------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def message_count(self) -> int:
        """Messages written so far."""
        return self._count

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"recorder for {self.path} is closed")

    # -- writing ------------------------------------------------------------------------------

    def _channel_for(self, cls: type[Message], topic: str) -> int:
        known = self._channels.get(topic)
        if known is not None:
            channel_id, type_name = known
            if type_name != cls.TYPE:
                raise ValueError(f"topic {topic!r} already records {type_name}, not {cls.TYPE}")
            return channel_id
        schema_id = self._schemas.get(cls.TYPE)
        if schema_id is None:
            data = json_schema_text(cls).encode("utf-8")
            schema_id = self._writer.register_schema(name=cls.TYPE, encoding=SCHEMA_ENCODING, data=data)
            self._schemas[cls.TYPE] = schema_id
        channel_id = self._writer.register_channel(
            topic=topic,
            message_encoding=MESSAGE_ENCODING,
            schema_id=schema_id,
            metadata={"type": cls.TYPE, "version": str(cls.VERSION)},
        )
        self._channels[topic] = (channel_id, cls.TYPE)
        self._sequences[channel_id] = 0
        return channel_id

    def write(self, msg: Message, log_time_ns: int | None = None, topic: str | None = None) -> None:
        """Append ``msg.encode()`` on ``topic`` (default ``/mea/<TypeName>``) at ``log_time_ns``
        (default now). The message is not re-validated here; readers validate."""
        if not isinstance(msg, Message) or msg.NESTED_ONLY:
            raise TypeError(f"cannot record {type(msg).__name__}: not a top-level wire message")
        if log_time_ns is None:
            log_time_ns = time.time_ns()
        elif type(log_time_ns) is not int or not 0 <= log_time_ns < 2**64:
            raise ValueError(f"log_time_ns must be an int in [0, 2**64), got {log_time_ns!r}")
        if topic is not None and (not isinstance(topic, str) or not topic):
            raise ValueError("topic must be a non-empty str")
        data = msg.encode()
        with self._lock:
            self._check_open()
            channel_id = self._channel_for(type(msg), topic or default_topic(msg.TYPE))
            seq = self._sequences[channel_id]
            self._sequences[channel_id] = (seq + 1) % 2**32
            self._writer.add_message(
                channel_id=channel_id, log_time=log_time_ns, data=data, publish_time=log_time_ns, sequence=seq
            )
            self._count += 1
            if (
                self._flush_interval_s is not None
                and time.monotonic() - self._last_flush >= self._flush_interval_s
            ):
                self._flush_locked()
            else:
                self._file.flush()  # hand any chunk the writer just closed to the OS

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Store a metadata record (run config, task, seeds...). Names are unique per file;
        ``recording`` is reserved for the recorder."""
        data = _check_str_map(name, data)
        with self._lock:
            self._check_open()
            if name == RECORDING_METADATA or name in self._metadata_names:
                raise ValueError(f"metadata {name!r} is reserved or already written")
            self._metadata_names.add(name)
            self._writer.add_metadata(name, data)
            self._file.flush()

    def write_config(self, name: str, cfg_json: str) -> None:
        """Store a resolved config (JSON text) as metadata ``config/<name>`` = ``{"json": cfg_json}``."""
        if not isinstance(cfg_json, str):
            raise TypeError("cfg_json must be a str of JSON")
        json.loads(cfg_json)  # refuse text that is not JSON (raises ValueError)
        self.add_metadata(CONFIG_METADATA_PREFIX + name, {"json": cfg_json})

    def _flush_locked(self) -> None:
        self._writer.flush()  # closes the open chunk, writes it, flushes our file object
        self._file.flush()
        self._last_flush = time.monotonic()

    def flush(self, fsync: bool = False) -> None:
        """Close the open chunk and hand everything to the OS (``fsync=True``: to the disk too)."""
        with self._lock:
            self._check_open()
            self._flush_locked()
            if fsync:
                os.fsync(self._file.fileno())

    # -- closing ------------------------------------------------------------------------------

    def close(self) -> None:
        """Finish the file (summary, indexes, footer), fsync it and rename it to ``path``."""
        self._finish(None)

    def _finish(self, error: BaseException | None) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            status = {
                "status": "complete" if error is None else "aborted",
                "messages": str(self._count),
                "started_at_ns": str(self._started_ns),
                "finished_at_ns": str(time.time_ns()),
            }
            if error is not None:
                status["error"] = f"{type(error).__name__}: {error}"[:1000]
            try:
                self._writer.add_metadata(RECORDING_METADATA, status)
                self._writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
            except BaseException:
                log.exception("could not finish MCAP recording; partial data left in %s", self.tmp_path)
                self._file.close()
                raise
            self._file.close()
            os.replace(self.tmp_path, self.path)
            _fsync_dir(self.path.parent)
            if error is not None:
                log.warning(
                    "MCAP recording %s closed after an error (%s); %d messages kept",
                    self.path,
                    type(error).__name__,
                    self._count,
                )


def _fsync_dir(directory: Path) -> None:
    with contextlib.suppress(OSError):  # not supported everywhere; the rename is done either way
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


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
    """The linear scan stopped at an incomplete or corrupt record (crashed or damaged file)."""
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


def _scan_records(f: IO[bytes], size: int, stats: ReadStats) -> Iterator:
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
            return  # the data section is complete; the summary repeats what we have seen
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
    for rec in _scan_records(f, size, stats):
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
            records = [r for r in _scan_records(f, size, ReadStats()) if isinstance(r, Metadata)]
        for rec in records:
            out[rec.name] = dict(rec.metadata)
    return out


def read_config(path: PathLike, name: str) -> str | None:
    """The JSON text stored by :meth:`McapRecorder.write_config` under ``name``, or None."""
    entry = read_metadata(path).get(CONFIG_METADATA_PREFIX + name)
    return None if entry is None else entry.get("json")


def recover(path: PathLike, *, out: PathLike | None = None) -> int:
    """How many complete messages a (possibly truncated) recording holds.

    Scans linearly, stopping at the first incomplete or corrupt record; payloads are not decoded
    (see :func:`read_messages` for that). With ``out``, also rewrites them, with their schemas,
    channels, times, sequence numbers and metadata, into a complete MCAP file at ``out`` (written
    via ``<out>.tmp`` and renamed), whose ``recording`` metadata says ``status: recovered``.
    """
    stats = ReadStats()
    with open(path, "rb") as f:
        size = f.seek(0, io.SEEK_END)
        if out is None:
            return sum(1 for r in _scan_records(f, size, stats) if isinstance(r, McapMessage))
        return _rewrite(_scan_records(f, size, stats), Path(path), Path(out))


def _rewrite(records: Iterator, src: Path, out: Path) -> int:
    if out.resolve() == src.resolve():
        raise ValueError("recover(out=...) must name a different file")
    tmp = tmp_path_for(out)
    count = 0
    with open(tmp, "wb") as fo:
        writer = Writer(fo, compression=CompressionType.LZ4)
        started = False
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for rec in records:
            if isinstance(rec, Header):
                writer.start(profile=rec.profile, library=rec.library)
                started = True
                continue
            if not started:
                writer.start(profile=PROFILE, library=LIBRARY)
                started = True
            if isinstance(rec, Schema):
                schema_ids[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
            elif isinstance(rec, Channel):
                channel_ids[rec.id] = writer.register_channel(
                    rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0), dict(rec.metadata)
                )
            elif isinstance(rec, McapMessage) and rec.channel_id in channel_ids:
                writer.add_message(
                    channel_ids[rec.channel_id], rec.log_time, rec.data, rec.publish_time, rec.sequence
                )
                count += 1
            elif isinstance(rec, Metadata) and rec.name != RECORDING_METADATA:
                writer.add_metadata(rec.name, dict(rec.metadata))
        if not started:
            writer.start(profile=PROFILE, library=LIBRARY)
        writer.add_metadata(
            RECORDING_METADATA, {"status": "recovered", "messages": str(count), "recovered_from": src.name}
        )
        writer.finish()
        fo.flush()
        os.fsync(fo.fileno())
    os.replace(tmp, out)
    _fsync_dir(out.parent)
    return count
