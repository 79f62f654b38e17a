"""`mea learner`: train recurrent SAC (Equi-RSAC) or GASv2 (the gasv2 presets: a DreamerV2 world
model with an imagination actor) from replay and broadcast versioned weights.

Design notes: docs/architecture-notes.md, services/learner/main.py."""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from proto.control import ACK_WINDOW, EpisodeAck
from proto.episode import Episode
from proto.topics import EPISODE_ACKS, EPISODES_AUGMENTED, REPLAY_GATE
from proto.weights import WeightsBlob
from services.common import config, weights_file
from services.common.bus.base import Bus, Delivery, Subscription
from services.common.config import ServiceConfig
from services.common.inbox import Inbox, receive_into
from services.common.runtime import ServiceContext, subscribing_bus_factory
from services.common.scalars import ScalarLog
from services.common.weights import WeightsServer
from services.learner import checkpoint, init_actor
from services.learner.config import (
    PRESETS,
    LearnerConfig,
    build_trainer,
    default_run_id,
    without_foreign_group,
)
from services.learner.metrics import UpdateRate, learner_metrics, record_gate, record_update, rejection_reason

log = logging.getLogger(__name__)
ACK_REFRESH_SECONDS = 5.0
"""An unchanged EpisodeAck is published again this often (for actors that joined since)."""
ANNOUNCED_KEPT = 4096
"""Weights versions whose announcement the learner remembers, to tell the lag of the episodes they act."""


