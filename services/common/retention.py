"""How long-running runs bound their disk use: names of numbered files, when a segment is rolled, and
which files to delete.

Pure: names, sizes and ages in, decisions out; the file system is the callers' (the launcher's
recording, ``services.common.mcap_io.segments``; the learner's checkpoints,
``services.learner.checkpoint``).

Recording segments are named ``<prefix>-<run>-<index><suffix>`` (``raw-2-0013.mcap``: resume 2,
segment 13; the index is zero-padded for listings but always compared as a number). A recording made
before segments existed, ``<prefix>-<run><suffix>``, reads as the first part of its run.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence

SEGMENT_DIGITS = 4
"""Zero-padding of segment indexes (names sort in a listing up to 9999; order never relies on it)."""

LEGACY_INDEX = -1
"""Segment index of a single-file recording from before segments: before its run's segment 0."""


def segment_name(run: int, index: int, prefix: str = "raw", suffix: str = ".mcap") -> str:
    """The file name of segment ``index`` of run ``run`` (both >= 0)."""
    if run < 0 or index < 0:
        raise ValueError(f"run and index must be >= 0, got {run}, {index}")
    return f"{prefix}-{run}-{index:0{SEGMENT_DIGITS}d}{suffix}"


def segment_key(name: str, prefix: str = "raw", suffix: str = ".mcap") -> tuple[int, int] | None:
    """``(run, index)`` of a segment's file name, ``(run, LEGACY_INDEX)`` for a single-file recording
    ``<prefix>-<run><suffix>``; None for any other name (a ``.tmp``, another series)."""
    m = re.fullmatch(re.escape(prefix) + r"-(\d+)(?:-(\d+))?" + re.escape(suffix), name)
    if m is None:
        return None
    return int(m.group(1)), LEGACY_INDEX if m.group(2) is None else int(m.group(2))


def ordered_segments(names: Iterable[str], prefix: str = "raw", suffix: str = ".mcap") -> list[str]:
    """The segment names among ``names``, oldest first: by run, then by index, both numerically
    (``raw-2-…`` before ``raw-10-…``); other names are left out."""
    keyed = [(k, n) for n in names if (k := segment_key(n, prefix, suffix)) is not None]
    return [n for _, n in sorted(keyed)]


def should_roll(size_bytes: int, age_seconds: float, max_bytes: int, max_seconds: float) -> bool:
    """Whether the open segment is closed and the next one started: it holds ``max_bytes`` or more
    (> 0), or has been open ``max_seconds`` or longer (> 0). Both 0: one segment for ever."""
    return (max_bytes > 0 and size_bytes >= max_bytes) or (max_seconds > 0 and age_seconds >= max_seconds)


def to_delete(files: Sequence[tuple[str, int]], *, keep: int = 0, max_bytes: int = 0) -> list[str]:
    """Which of ``files`` (``(name, size in bytes)``, oldest first) to delete, oldest first.

    What stays is the newest run of files that is at most ``keep`` long (0: any length) and at most
    ``max_bytes`` in total (0: no budget); the newest file always stays, whatever its size. Everything
    older than the first file that does not fit goes, so what is kept never has holes.
    """
    if keep < 0 or max_bytes < 0:
        raise ValueError(f"keep and max_bytes must be >= 0, got {keep}, {max_bytes}")
    kept, total = 0, 0
    for _, size in reversed(files):
        if kept and ((keep and kept >= keep) or (max_bytes and total + size > max_bytes)):
            break
        kept, total = kept + 1, total + size
    return [name for name, _ in files[: len(files) - kept]]


__all__ = [
    "LEGACY_INDEX",
    "SEGMENT_DIGITS",
    "ordered_segments",
    "segment_key",
    "segment_name",
    "should_roll",
    "to_delete",
]
