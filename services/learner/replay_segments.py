"""Incremental replay checkpoints: each checkpoint writes only the episodes no earlier one holds.

A replay's ``state_dict`` is split in two. The *manifest* (the buffer's configuration, counters,
generator state and the serials of its episodes in insertion order) goes into the checkpoint file.
The episodes themselves go into *segments*, ``replay-<n>.npz`` beside the checkpoints, segment ``n``
written with checkpoint ``n`` and holding the episodes stored since the checkpoint before it. A
checkpoint lists the segments it reads, so the older checkpoints kept share their segments, and a
segment is deleted when no kept checkpoint lists it.

Evicted episodes stay in their segment while a kept checkpoint lists it; when the stored episodes
fill less than ``COMPACT_BELOW`` of the transitions the listed segments hold, the next checkpoint
writes every stored episode into its own segment again, so the segments hold at most about twice
the replay.

Segments are numpy archives read with ``allow_pickle=False``: numbers and strings, never objects.
"""

from __future__ import annotations

import os
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

LAYOUT = "segments"
"""``replay["layout"]`` of a checkpoint whose replay lives in segments (older ones hold it whole)."""
COMPACT_BELOW = 0.5
"""Stored share of the listed segments' transitions below which every stored episode is rewritten."""
EPISODE_KEYS = ("lengths", "serial", "is_demo", "kind", "episode_id", "source_episode_id")
"""Per-episode entries of a replay state (one row per episode)."""
OBS_KEYS = ("image_codes", "constant", "state")
"""Per-observation entries (``length + 1`` rows per episode)."""
TRANS_KEYS = ("actions", "rewards", "terminated", "truncated")
"""Per-transition entries (``length`` rows per episode)."""
_TMP = ".replay.npz.tmp"


class SegmentError(ValueError):
    """A segment is missing, damaged or does not hold what its checkpoint lists."""


@dataclass(frozen=True)
class Segment:
    """One segment file as a checkpoint lists it: its name, the serials it holds and their
    transitions."""

    name: str
    serials: tuple[int, ...]
    transitions: int

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "serials": list(self.serials), "transitions": self.transitions}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Segment:
        name = str(d["name"])
        if segment_number(name) is None:
            raise SegmentError(f"{name!r} is not a replay segment's name")
        return cls(name, tuple(int(s) for s in d["serials"]), int(d["transitions"]))


def segment_name(number: int) -> str:
    """The name of the segment written with checkpoint ``number``."""
    return f"replay-{number:06d}.npz"


def segment_number(name: str) -> int | None:
    m = re.fullmatch(r"replay-(\d+)\.npz", name)
    return None if m is None else int(m.group(1))


# ------------------------------------------------------------------------------------------------
# Pure: which episodes to write, and episode-wise slicing of replay states
# ------------------------------------------------------------------------------------------------


def plan(
    previous: list[Segment], serials: np.ndarray, lengths: np.ndarray, compact_below: float = COMPACT_BELOW
) -> tuple[list[Segment], np.ndarray]:
    """(the previous segments still needed, the serials to write into a new segment) for a replay
    storing ``serials`` (with ``lengths`` transitions each), given the segments the newest
    checkpoint lists (``previous``). Everything is rewritten when the stored episodes fill less than
    ``compact_below`` of the previous segments' transitions."""
    serials = np.asarray(serials, np.int64)
    stored = dict(zip(serials.tolist(), np.asarray(lengths).tolist(), strict=True))
    kept = [seg for seg in previous if any(s in stored for s in seg.serials)]
    held = {s for seg in kept for s in seg.serials if s in stored}
    total = sum(seg.transitions for seg in kept)
    if total and sum(stored[s] for s in held) < compact_below * total:
        return [], serials
    return kept, serials[[s not in held for s in serials.tolist()]]


def _row_index(lengths: np.ndarray, positions: np.ndarray, extra: int) -> np.ndarray:
    """Rows of the episodes at ``positions`` (in that order) in arrays that hold ``length + extra``
    rows per episode, episodes concatenated."""
    sizes = lengths.astype(np.int64) + extra
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    take = sizes[positions]
    if not take.size:
        return np.zeros(0, np.int64)
    first = np.repeat(starts[positions] - np.concatenate([[0], np.cumsum(take)[:-1]]), take)
    return first + np.arange(int(take.sum()))