class Learner:
    """The service's body, separate from the bus setup so that it can be driven directly."""

    def __init__(self, cfg: LearnerConfig, ctx: ServiceContext, sub: Subscription) -> None:
        self.cfg, self.ctx, self.sub = cfg, ctx, sub
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        self.lock = threading.Lock()  # the trainer's guard: ingest vs the training loop
        self.trainer = build_trainer(cfg, self.lock)
        self.spec = cfg.algorithm.spec()
        self.mx = learner_metrics(ctx.metrics)
        self.mx["replay_bytes"].set(self.trainer.replay.nbytes)
        self.server = WeightsServer(ctx.bus, ctx.instance)
        self.run_id = cfg.run_id or default_run_id(cfg.run_dir)
        self.version = -1
        self.published_at = -1  # updates when the newest version was announced
        # version -> updates owed at its announcement (inserted env steps x samples per insert, less
        # the updates made), for the recent versions: the data the weights that acted an episode had
        # not yet learned from (versions from before a restart, or a limiter with no ratio: unknown)
        self._announced: OrderedDict[int, float | None] = OrderedDict()
        self.lag: float | None = None  # of the newest learned episode, in updates
        self.last: dict[str, float] = {}
        self.counts = {"episodes_in": 0, "rejected": 0}
        self.taken: deque[str] = deque(maxlen=ACK_WINDOW)  # raw episode ids, for EpisodeAck
        self._acks_due, self._acked_at = False, 0.0
        self.wait_seconds = 0.0
        self.segments: list[checkpoint.Segment] = []  # replay segments the newest checkpoint reads
        self._rate = UpdateRate()
        self.scalars = (
            None
            if cfg.tensorboard_dir is None
            else ScalarLog(cfg.tensorboard_dir, cfg.tensorboard_every, ctx.instance)
        )
        # received episodes wait here for the replay, so that receiving never waits on its lock (inbox.py)
        self.inbox: Inbox[Delivery] = Inbox(cfg.inbox_mb << 20)
        self.mx["inbox_bytes"].set_function(lambda: self.inbox.nbytes)  # read at scrape time
        self._stop_receive, self._stop_ingest = threading.Event(), threading.Event()
        self._threads: list[threading.Thread] = []
        self.ckpt_dir = cfg.run_dir / "checkpoints"
        self._last_ckpt = time.monotonic()

    # ---------------------------------------------------------------- replay side
    def ingest(self, ep: Episode) -> None:
        kind = "raw" if ep.augmentation is None else ep.augmentation.kind
        if ep.augmentation is None:  # taken, whatever happens below: the actor may let it go
            self.taken.append(ep.episode_id)
            self._acks_due = True
        lag = self._announced.get(ep.policy_version) if ep.augmentation is None else None
        try:
            self.trainer.insert(ep)
        except ValueError as exc:
            self.counts["rejected"] += 1
            self.mx["rejected"].labels(rejection_reason(str(exc))).inc()
            log.warning("episode refused", extra={"episode_id": ep.episode_id, "error": str(exc)[:300]})
            return
        self.counts["episodes_in"] += 1
        self.mx["episodes_in"].labels(kind).inc()
        if lag is not None:
            self.lag = lag
            self.mx["episode_lag"].observe(lag)

    def _ingest_loop(self) -> None:
        next_gate = 0.0
        # on stop, what was received is still inserted (and acknowledged) before the thread ends
        while not self._stop_ingest.is_set() or len(self.inbox):
            d = self.inbox.get(timeout=0.05)
            if d is not None:
                self.ingest(d.message)
            if time.monotonic() >= next_gate or d is not None:
                self.publish_gate()
                next_gate = time.monotonic() + self.cfg.gate_seconds

    def publish_gate(self) -> None:
        reading = self.trainer.gate()
        record_gate(self.mx, reading)
        gate = reading.message(self.ctx.instance, self.run_id, max(self.version, -1), time.time())
        try:
            self.ctx.bus.publish(REPLAY_GATE, gate, source=self.ctx.instance)
            if self._acks_due or time.monotonic() - self._acked_at > ACK_REFRESH_SECONDS:
                ack = EpisodeAck(learner_id=self.ctx.instance, run_id=self.run_id,
                                 episode_ids=list(self.taken), created_at=time.time())  # fmt: skip
                self.ctx.bus.publish(EPISODE_ACKS, ack, source=self.ctx.instance)
                self._acks_due, self._acked_at = False, time.monotonic()
        except Exception:  # noqa: BLE001 - a lost gate or ack is replaced half a second later
            log.exception("publishing the replay gate failed")

    def start_ingest(self) -> None:
        self._threads = [
            threading.Thread(
                target=receive_into,
                args=(self.sub, self.inbox, self._stop_receive, 0.05),
                name="receive",
                daemon=True,
            ),
            threading.Thread(target=self._ingest_loop, name="ingest", daemon=True),
        ]
        for t in self._threads:
            t.start()

    def stop_ingest(self) -> None:
        """Stop receiving, then insert what was received and stop inserting."""
        self._stop_receive.set()
        if self._threads:
            self._threads[0].join(timeout=5.0)
        self._stop_ingest.set()
        for t in self._threads[1:]:
            t.join(timeout=30.0)

    # ---------------------------------------------------------------- training side
    def try_update(self) -> bool:
        """One update if the limiter allows it; False (after a short wait) otherwise."""
        t0 = time.perf_counter()
        info = self.trainer.step()
        if info is None:
            self.ctx.shutdown.wait(0.02)
            waited = time.perf_counter() - t0
            self.wait_seconds += waited
            self.mx["wait"].inc(waited)
            return False
        # on a GPU the losses come every metrics_every updates (trainer.py, "Devices"): keep the last read
        self.last = info if self.trainer.metrics_every == 1 else self.last | info
        rate = self._rate.tick(time.monotonic())
        record_update(self.mx, info, time.perf_counter() - t0, rate)
        if self.scalars is not None:
            extra = {"updates_per_second": rate}
            if self.lag is not None:
                extra["episode_lag_updates"] = self.lag
            self.scalars.add(info | extra, self.trainer.env_steps)
        if not math.isfinite(info.get("critic_loss", 0.0)):
            log.error("non-finite critic loss", extra={"updates": self.trainer.updates})
        if self.trainer.publish_due():
            self.publish_weights()
        return True

    def publish_weights(self) -> WeightsBlob:
        t0 = time.perf_counter()
        self.version += 1
        checkpoint.record_published(self.ckpt_dir, self.run_id, self.version)
        self.published_at = self.trainer.updates
        self._announced[self.version] = getattr(self.trainer.limiter, "diff", None)  # updates owed
        while len(self._announced) > ANNOUNCED_KEPT:
            self._announced.popitem(last=False)
        tensors = self.trainer.policy_tensors()
        blob = WeightsBlob.create(
            self.version, self.cfg.algorithm.name, self.run_id, tensors, self.spec.to_json()
        )
        payload = blob.encode()  # once, for the bus and the weights file
        self.server.publish(blob, payload)
        creds = self.ctx.bus.credentials
        weights_file.write(self.cfg.run_dir / weights_file.DIRECTORY, blob, None if creds is None else creds.key,
                           self.ctx.instance, body=payload)  # fmt: skip
        self.ctx.policy_version = self.version
        self.mx["version"].set(self.version)
        self.mx["publish_seconds"].observe(time.perf_counter() - t0)
        return blob

    # ---------------------------------------------------------------- checkpoints
    def maybe_checkpoint(self) -> None:
        cfg, since = self.cfg, time.monotonic() - self._last_ckpt
        if checkpoint.due(since, self.trainer.updates, cfg.checkpoint_minutes, cfg.checkpoint_every):
            self.save_checkpoint()

    def save_checkpoint(self) -> Path:
        t0, cfg = time.perf_counter(), self.cfg
        lineage = checkpoint.Lineage(self.version, self.run_id, self.last)
        keep = {"keep": cfg.keep_checkpoints, "max_bytes": cfg.checkpoint_max_bytes}
        with self.lock:
            path, self.segments = checkpoint.save_trainer(
                self.ckpt_dir, self.trainer, lineage, config.to_jsonable(cfg), **keep, segments=self.segments
            )
        self._last_ckpt = time.monotonic()
        self.mx["checkpoints"].inc()
        self.mx["checkpoint_seconds"].observe(time.perf_counter() - t0)
        log.info("checkpoint", extra={"updates": self.trainer.updates, "version": self.version,
                                      "seconds": round(time.perf_counter() - t0, 3)})  # fmt: skip
        return path

    def start_actor_from(self, path: Path) -> None:
        """Load the actor (and a critic encoder it shares) from weights on disk: ``--init-actor``."""
        try:
            file, blob = init_actor.read(path)
            init_actor.load_into(self.trainer, init_actor.check_fits(blob, self.cfg.algorithm))
        except ValueError as exc:
            raise SystemExit(f"learner: --init-actor: {exc}") from None
        log.info("actor initialised from weights", extra={"file": str(file), "source_run": blob.run_id,
                                                          "source_version": blob.version, "digest": blob.digest[:16]})  # fmt: skip

    def restore(self) -> None:
        """Continue the run in ``ckpt_dir``: the checkpoint if there is one, and in any case past the
        newest version the run announced (``checkpoint.continued_lineage``)."""
        restored = None
        if checkpoint.exists(self.ckpt_dir):
            restored, self.segments = checkpoint.restore_trainer(self.ckpt_dir, self.trainer)
        if restored is None:
            log.warning("--resume: no checkpoint yet, starting fresh", extra={"dir": str(self.ckpt_dir)})
        lineage = checkpoint.continued_lineage(
            restored, checkpoint.last_published(self.ckpt_dir), self.run_id
        )
        if restored is not None and lineage.version > restored.version:
            log.warning("versions announced after the checkpoint are skipped",
                        extra={"checkpoint_version": restored.version, "last_announced": lineage.version})  # fmt: skip
        self.version, self.run_id, self.last = lineage.version, lineage.run_id, lineage.last
        log.info("resumed", extra={"version": self.version, "updates": self.trainer.updates,
                                   "replay_transitions": len(self.trainer.replay), "run_id": self.run_id})  # fmt: skip

    # ---------------------------------------------------------------- loop
    def heartbeat_counters(self) -> dict[str, float]:
        out = {
            "updates": self.trainer.updates,
            "env_steps": self.trainer.env_steps,
            "replay_transitions": len(self.trainer.replay),
            # the replay's arrays are reserved at start and touched as they fill: RSS grows with data
            "replay_bytes_filled": self.trainer.replay.nbytes
            * len(self.trainer.replay)
            / max(1, self.trainer.replay.capacity_transitions),
            "version": self.version,
            "episodes_in": self.counts["episodes_in"],
            "rejected": self.counts["rejected"],
            "wait_seconds": self.wait_seconds,
            "inbox_episodes": len(self.inbox),
            "inbox_peak_bytes": self.inbox.peak_bytes,
        }
        out.update({k: v for k, v in self.last.items() if math.isfinite(v)})
        return out

    def loop(self) -> None:
        while not self.ctx.shutdown.is_set() and not self.trainer.done():
            if self.try_update():
                self.maybe_checkpoint()


