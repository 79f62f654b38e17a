"""`mea augmenter`: turn every raw episode into what the learner stores, and publish it.

Loop: receive a raw ``Episode`` on ``EPISODES_RAW`` (any actor), skip it unless it belongs to this
shard, run ``augment_episode`` (raw + isometric copies + MEA copies, all re-projected to uint8
policy images) and publish every output on ``EPISODES_AUGMENTED`` with ``source=<instance>``: the
raw episode first, then its isometric copies, then its MEA copies. The learner consumes only that
topic, so raw episodes reach it through here too.

Input backpressure
    Raw episodes wait in a bounded queue (``--queue`` episodes) between the Zenoh receive thread
    and this loop. When the queue is full the receive thread waits until there is room; since
    episodes travel with BLOCK congestion control, the router's queue towards this process then
    fills and the actors' ``publish`` calls block: a slow augmenter slows the actors down instead
    of losing episodes. Nothing accepted is dropped. Publishing outputs blocks the same way when
    the learner is slow, which in turn stops this loop from draining its queue. (Side effect of
    the shared session: while the receive thread waits, nothing else arrives in this process.)
    On shutdown the subscription is closed first (nothing new is accepted), then what is already
    queued is still augmented and published, for at most ``--drain-seconds``.

Sharding
    Several augmenters can share the load: with ``--shards n``, augmenter ``--shard i`` processes
    a raw episode iff ``crc32(episode.actor_id) % n == i`` and skips (and counts) the others. The
    key is the actor id rather than the episode id so that every episode of one actor goes to the
    same augmenter, in the order that actor published them: per-actor order (demonstrations
    first, then the actor's own stream) survives sharding, and one actor's burst cannot be split
    across augmenters and reordered. crc32 is stable across processes and restarts (``hash`` of a
    str is salted per process). Every shard still receives and decodes every raw episode; the
    skip costs a decode (~0.5 ms for a 35-step episode), not an augmentation.

Bad input
    A message that fails to decode or validate is counted by the bus
    (``mea_bus_rejected_messages_total{topic="episodes_raw"}``) and skipped; an episode whose
    augmentation or publication raises is logged, counted (``mea_augmenter_failed_episodes_total``)
    and skipped. Neither stops the service.

Physics audit (optional, ``--audit-fraction f``)
    A background thread replays a fraction f of the MEA copies through the simulator with
    ``services.augmenter.audit_physics.audit_episode`` (imported lazily, in that thread: it pulls in
    pybullet) and exports the fraction of audited transitions found valid
    (``mea_augmenter_audit_valid_ratio``). Copies are chosen by a stable hash of their id. The
    audit sees the MEA copy before the shared isometric rotation (regenerated from its recorded
    seed), because a rotated scene has no simulated counterpart. Its queue is bounded and a copy
    that finds it full is not audited (counted), so the audit never slows augmentation.

Metrics (``mea_augmenter_*``): episodes in (processed / skipped_shard), episodes out (raw /
isometric / mea), transitions out, augment seconds, latency from raw received to its last output
published, age of raw episodes when published, MEA guard rejections, cut and empty MEA copies,
input queue depth, failed episodes, audit counters and the audit valid fraction.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from proto.episode import Episode
from proto.topics import EPISODES_AUGMENTED, EPISODES_RAW
from services.augmenter.core.mea import augment
from services.augmenter.core.pipeline import AugmentSettings, augment_episode, mea_copy_rng
from services.common import config
from services.common.bus.base import Bus, Subscription
from services.common.config import ServiceConfig
from services.common.metrics import ServiceMetrics
from services.common.runtime import ServiceContext, subscribing_bus_factory

log = logging.getLogger(__name__)

MEA_KINDS = ("mea", "mea+isometric")

AuditFn = Callable[[Episode, Episode], np.ndarray]
"""``audit(copy, source) -> (T,) bool``: which transitions of the MEA copy the physics reproduces."""


@dataclass(frozen=True)
class AugmenterConfig:
    """Augment raw episodes (isometric + MEA copies, re-projected) and publish them for the learner."""

    augment: AugmentSettings = field(default_factory=AugmentSettings)
    """What is made of each raw episode: copies, which episodes get MEA, projection."""
    queue: int = 16
    """Bounded input queue (raw episodes). When full, the receive thread waits: backpressure on the
    actors through Zenoh's BLOCK congestion control; nothing accepted is dropped."""
    shard: int = 0
    """This augmenter's shard, 0 <= shard < shards."""
    shards: int = 1
    """Augmenters sharing the load: each processes the raw episodes with crc32(actor_id) % shards ==
    shard, so all episodes of one actor go to one augmenter, in order."""
    audit_fraction: float = 0.0
    """Fraction of MEA copies replayed through physics in a background thread (0: off)."""
    audit_queue: int = 4
    """MEA copies waiting for the audit at most; a copy that finds the queue full is not audited."""
    max_episodes: int = 0
    """Stop after receiving this many valid raw episodes, in this shard or not (0: until stopped)."""
    drain_seconds: float = 3.0
    """On shutdown, time allowed to augment what is already queued and finish pending audits."""
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


