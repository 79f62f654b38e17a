"""Which augmenter handles a raw episode (``shard_of``) and what kind of output an episode is
(``output_kind``, ``MEA_KINDS``).

Sharding is by actor id rather than episode id, so that every episode of one actor goes to the same
augmenter, in the order that actor published them: per-actor order (demonstrations first, then the
actor's own stream) survives sharding. crc32 is stable across processes and restarts (``hash`` of a
str is salted per process).
"""

from __future__ import annotations

import zlib

from proto.episode import Episode

MEA_KINDS = ("mea", "mea+isometric")
"""``Augmentation.kind`` of MEA copies, rotated or not."""


def shard_of(actor_id: str, shards: int) -> int:
    """Shard of every episode of ``actor_id``: crc32 (stable across processes) modulo ``shards``."""
    return zlib.crc32(actor_id.encode()) % shards


def output_kind(ep: Episode) -> str:
    """Metric label of an output: raw, isometric or mea (MEA copies, rotated or not)."""
    if ep.augmentation is None:
        return "raw"
    return "mea" if ep.augmentation.kind in MEA_KINDS else "isometric"


__all__ = ["MEA_KINDS", "output_kind", "shard_of"]
