"""A recording in numbered segments, so that a run of days keeps its disk use bounded.

:class:`SegmentedRecorder` writes bounded MCAP segments and deletes the oldest finished ones past a
byte budget; :func:`recording_segments` and :func:`read_recording` read them back in order.

Design notes: docs/architecture-notes.md, services/common/mcap_io/segments.py."""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from proto.codec import Message
from proto.msgpack_wire import DEFAULT_LIMITS, Limits
from services.common.mcap_io.layout import TMP_SUFFIX, PathLike
from services.common.mcap_io.reader import OnError, ReadStats, read_messages
from services.common.mcap_io.recorder import McapRecorder
from services.common.retention import ordered_segments, segment_key, segment_name, should_roll, to_delete

log = logging.getLogger(__name__)

SEGMENT_METADATA = "segment"
"""Metadata record of each segment: ``run`` and ``index`` (decimal strings)."""
PREFIX = "raw"
SUFFIX = ".mcap"


def _base(name: str) -> str:
    return name[: -len(TMP_SUFFIX)] if name.endswith(TMP_SUFFIX) else name


def recording_segments(directory: PathLike, prefix: str = PREFIX, *, unfinished: bool = True) -> list[Path]:
    """The segment files in ``directory``, oldest first. With ``unfinished``, a segment that was
    never closed (a killed launcher, or the one being written now) is there as its ``.tmp``, which
    :func:`read_messages` reads up to its last complete chunk; without, only finished files."""
    d = Path(directory)
    if not d.is_dir():
        return []
    names = set(os.listdir(d))
    bases = {_base(n) for n in names if unfinished or not n.endswith(TMP_SUFFIX)}
    return [d / b if b in names else d / (b + TMP_SUFFIX) for b in ordered_segments(bases, prefix, SUFFIX)]


def read_recording(
    directory: PathLike,
    prefix: str = PREFIX,
    *,
    unfinished: bool = True,
    types: set[str] | None = None,
    limits: Limits = DEFAULT_LIMITS,
    on_error: OnError = "raise",
    stats: ReadStats | None = None,
) -> Iterator[tuple[str, Message]]:
    """``(topic, message)`` of every segment in ``directory`` (:func:`recording_segments`), segment
    after segment, each in file order (see :func:`read_messages`; ``stats`` adds up over the
    segments and is ``truncated`` if any segment is, with each damaged one in ``stats.damage``).
    ``directory`` may also be one recording file, which is read alone; a path that does not exist
    reads as empty, with a warning."""
    stats = stats if stats is not None else ReadStats()
    d = Path(directory)
    if d.is_file():  # one file, e.g. a segment or `mea demos` output: not silently nothing
        paths = [d]
    else:
        if not d.exists():
            log.warning("no recording at %s: the path does not exist", d, extra={"path": str(d)})
        paths = recording_segments(d, prefix, unfinished=unfinished)
    for path in paths:
        yield from read_messages(path, types=types, limits=limits, on_error=on_error, stats=stats)