def take(episodes: dict[str, Any], positions: np.ndarray) -> dict[str, Any]:
    """The episodes at ``positions`` of ``episodes`` (the ``EPISODE_KEYS``, ``OBS_KEYS`` and
    ``TRANS_KEYS`` entries of a replay state, whichever it has), in that order."""
    positions = np.asarray(positions, np.int64)
    lengths = np.asarray(episodes["lengths"])
    obs, trans = _row_index(lengths, positions, 1), _row_index(lengths, positions, 0)
    out: dict[str, Any] = {}
    for key, value in episodes.items():
        if key in EPISODE_KEYS:
            out[key] = np.asarray(value)[positions]
        elif key in OBS_KEYS:
            out[key] = np.asarray(value)[obs]
        elif key in TRANS_KEYS:
            out[key] = np.asarray(value)[trans]
    return out


def split(state: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the manifest's part of a replay state, its per-episode arrays)."""
    keys = set(EPISODE_KEYS + OBS_KEYS + TRANS_KEYS)
    return {k: v for k, v in state.items() if k not in keys}, {k: v for k, v in state.items() if k in keys}


def join(manifest: dict[str, Any], parts: list[dict[str, Any]], order: np.ndarray) -> dict[str, Any]:
    """A whole replay state: ``manifest`` with the episodes of ``parts`` (segments' contents) whose
    serials are ``order``, in that order. SegmentError if one is not in any part."""
    keys = [k for k in EPISODE_KEYS + OBS_KEYS + TRANS_KEYS if parts and all(k in p for p in parts)]
    merged: dict[str, Any] = {}
    for key in keys:
        merged[key] = np.concatenate([np.asarray(p[key]) for p in parts]) if parts else np.zeros(0)
    serials = np.asarray(merged.get("serial", np.zeros(0, np.int64)), np.int64)
    where = {s: i for i, s in enumerate(serials.tolist())}  # a serial in two segments: the later one
    missing = [s for s in np.asarray(order).tolist() if s not in where]
    if missing:
        raise SegmentError(
            f"{len(missing)} stored episodes are in none of its segments (serial {missing[0]}, ...)"
        )
    state = dict(manifest)
    positions = np.array([where[s] for s in np.asarray(order).tolist()], np.int64)
    if keys and np.array_equal(positions, np.arange(serials.size)):
        state.update(merged)  # the usual case: segments in insertion order, nothing evicted
    elif keys:
        state.update(take(merged, positions))
    for key in ("episode_id", "source_episode_id"):
        if key in state:
            state[key] = [str(s) for s in state[key]]
    return state


# ------------------------------------------------------------------------------------------------
# Files
# ------------------------------------------------------------------------------------------------


def write(directory: Path, number: int, episodes: dict[str, Any]) -> Segment:
    """Write ``episodes`` (per-episode arrays of a replay state) as segment ``number``, atomically."""
    arrays = {k: np.asarray(v, dtype=str if k.endswith("episode_id") else None) for k, v in episodes.items()}
    path, tmp = directory / segment_name(number), directory / _TMP
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    lengths = np.asarray(episodes["lengths"])
    return Segment(path.name, tuple(int(s) for s in np.asarray(episodes["serial"])), int(lengths.sum()))


def read(directory: Path, segment: Segment) -> dict[str, Any]:
    """The per-episode arrays of ``segment``; SegmentError naming the file and what is wrong."""
    path = directory / segment.name
    try:
        with np.load(path, allow_pickle=False) as archive:
            out = {k: archive[k] for k in archive.files}
    except FileNotFoundError:
        raise SegmentError(f"{path}: missing") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise SegmentError(f"{path}: damaged ({type(exc).__name__}: {str(exc)[:120]})") from None
    if tuple(int(s) for s in out.get("serial", ())) != segment.serials:
        raise SegmentError(f"{path}: does not hold the episodes its checkpoint lists")
    return out


def delete_unlisted(directory: Path, listed: set[str]) -> list[str]:
    """Delete the segments in ``directory`` that no name in ``listed`` names (and a leftover
    temporary file); returns the names deleted."""
    deleted = []
    for name in sorted(os.listdir(directory)):
        if (segment_number(name) is not None and name not in listed) or name == _TMP:
            try:
                (directory / name).unlink()
            except FileNotFoundError:
                continue
            deleted.append(name)
    return deleted