def shard_of(actor_id: str, shards: int) -> int:
    """Shard of every episode of ``actor_id``: crc32 (stable across processes) modulo ``shards``."""
    return zlib.crc32(actor_id.encode()) % shards


def output_kind(ep: Episode) -> str:
    """Metric label of an output: raw, isometric or mea (MEA copies, rotated or not)."""
    if ep.augmentation is None:
        return "raw"
    return "mea" if ep.augmentation.kind in MEA_KINDS else "isometric"


# --------------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------------

_SECONDS = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


def _metrics(m: ServiceMetrics) -> dict:
    return {
        "episodes_in": m.counter(
            "mea_augmenter_episodes_in",
            "Raw episodes received, by kind (processed, skipped_shard).",
            ["kind"],
        ),
        "episodes_out": m.counter(
            "mea_augmenter_episodes_out", "Episodes published, by kind (raw, isometric, mea).", ["kind"]
        ),
        "transitions_out": m.counter(
            "mea_augmenter_transitions_out", "Transitions in the published episodes."
        ),
        "augment_seconds": m.histogram(
            "mea_augmenter_augment_seconds", "Time to augment and re-project one raw episode.", _SECONDS
        ),
        "latency_seconds": m.histogram(
            "mea_augmenter_latency_seconds",
            "From a raw episode leaving the input queue to its last output published.",
            _SECONDS,
        ),
        "age_seconds": m.histogram(
            "mea_augmenter_episode_age_seconds",
            "Age of a raw episode (created_at, wall clock) when its last output is published.",
            (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0),
        ),
        "rejections": m.counter(
            "mea_augmenter_mea_rejections", "MEA group draws refused by the feasibility guards."
        ),
        "cuts": m.counter("mea_augmenter_mea_cut_copies", "MEA copies cut short by the feasibility guards."),
        "empty": m.counter(
            "mea_augmenter_mea_empty_copies",
            "MEA copies not made: no non-trivial step left after the guards.",
        ),
        "failed": m.counter(
            "mea_augmenter_failed_episodes", "Raw episodes whose augmentation or publication raised."
        ),
        "queue": m.gauge("mea_augmenter_queue_depth", "Raw episodes waiting in the input queue."),
    }


# --------------------------------------------------------------------------------------------
# physics audit (background)
# --------------------------------------------------------------------------------------------


class PhysicsAudit:
    """The default audit: ``services.augmenter.audit_physics.audit_episode`` in one env per (task, points).

    Everything is imported and built lazily, on the audit thread, at the first copy audited."""

    def __init__(self) -> None:
        self._audit = None
        self._envs: dict = {}

    def __call__(self, copy: Episode, source: Episode) -> np.ndarray:
        if self._audit is None:
            from services.augmenter.audit_physics import audit_episode  # pulls in pybullet

            self._audit = audit_episode
        key = (copy.task, int(copy.points.shape[2]))
        env = self._envs.get(key)
        if env is None:
            from services.tasks import EnvSettings, make_env
            from services.tasks.camera import CameraSettings

            env = make_env(copy.task, EnvSettings(camera=CameraSettings(points_per_segment=key[1])))
            self._envs[key] = env
        return np.asarray(self._audit(env, copy, source).valid, dtype=bool)

    def close(self) -> None:
        for env in self._envs.values():
            with contextlib.suppress(Exception):
                env.close()
        self._envs.clear()


