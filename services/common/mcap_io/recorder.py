"""Writing: :class:`McapRecorder`, crash-tolerant and published atomically at its path on close."""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import IO

from mcap.writer import CompressionType, Writer

from proto.codec import Message
from proto.jsonschema import json_schema_text
from services.common.mcap_io.layout import (
    CONFIG_METADATA_PREFIX,
    LIBRARY,
    MESSAGE_ENCODING,
    PROFILE,
    RECORDING_METADATA,
    RUN_METADATA,
    SCHEMA_ENCODING,
    PathLike,
    default_topic,
    fsync_dir,
    tmp_path_for,
)

log = logging.getLogger(__name__)

_MESSAGE_OVERHEAD = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel, sequence, log and publish times
_COMPRESSIONS = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "none": CompressionType.NONE}


def _check_str_map(name: str, data: dict[str, str]) -> dict[str, str]:
    if not isinstance(name, str) or not name:
        raise ValueError("metadata name must be a non-empty str")
    if not isinstance(data, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in data.items()
    ):
        raise TypeError(f"metadata {name!r} must be a dict[str, str]")
    return dict(data)


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
        self._pending = 0  # message bytes in the open chunk (not in the file yet)
        self._size = 0
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

    @property
    def size_bytes(self) -> int:
        """The file's size so far, the open chunk's messages counted uncompressed (so at least what
        the file will take once they are written; the summary written on close adds a little)."""
        with self._lock:
            return self._size if self._closed else self._file.tell() + self._pending

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
            before = self._file.tell()
            self._writer.add_message(
                channel_id=channel_id, log_time=log_time_ns, data=data, publish_time=log_time_ns, sequence=seq
            )
            written = self._file.tell() != before  # the writer wrote its chunk out, this message included
            self._pending = 0 if written else self._pending + _MESSAGE_OVERHEAD + len(data)
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
        self._pending = 0
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
            self._size = self._file.tell()
            self._file.close()
            os.replace(self.tmp_path, self.path)
            fsync_dir(self.path.parent)
            if error is not None:
                log.warning(
                    "MCAP recording %s closed after an error (%s); %d messages kept",
                    self.path,
                    type(error).__name__,
                    self._count,
                )