def run(cfg: LearnerConfig, bus_factory: Callable[[ServiceConfig], Bus] | None = None) -> int:
    holder: dict[str, object] = {}

    def declare(bus: Bus) -> None:
        holder["sub"] = bus.subscribe(EPISODES_AUGMENTED, capacity=cfg.queue)

    def counters() -> dict[str, float]:
        core = holder.get("core")
        return core.heartbeat_counters() if isinstance(core, Learner) else {}

    cfg.run_dir.mkdir(parents=True, exist_ok=True)
    make_bus = subscribing_bus_factory(bus_factory, declare)
    with ServiceContext("learner", cfg.service, bus_factory=make_bus, counters=counters) as ctx:
        core = Learner(cfg, ctx, holder["sub"])  # type: ignore[arg-type]
        fresh = not (cfg.resume and checkpoint.exists(core.ckpt_dir))
        if cfg.resume:
            core.restore()
        if cfg.init_actor is not None and fresh:  # a restarted learner with a checkpoint keeps its own
            core.start_actor_from(cfg.init_actor)
        config.save(dataclasses.replace(cfg, run_id=core.run_id), cfg.run_dir / "learner.json")
        holder["core"] = core
        core.publish_weights()
        core.start_ingest()
        ctx.detail = f"run {core.run_id}"
        log.info("training", extra={"algorithm": cfg.algorithm.name, "group": cfg.algorithm.group, "device": cfg.device, "run_id": core.run_id,
                                    "version": core.version, "replay_bytes": core.trainer.replay.nbytes})  # fmt: skip
        try:
            core.loop()
        finally:
            core.stop_ingest()
            if core.trainer.updates != core.published_at:  # a new version only for new weights
                core.publish_weights()
            core.save_checkpoint()
            core.server.close()
            if core.scalars is not None:
                core.scalars.close()
        log.info("learner done", extra={"updates": core.trainer.updates, "version": core.version})
    return 0


def main(argv: Sequence[str]) -> int:
    return run(
        config.parse(
            LearnerConfig, PRESETS, without_foreign_group(argv), "mea learner", LearnerConfig.__doc__ or ""
        )
    )


__all__ = ["Learner", "main", "run"]