class Auditor:
    """Replays a stable-hash-chosen fraction of MEA copies through ``audit`` on a background thread.

    ``audit(copy, source)`` returns the (T,) validity of the copy's transitions; the default is
    :class:`PhysicsAudit`. Tests inject a stub here. The valid fraction (valid / audited
    transitions, cumulative) is exported as ``mea_augmenter_audit_valid_ratio`` (NaN before the
    first audit). If the audit cannot be imported or raises, that copy counts as an error.
    """

    def __init__(
        self,
        fraction: float,
        settings: AugmentSettings,
        metrics: ServiceMetrics,
        audit: AuditFn | None = None,
        capacity: int = 4,
    ) -> None:
        self.fraction = fraction
        self.settings = settings
        self._audit = audit
        self._q: queue.Queue = queue.Queue(maxsize=capacity)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.copies = self.errors = self.skipped = self.valid = self.transitions = 0
        m = metrics
        self._m_copies = m.counter(
            "mea_augmenter_audited_copies", "MEA copies audited, by result (done, error).", ["result"]
        )
        self._m_skipped = m.counter(
            "mea_augmenter_audit_skipped_copies",
            "MEA copies chosen for the audit but not queued (queue full).",
        )
        self._m_transitions = m.counter(
            "mea_augmenter_audited_transitions", "Transitions of audited MEA copies, by result.", ["result"]
        )
        self._m_fraction = m.gauge(
            "mea_augmenter_audit_valid_ratio",
            "Fraction of audited MEA transitions the physics reproduces (NaN before the first audit).",
        )
        self._m_fraction.set(math.nan)

    @property
    def enabled(self) -> bool:
        return self.fraction > 0.0

    @property
    def valid_fraction(self) -> float:
        return self.valid / self.transitions if self.transitions else math.nan

    def chosen(self, episode_id: str) -> bool:
        """Stable choice of ``fraction`` of the copies (same ids, same choice, in every process)."""
        return zlib.crc32(episode_id.encode()) < self.fraction * 2**32

    def start(self) -> Auditor:
        if self.enabled and self._thread is None:
            self._thread = threading.Thread(target=self._work, name="audit", daemon=True)
            self._thread.start()
        return self

    def offer(self, source: Episode, outputs: Sequence[Episode]) -> int:
        """Queue the chosen MEA copies among ``outputs`` (never blocks); returns how many were queued."""
        if not self.enabled:
            return 0
        queued = 0
        for ep in outputs:
            aug = ep.augmentation
            if aug is None or aug.kind not in MEA_KINDS or not self.chosen(ep.episode_id):
                continue
            try:
                self._q.put_nowait((source, ep))
                queued += 1
            except queue.Full:
                self.skipped += 1
                self._m_skipped.inc()
        return queued

    def unrotated(self, source: Episode, copy: Episode) -> Episode | None:
        """The MEA copy as the physics sees it: regenerated from its seed when it was also rotated."""
        aug = copy.augmentation
        if aug.kind == "mea":
            return copy
        rng = mea_copy_rng(aug.seed, aug.copy_index)
        again, _ = augment(source, self.settings.mea, rng, seed=aug.seed, copy_index=aug.copy_index,
                           episode_id=copy.episode_id)  # fmt: skip
        return again

    def _work(self) -> None:
        audit = self._audit
        try:
            while not self._stop.is_set():
                try:
                    source, copy = self._q.get(timeout=0.2)
                except queue.Empty:
                    continue
                try:
                    if audit is None:
                        audit = self._audit = PhysicsAudit()
                    self._audit_one(audit, source, copy)
                finally:
                    self._q.task_done()
        finally:
            if isinstance(audit, PhysicsAudit):
                audit.close()

    def _audit_one(self, audit: AuditFn, source: Episode, copy: Episode) -> None:
        try:
            target = self.unrotated(source, copy)
            valid = np.asarray(audit(target, source), dtype=bool) if target is not None else None
        except Exception:  # noqa: BLE001 - a failing audit must not take the augmenter down
            log.exception("audit failed", extra={"episode_id": copy.episode_id})
            self.errors += 1
            self._m_copies.labels("error").inc()
            return
        if valid is None:
            return
        n, ok = int(valid.size), int(valid.sum())
        self.copies += 1
        self.valid += ok
        self.transitions += n
        self._m_copies.labels("done").inc()
        self._m_transitions.labels("valid").inc(ok)
        self._m_transitions.labels("invalid").inc(n - ok)
        if self.transitions:
            self._m_fraction.set(self.valid_fraction)

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every queued copy was audited (bounded); True if the queue emptied."""
        if self._thread is None:
            return True
        with self._q.all_tasks_done:  # queue.Queue.join, with a timeout
            return self._q.all_tasks_done.wait_for(lambda: not self._q.unfinished_tasks, timeout)

    def close(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None


# --------------------------------------------------------------------------------------------
# the service
# --------------------------------------------------------------------------------------------


class Augmenter:
    """The service's loop body, separate from the bus setup so it can be driven directly."""

    def __init__(
        self, cfg: AugmenterConfig, ctx: ServiceContext, sub: Subscription, auditor: Auditor
    ) -> None:
        self.cfg = cfg
        self.ctx = ctx
        self.sub = sub
        self.auditor = auditor
        self.mx = _metrics(ctx.metrics)
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
            log.exception("augmenting an episode failed", extra={"episode_id": raw.episode_id})
            self.counts["failed"] += 1
            self.mx["failed"].inc()
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


def launch_args(run_cfg, run_dir: Path, index: int) -> list[str]:
    """Arguments `mea run` passes to augmenter ``index``: what the run's variant augments.

    mea: voxel projection, isometric x4 + MEA x6 on what ``RunConfig.resolved_mea_on`` says (demos in the paper);
    equiobs: voxel projection, isometric x4; equirsac: the rendered depth image, isometric x4."""
    args = ["--augment.seed", str(run_cfg.seed)]
    args += ["--augment.success-isometric-copies", str(run_cfg.resolved_success_rotations())]
    if run_cfg.variant == "mea":
        return args + ["--augment.mea-on", run_cfg.resolved_mea_on()]
    if run_cfg.variant == "equiobs":
        return args + ["--augment.mea-on", "none"]
    return args + ["--augment.mea-on", "none", "--augment.observation", "depth"]


__all__ = [
    "Auditor",
    "Augmenter",
    "AugmenterConfig",
    "PhysicsAudit",
    "launch_args",
    "main",
    "output_kind",
    "run",
    "shard_of",
]
