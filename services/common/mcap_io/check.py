"""What one recording holds and whether it is whole (the report behind `mea recording check`)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from proto.msgpack_wire import DEFAULT_LIMITS, Limits
from services.common.mcap_io.layout import RECORDING_METADATA, PathLike
from services.common.mcap_io.reader import Damage, ReadStats, decoded_records, read_metadata


@dataclass(frozen=True)
class RecordingReport:
    """One file's messages, channels, time range and damage."""

    path: str
    size: int
    messages: int
    """Messages read and decoded (up to the damage, if any)."""
    channels: dict[str, int] = field(default_factory=dict)
    """Messages per topic."""
    first_ns: int | None = None
    """Smallest and largest log time (UNIX ns); None without messages."""
    last_ns: int | None = None
    indexed: bool = False
    """Read through its summary (a finished file)."""
    bad_records: int = 0
    """Messages that did not decode (skipped)."""
    ignored: int = 0
    """Messages on channels that are not msgpack (not ours)."""
    damage: Damage | None = None
    status: str = ""
    """The ``recording`` metadata's status (complete, aborted, recovered); empty: never closed."""
    errors: tuple[str, ...] = ()

    @property
    def whole(self) -> bool:
        return self.damage is None and self.bad_records == 0


def check_recording(path: PathLike, limits: Limits = DEFAULT_LIMITS) -> RecordingReport:
    """Read all of ``path`` (every message decoded, bad ones counted) and report it. Raises OSError for
    a file that cannot be read and ``mcap.exceptions.InvalidMagic`` for one that is not MCAP."""
    stats = ReadStats()
    channels: Counter[str] = Counter()
    first = last = None
    for channel, rec, _ in decoded_records(path, None, limits, "skip", stats):
        channels[channel.topic] += 1
        first = rec.log_time if first is None else min(first, rec.log_time)
        last = rec.log_time if last is None else max(last, rec.log_time)
    status = read_metadata(path).get(RECORDING_METADATA, {}).get("status", "")
    return RecordingReport(
        path=str(path),
        size=Path(path).stat().st_size,
        messages=stats.messages,
        channels=dict(channels),
        first_ns=first,
        last_ns=last,
        indexed=stats.indexed,
        bad_records=stats.skipped,
        ignored=stats.ignored,
        damage=stats.damage[0] if stats.damage else None,
        status=status,
        errors=tuple(stats.errors),
    )
