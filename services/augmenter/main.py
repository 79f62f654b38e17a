"""`mea augmenter`: turn every raw episode into what the learner stores, and publish it.

Design notes: docs/architecture-notes.md, services/augmenter/main.py."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Sequence

from proto.episode import Episode
from proto.topics import EPISODES_AUGMENTED, EPISODES_RAW
from services.augmenter.audit_worker import AuditFn, Auditor
from services.augmenter.config import PRESETS, AugmenterConfig
from services.augmenter.core.pipeline import augment_episode
from services.augmenter.core.routing import output_kind, shard_of
from services.augmenter.metrics import augmenter_metrics
from services.common import config
from services.common.bus.base import Bus, Subscription
from services.common.config import ServiceConfig
from services.common.runtime import ServiceContext, subscribing_bus_factory

log = logging.getLogger(__name__)


class Augmenter:
    """The service's loop body, separate from the bus setup so it can be driven directly."""

    def __init__(
        self, cfg: AugmenterConfig, ctx: ServiceContext, sub: Subscription, auditor: Auditor
    ) -> None:
        self.cfg = cfg
        self.ctx = ctx
        self.sub = sub
        self.auditor = auditor
        self.mx = augmenter_metrics(ctx.metrics)
        self.mx["queue"].set_function(sub.qsize)
        self.received = 0
        self.counts = {"episodes_in": 0, "episodes_out": 0, "transitions_out": 0, "skipped_shard": 0,
                       "failed": 0}  # fmt: skip

    def heartbeat_counters(self) -> dict[str, float]:
        """For the launcher table (the first four are shown): processed in, out, transitions, queue."""
        out = {
            "episodes_in": self.counts["episodes_in"],
            "episodes_out": self.counts["episodes_out"],
            "transitions_out": self.counts["transitions_out"],
            "queue": self.sub.qsize(),
            "skipped_shard": self.counts["skipped_shard"],
            "failed": self.counts["failed"],
        }
        if self.auditor.enabled:
            out["audited_copies"] = self.auditor.copies
            if self.auditor.transitions:  # heartbeat counters must be finite: none before the first audit
                out["audit_valid_fraction"] = self.auditor.valid_fraction
        return out

    def in_shard(self, ep: Episode) -> bool:
        return shard_of(ep.actor_id, self.cfg.shards) == self.cfg.shard

    def handle(self, raw: Episode) -> None:
        """One raw episode: shard filter, augment, publish raw first then the copies."""
        t_recv = time.monotonic()
        self.received += 1
        if not self.in_shard(raw):
            self.counts["skipped_shard"] += 1
            self.mx["episodes_in"].labels("skipped_shard").inc()
            return
        self.counts["episodes_in"] += 1
        self.mx["episodes_in"].labels("processed").inc()
        try:
            t0 = time.perf_counter()
            outputs, stats = augment_episode(raw, self.cfg.augment)
            self.mx["augment_seconds"].observe(time.perf_counter() - t0)
            for ep in outputs:
                self.ctx.bus.publish(EPISODES_AUGMENTED, ep, source=self.ctx.instance)
                self.counts["episodes_out"] += 1
                self.counts["transitions_out"] += ep.num_steps
                self.mx["episodes_out"].labels(output_kind(ep)).inc()
                self.mx["transitions_out"].inc(ep.num_steps)
        except Exception:  # noqa: BLE001 - one bad episode must not take the augmenter down
            log.exception(
                "augmenting an episode failed; passing it on unaugmented",
                extra={"episode_id": raw.episode_id},
            )
            self.counts["failed"] += 1
            self.mx["failed"].inc()
            # the actor's data is still good: the learner takes (and acknowledges) it without copies
            with contextlib.suppress(Exception):
                self.ctx.bus.publish(EPISODES_AUGMENTED, raw, source=self.ctx.instance)
            return
        self.mx["latency_seconds"].observe(time.monotonic() - t_recv)
        self.mx["age_seconds"].observe(max(0.0, time.time() - raw.created_at))
        self.mx["rejections"].inc(stats.rejections)
        self.mx["cuts"].inc(stats.cuts)
        self.mx["empty"].inc(stats.mea_empty)
        self.auditor.offer(raw, outputs)

    def done(self) -> bool:
        return self.cfg.max_episodes > 0 and self.received >= self.cfg.max_episodes

    def loop(self) -> None:
        while not self.ctx.shutdown.is_set() and not self.done():
            d = self.sub.recv(timeout=0.25)
            if d is not None:
                self.handle(d.message)

    def drain(self) -> None:
        """After the loop: accept nothing new, then augment what was already queued (bounded)."""
        self.sub.close()
        deadline = time.monotonic() + self.cfg.drain_seconds
        while time.monotonic() < deadline and not self.done():
            d = self.sub.recv(timeout=0.0)
            if d is None:
                break
            self.handle(d.message)
        left = self.sub.qsize()
        if left:
            log.warning("queued raw episodes not augmented at shutdown", extra={"episodes": left})
        self.auditor.wait_idle(max(0.0, deadline - time.monotonic()))


def run(cfg: AugmenterConfig, bus_factory: Callable[[ServiceConfig], Bus] | None = None,
        audit: AuditFn | None = None) -> int:  # fmt: skip
    """Run the augmenter until stopped (or ``max_episodes``); ``audit`` replaces the physics audit."""
    holder: dict[str, object] = {}

    def declare(bus: Bus) -> None:
        holder["sub"] = bus.subscribe(EPISODES_RAW, capacity=cfg.queue)

    def counters() -> dict[str, float]:
        core = holder.get("core")
        return core.heartbeat_counters() if isinstance(core, Augmenter) else {}

    make_bus = subscribing_bus_factory(bus_factory, declare)
    with ServiceContext("augmenter", cfg.service, bus_factory=make_bus, counters=counters) as ctx:
        auditor = Auditor(cfg.audit_fraction, cfg.augment, ctx.metrics, audit, cfg.audit_queue).start()
        core = Augmenter(cfg, ctx, holder["sub"], auditor)  # type: ignore[arg-type]
        holder["core"] = core
        ctx.detail = f"shard {cfg.shard}/{cfg.shards}"
        log.info("augmenting", extra={"shard": cfg.shard, "shards": cfg.shards, "queue": cfg.queue,
                                      "mea_on": cfg.augment.mea_on, "audit_fraction": cfg.audit_fraction})  # fmt: skip
        try:
            core.loop()
            core.drain()
        finally:
            auditor.close()
        log.info("augmenter done", extra=dict(core.counts, received=core.received))
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(AugmenterConfig, PRESETS, argv, "mea augmenter", AugmenterConfig.__doc__ or ""))


__all__ = ["Augmenter", "main", "run"]
