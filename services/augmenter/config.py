"""Settings of `mea augmenter` (``AugmenterConfig``) and its presets: plain data, nothing here opens a bus."""

from __future__ import annotations

from dataclasses import dataclass, field

from services.augmenter.core.pipeline import AugmentSettings
from services.common.config import ServiceConfig


@dataclass(frozen=True)
class AugmenterConfig:
    """Augment raw episodes (isometric + MEA copies, re-projected) and publish them for the learner."""

    augment: AugmentSettings = field(default_factory=AugmentSettings)
    """What is made of each raw episode: copies, which episodes get MEA, projection."""
    queue: int = 16
    """Bounded input queue of raw episodes (full: backpressure)."""
    shard: int = 0
    """This augmenter's shard, 0 <= shard < shards."""
    shards: int = 1
    """Augmenters sharing the load (by crc32(actor_id) % shards)."""
    audit_fraction: float = 0.0
    """Share of MEA copies audited in physics (0: off)."""
    audit_queue: int = 4
    """MEA copies waiting for the audit at most."""
    max_episodes: int = 0
    """Stop after this many valid raw episodes (0: until stopped)."""
    drain_seconds: float = 3.0
    """Seconds to finish queued work on shutdown."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""

    def __post_init__(self) -> None:
        if self.shards < 1 or not 0 <= self.shard < self.shards:
            raise ValueError(
                f"need shards >= 1 and 0 <= shard < shards, got shard={self.shard} shards={self.shards}"
            )
        if self.queue < 1 or self.audit_queue < 1:
            raise ValueError("queue and audit_queue must be >= 1")
        if not 0.0 <= self.audit_fraction <= 1.0:
            raise ValueError(f"audit_fraction must be in [0, 1], got {self.audit_fraction}")
        if self.max_episodes < 0 or self.drain_seconds < 0:
            raise ValueError("max_episodes and drain_seconds must be >= 0")


PRESETS = {
    "default": AugmenterConfig(),
    "baseline": AugmenterConfig(augment=AugmentSettings(mea_on="none")),
}

__all__ = ["PRESETS", "AugmenterConfig"]
