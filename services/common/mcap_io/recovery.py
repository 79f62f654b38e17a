"""Recovering a crashed recording: count its complete messages, or rewrite them into a finished file."""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path

from mcap.records import Channel, Header, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.writer import CompressionType, Writer

from services.common.mcap_io.layout import (
    LIBRARY,
    PROFILE,
    RECORDING_METADATA,
    PathLike,
    fsync_dir,
    tmp_path_for,
)
from services.common.mcap_io.reader import ReadStats, scan_records


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
            return sum(1 for r in scan_records(f, size, stats) if isinstance(r, McapMessage))
        return _rewrite(scan_records(f, size, stats), Path(path), Path(out))


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
    fsync_dir(out.parent)
    return count