class SegmentedRecorder:
    """Record wire messages into rolling segments ``<directory>/<prefix>-<run>-<index>.mcap``.

    ``segment_bytes`` / ``segment_seconds``: roll once the open segment reaches that size (its open
    chunk counted uncompressed) or age (0: no such limit); ``max_bytes``: budget of the finished
    segments in ``directory`` (0: none). Indexes continue after any segment of ``run`` already there,
    so nothing is overwritten. The first segment opens at once, later ones with their first message
    (an idle run leaves no empty files). Thread-safe.
    """

    def __init__(
        self,
        directory: PathLike,
        run: int,
        *,
        metadata: dict[str, str] | None = None,
        compression: str = "zstd",
        segment_bytes: int = 0,
        segment_seconds: float = 0.0,
        max_bytes: int = 0,
        prefix: str = PREFIX,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if segment_bytes < 0 or segment_seconds < 0 or max_bytes < 0:
            raise ValueError("segment_bytes, segment_seconds and max_bytes must be >= 0")
        self.directory, self.run, self.prefix = Path(directory), int(run), prefix
        self.metadata, self.compression = dict(metadata or {}), compression
        self.segment_bytes, self.segment_seconds, self.max_bytes = segment_bytes, segment_seconds, max_bytes
        self._clock = clock
        self._lock = threading.Lock()
        self._current: McapRecorder | None = None
        self._opened_at = 0.0
        self._closed = False
        self.message_count = 0
        """Messages written, over every segment."""
        self.directory.mkdir(parents=True, exist_ok=True)
        taken = [segment_key(_base(n), prefix, SUFFIX) for n in os.listdir(self.directory)]
        self._next = 1 + max((k[1] for k in taken if k is not None and k[0] == self.run), default=-1)
        self.prune()
        with self._lock:
            self._open()

    @property
    def path(self) -> Path | None:
        """Where the open segment will be once closed (None between segments)."""
        current = self._current
        return None if current is None else current.path

    def _open(self) -> None:
        index = self._next
        path = self.directory / segment_name(self.run, index, self.prefix, SUFFIX)
        rec = McapRecorder(path, metadata=self.metadata or None, compression=self.compression)
        try:
            rec.add_metadata(SEGMENT_METADATA, {"run": str(self.run), "index": str(index)})
        except BaseException:
            rec.close()
            raise
        self._current, self._opened_at, self._next = rec, self._clock(), index + 1

    def _due(self, rec: McapRecorder) -> bool:
        age = self._clock() - self._opened_at
        due = should_roll(rec.size_bytes, age, self.segment_bytes, self.segment_seconds)
        return due and rec.message_count > 0

    def write(self, msg: Message, log_time_ns: int | None = None, topic: str | None = None) -> None:
        """Append ``msg`` to the open segment (opening the next one if none is), then roll if due."""
        with self._lock:
            if self._closed:
                raise RuntimeError(f"segmented recorder in {self.directory} is closed")
            if self._current is None:
                self._open()
            rec = self._current
            assert rec is not None
            rec.write(msg, log_time_ns=log_time_ns, topic=topic)
            self.message_count += 1
            rolled = self._due(rec)
            if rolled:
                self._close_current()
        if rolled:
            self.prune()

    def tick(self) -> None:
        """Roll if the open segment is old enough (call it while no message comes: an idle hour
        still ends a segment). A segment with no message is never rolled."""
        with self._lock:
            rec = self._current
            if rec is None or not self._due(rec):
                return
            self._close_current()
        self.prune()

    def _close_current(self) -> None:
        rec, self._current = self._current, None
        if rec is not None:
            rec.close()
            log.info("recording segment closed", extra={"path": str(rec.path), "messages": rec.message_count,
                                                         "bytes": rec.size_bytes})  # fmt: skip

    def prune(self) -> list[Path]:
        """Delete the oldest finished segments beyond ``max_bytes``; returns what was deleted."""
        if not self.max_bytes:
            return []
        files = []
        for path in recording_segments(self.directory, self.prefix, unfinished=False):
            try:
                files.append((path.name, path.stat().st_size))
            except FileNotFoundError:  # deleted meanwhile
                continue
        deleted = []
        for name in to_delete(files, max_bytes=self.max_bytes):
            path = self.directory / name
            try:
                path.unlink()
            except FileNotFoundError:  # another prune got there first
                continue
            except OSError as exc:
                log.warning("recording segment not deleted", extra={"path": str(path), "error": str(exc)})
                continue
            deleted.append(path)
            log.info("recording segment deleted (recording_max_bytes)", extra={"path": str(path)})
        return deleted

    def close(self) -> None:
        """Close the open segment (if any) and apply the budget; later writes raise."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._close_current()
        self.prune()

    def __enter__(self) -> SegmentedRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["SEGMENT_METADATA", "SegmentedRecorder", "read_recording", "recording_segments"]
