"""`mea learner`: train recurrent SAC (Equi-RSAC) from replay and broadcast versioned weights.

Threads
    * ingest: drains ``EPISODES_AUGMENTED`` (raw episodes pass through the augmenter, then their
      copies) into the sequence replay, and publishes the replay gate. It never waits on training,
      so the Zenoh receive thread is never held up by a gradient update.
    * train (main thread): while the sample-to-insert limiter allows, samples 32 whole episodes,
      runs one SAC update, and every ``publish_every`` updates announces a new weights version.

Rate limiting (``services.learner.core.rate_limiter``)
    Inserts are counted in raw env steps (augmented copies are not new experience) and samples in
    updates. The learner trains only while updates <= samples_per_insert x env steps + slack, so a
    slow actor fleet never makes it over-train the same data, and it waits (counted in
    ``mea_learner_wait_seconds_total``) until ``min_steps`` env steps are in. The other side is the
    replay gate (``ReplayGate`` on ``learner/gate``): the learner publishes how many env steps it will
    take before producers should wait, and actors hold back new episodes while that allowance is
    used up, so fast actors do not run ahead of the learner's update budget. Everything published
    is still accepted: the gate asks, it never drops.

Weights
    Version 0 (random initial weights) is published at start so that actors can act at once;
    a resumed run publishes checkpoint version + 1 and keeps the run id: one version lineage.

Checkpoints (``services.learner.checkpoint``)
    Every ``checkpoint_minutes`` (and every ``checkpoint_every`` updates if set) and on SIGTERM,
    atomically: networks, optimisers, alpha, replay contents, limiter, counters, RNG states,
    weights version and run id. ``--resume`` continues from it.

Bad input
    An episode the replay refuses (no policy images, wrong shape, too long) is logged, counted in
    ``mea_learner_rejected_episodes_total{reason}`` and skipped; the learner keeps running.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from proto.control import ReplayGate
from proto.episode import Episode
from proto.topics import EPISODES_AUGMENTED, REPLAY_GATE
from proto.weights import WeightsBlob
from services.common import config
from services.common.bus.base import Bus, Subscription
from services.common.config import ServiceConfig
from services.common.runtime import ServiceContext, subscribing_bus_factory
from services.common.weights import WeightsServer
from services.learner import checkpoint
from services.learner.config import PRESETS, LearnerConfig, default_run_id
from services.learner.core.batch import to_batch
from services.learner.core.networks import build_actor, build_critic
from services.learner.core.policy import PolicySpec, actor_tensors
from services.learner.core.privileged import STATE_DIM, episode_critic_state
from services.learner.core.rate_limiter import SampleToInsertRatio
from services.learner.core.replay import SequenceReplay
from services.learner.core.sac import RecurrentSAC

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------------


def _metrics(m) -> dict:
    return {
        "updates": m.counter("mea_learner_updates", "Gradient updates done."),
        "update_seconds": m.histogram(
            "mea_learner_update_seconds",
            "Wall time of one update (sample, transfer, losses, optimiser steps).",
            (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0),
        ),
        "loss": m.gauge("mea_learner_loss", "Latest loss by name (critic, actor, alpha, bc).", ["loss"]),
        "alpha": m.gauge("mea_learner_alpha", "Entropy temperature."),
        "batch_demo_share": m.gauge(
            "mea_learner_batch_demo_share",
            "Share of the latest batch's episodes drawn from the demonstration set.",
        ),
        "batch_reward_transitions": m.gauge(
            "mea_learner_batch_reward_transitions", "Transitions with reward > 0 in the latest batch."
        ),
        "entropy": m.gauge("mea_learner_policy_entropy", "Latest policy entropy estimate (-mean log pi)."),
        "q": m.gauge("mea_learner_q", "Latest mean Q values (q1, q2, target).", ["stat"]),
        "updates_per_second": m.gauge("mea_learner_updates_per_second", "Updates per second (recent)."),
        "wait": m.counter("mea_learner_wait_seconds", "Time the trainer waited for the limiter or data."),
        "episodes_in": m.counter("mea_learner_episodes_in", "Episodes inserted, by kind.", ["kind"]),
        "rejected": m.counter(
            "mea_learner_rejected_episodes", "Episodes the replay refused, by reason.", ["reason"]
        ),
        "env_steps": m.gauge("mea_learner_env_steps", "Raw env steps inserted (the limiter's inserts)."),
        "replay_transitions": m.gauge("mea_learner_replay_transitions", "Transitions stored in replay."),
        "replay_episodes": m.gauge("mea_learner_replay_episodes", "Episodes stored in replay."),
        "replay_bytes": m.gauge("mea_learner_replay_bytes", "Bytes reserved by the replay arrays."),
        "can_sample": m.gauge("mea_learner_limiter_can_sample", "1 if the limiter allows an update now."),
        "samples_allowed": m.gauge("mea_learner_limiter_samples_allowed", "Updates the limiter allows now."),
        "inserts_allowed": m.gauge(
            "mea_learner_limiter_inserts_allowed", "Env steps producers may still add before waiting."
        ),
        "version": m.gauge("mea_learner_weights_version", "Latest weights version published."),
        "publish_seconds": m.histogram(
            "mea_learner_weights_publish_seconds",
            "Export, encode and announce one weights version.",
            (0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0),
        ),
        "checkpoints": m.counter("mea_learner_checkpoints", "Checkpoints written."),
        "checkpoint_seconds": m.histogram(
            "mea_learner_checkpoint_seconds", "Time to write one checkpoint.", (0.1, 0.5, 1, 2, 5, 10, 30, 60)
        ),
    }


# --------------------------------------------------------------------------------------------
# the service
# --------------------------------------------------------------------------------------------


class Learner:
    """The service's body, separate from the bus setup so that it can be driven directly."""

    def __init__(self, cfg: LearnerConfig, ctx: ServiceContext, sub: Subscription) -> None:
        self.cfg, self.ctx, self.sub = cfg, ctx, sub
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.sac = RecurrentSAC(build_actor(cfg.net), build_critic(cfg.net), cfg.sac)
        self.replay = SequenceReplay(
            cfg.replay_capacity,
            image_size=cfg.net.image_size,
            seq_len=cfg.seq_len,
            channels=cfg.net.in_channels,
            seed=cfg.seed,
            state_dim=STATE_DIM if cfg.net.critic_input == "state" else 0,
        )
        self.limiter = SampleToInsertRatio(cfg.samples_per_insert, cfg.min_steps, cfg.error_buffer)
        self.spec = PolicySpec(cfg.net, cfg.observation)
        self.lock = threading.Lock()
        self.mx = _metrics(ctx.metrics)
        self.mx["replay_bytes"].set(self.replay.nbytes)
        self.server = WeightsServer(ctx.bus, ctx.instance)
        self.run_id = cfg.run_id or default_run_id(cfg.run_dir)
        self.version = -1
        self.last: dict[str, float] = {}
        self.counts = {"episodes_in": 0, "rejected": 0}
        self.wait_seconds = 0.0
        self._recent: list[float] = []
        self._stop_ingest = threading.Event()
        self._ingest_thread: threading.Thread | None = None
        self.ckpt_dir = cfg.run_dir / "checkpoints"
        self._last_ckpt = time.monotonic()

    @property
    def env_steps(self) -> int:
        """Raw env steps inserted: the limiter's inserts (augmented copies are not counted)."""
        return self.limiter.inserts

    # ---------------------------------------------------------------- replay side
    def ingest(self, ep: Episode) -> None:
        kind = "raw" if ep.augmentation is None else ep.augmentation.kind
        try:
            state = episode_critic_state(ep) if self.replay.state_dim else None
            with self.lock:
                self.replay.insert(ep, state)
                if ep.augmentation is None:
                    self.limiter.inserted(ep.num_steps)
        except ValueError as exc:
            reason = _reason(str(exc))
            self.counts["rejected"] += 1
            self.mx["rejected"].labels(reason).inc()
            log.warning("episode refused", extra={"episode_id": ep.episode_id, "error": str(exc)[:300]})
            return
        self.counts["episodes_in"] += 1
        self.mx["episodes_in"].labels(kind).inc()

    def _ingest_loop(self) -> None:
        next_gate = 0.0
        while not self._stop_ingest.is_set():
            d = self.sub.recv(timeout=0.05)
            if d is not None:
                self.ingest(d.message)
            if time.monotonic() >= next_gate or d is not None:
                self.publish_gate()
                next_gate = time.monotonic() + self.cfg.gate_seconds

    def publish_gate(self) -> None:
        with self.lock:
            inserted = self.env_steps
            allowed = inserted + max(0, self.limiter.inserts_allowed())
            if self.cfg.max_env_steps:
                allowed = max(inserted, min(allowed, self.cfg.max_env_steps))
            replay_n, samples_allowed = len(self.replay), self.limiter.samples_allowed()
            can_sample = self.limiter.can_sample()
        self.mx["env_steps"].set(inserted)
        self.mx["replay_transitions"].set(replay_n)
        self.mx["replay_episodes"].set(self.replay.num_episodes)
        self.mx["inserts_allowed"].set(allowed - inserted)
        self.mx["samples_allowed"].set(samples_allowed)
        self.mx["can_sample"].set(int(can_sample))
        gate = ReplayGate(
            learner_id=self.ctx.instance,
            run_id=self.run_id,
            inserted_steps=inserted,
            allowed_steps=allowed,
            updates=self.sac.updates,
            policy_version=max(self.version, -1),
            replay_transitions=replay_n,
            created_at=time.time(),
        )
        try:
            self.ctx.bus.publish(REPLAY_GATE, gate, source=self.ctx.instance)
        except Exception:  # noqa: BLE001 - a lost gate is replaced half a second later
            log.exception("publishing the replay gate failed")

    def start_ingest(self) -> None:
        self._ingest_thread = threading.Thread(target=self._ingest_loop, name="ingest", daemon=True)
        self._ingest_thread.start()

    def stop_ingest(self) -> None:
        self._stop_ingest.set()
        if self._ingest_thread is not None:
            self._ingest_thread.join(timeout=5.0)

    # ---------------------------------------------------------------- training side
    def try_update(self) -> bool:
        """One update if the limiter allows it; False (after a short wait) otherwise."""
        t0 = time.perf_counter()
        with self.lock:
            ready = self.replay.num_episodes > 0 and self.limiter.can_sample()
            sample = (
                self.replay.sample(
                    self.cfg.batch_size,
                    self.rng,
                    demo_fraction=self.cfg.demo_fraction,
                    successes_as_demos=self.cfg.successes_as_demos,
                    trim=self.cfg.trim_batches,
                )
                if ready
                else None
            )
        if sample is None:
            self.ctx.shutdown.wait(0.02)
            waited = time.perf_counter() - t0
            self.wait_seconds += waited
            self.mx["wait"].inc(waited)
            return False
        info = self.sac.update(to_batch(sample))
        info["batch_demo_share"] = float(sample.from_demo_set.mean())
        info["batch_reward_transitions"] = float((sample.rewards > 0).sum())
        with self.lock:
            self.limiter.sampled()
        dt = time.perf_counter() - t0
        self._record(info, dt)
        if self.sac.updates % self.cfg.publish_every == 0:
            self.publish_weights()
        return True

    def _record(self, info: dict[str, float], dt: float) -> None:
        self.last = info
        mx = self.mx
        mx["updates"].inc()
        mx["update_seconds"].observe(dt)
        for name in ("critic", "actor", "alpha", "bc"):
            if f"{name}_loss" in info:
                mx["loss"].labels(name).set(info[f"{name}_loss"])
        mx["alpha"].set(info["alpha"])
        mx["batch_demo_share"].set(info["batch_demo_share"])
        mx["batch_reward_transitions"].set(info["batch_reward_transitions"])
        mx["entropy"].set(info["entropy"])
        for stat, key in (("q1", "q1"), ("q2", "q2"), ("target", "target_q")):
            mx["q"].labels(stat).set(info[key])
        now = time.monotonic()
        self._recent = [t for t in self._recent if now - t < 30.0] + [now]
        if len(self._recent) > 1:
            mx["updates_per_second"].set((len(self._recent) - 1) / max(1e-9, now - self._recent[0]))
        if not math.isfinite(info["critic_loss"]):
            log.error("non-finite critic loss", extra={"updates": self.sac.updates})

    def publish_weights(self) -> WeightsBlob:
        t0 = time.perf_counter()
        self.version += 1
        blob = WeightsBlob.create(
            self.version,
            "equi_rsac" if self.cfg.algorithm == "equi_rsac" else "rsac",
            self.run_id,
            actor_tensors(self.sac.actor),
            self.spec.to_json(),
        )
        self.server.publish(blob)
        self.ctx.policy_version = self.version
        self.mx["version"].set(self.version)
        self.mx["publish_seconds"].observe(time.perf_counter() - t0)
        return blob

    # ---------------------------------------------------------------- checkpoints
    def maybe_checkpoint(self) -> None:
        cfg = self.cfg
        due = (
            cfg.checkpoint_minutes > 0 and time.monotonic() - self._last_ckpt >= 60.0 * cfg.checkpoint_minutes
        )
        due |= (
            cfg.checkpoint_every > 0 and self.sac.updates > 0 and self.sac.updates % cfg.checkpoint_every == 0
        )
        if due:
            self.save_checkpoint()

    def save_checkpoint(self) -> Path:
        t0 = time.perf_counter()
        with self.lock:
            meta = {
                "version": self.version,
                "run_id": self.run_id,
                "env_steps": self.env_steps,
                "limiter": self.limiter.state_dict(),
                "last": self.last,
                "config": config.to_jsonable(self.cfg),
                "saved_at": time.time(),
            }
            learner = {"sac": self.sac.state_dict(), "rng": checkpoint.rng_state(self.rng)}
            path = checkpoint.save(self.ckpt_dir, learner=learner, replay=self.replay.state_dict(), meta=meta)
        self._last_ckpt = time.monotonic()
        self.mx["checkpoints"].inc()
        self.mx["checkpoint_seconds"].observe(time.perf_counter() - t0)
        log.info("checkpoint", extra={"updates": self.sac.updates, "version": self.version,
                                      "seconds": round(time.perf_counter() - t0, 3)})  # fmt: skip
        return path

    def restore(self) -> None:
        learner, replay, meta = checkpoint.load(self.ckpt_dir)
        self.sac.load_state_dict(learner["sac"])
        checkpoint.restore_rng(learner["rng"], self.rng)
        self.replay.load_state_dict(replay)
        self.limiter.load_state_dict(meta["limiter"])
        self.version, self.run_id = int(meta["version"]), str(meta["run_id"])
        self.last = dict(meta.get("last", {}))
        log.info("resumed", extra={"version": self.version, "updates": self.sac.updates,
                                   "replay_transitions": len(self.replay), "run_id": self.run_id})  # fmt: skip

    # ---------------------------------------------------------------- loop
    def heartbeat_counters(self) -> dict[str, float]:
        out = {
            "updates": self.sac.updates,
            "env_steps": self.env_steps,
            "replay_transitions": len(self.replay),
            "version": self.version,
            "episodes_in": self.counts["episodes_in"],
            "rejected": self.counts["rejected"],
            "wait_seconds": self.wait_seconds,
        }
        out.update({k: v for k, v in self.last.items() if math.isfinite(v)})
        return out

    def done(self) -> bool:
        return self.cfg.max_updates > 0 and self.sac.updates >= self.cfg.max_updates

    def loop(self) -> None:
        while not self.ctx.shutdown.is_set() and not self.done():
            if self.try_update():
                self.maybe_checkpoint()


def _reason(message: str) -> str:
    """A short, bounded metric label from a replay error ("images: ..." -> "images")."""
    head = message.split(":", 1)[0].strip().split()[0] if message.strip() else "invalid"
    return re.sub(r"[^a-z_]", "", head.lower())[:32] or "invalid"


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
        if cfg.resume and checkpoint.exists(core.ckpt_dir):
            core.restore()
        elif cfg.resume:
            log.warning("--resume: no checkpoint yet, starting fresh", extra={"dir": str(core.ckpt_dir)})
        config.save(dataclasses.replace(cfg, run_id=core.run_id), cfg.run_dir / "learner.json")
        holder["core"] = core
        core.publish_weights()
        core.start_ingest()
        ctx.detail = f"run {core.run_id}"
        log.info("training", extra={"algorithm": cfg.algorithm, "group": cfg.net.group, "run_id": core.run_id,
                                    "version": core.version, "replay_bytes": core.replay.nbytes})  # fmt: skip
        try:
            core.loop()
        finally:
            core.stop_ingest()
            core.publish_weights()
            core.save_checkpoint()
            core.server.close()
        log.info("learner done", extra={"updates": core.sac.updates, "version": core.version})
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(LearnerConfig, PRESETS, argv, "mea learner", LearnerConfig.__doc__ or ""))


def launch_args(run_cfg, run_dir: Path, index: int) -> list[str]:
    """Arguments `mea run` passes to the learner: its preset, Equi-RSAC's group per task (C4 for Block
    Pull, D4 for the others), the variant's observation, the run's env-step budget, one torch thread
    (it shares the cores with actors and augmenter; two OpenMP threads on a busy 2-core machine wait
    on each other), state under run_dir/learner, ``--resume`` when the run is resumed."""
    group = "c4" if run_cfg.task == "block_pull" else "d4"
    args = ["--preset", run_cfg.learner_preset, "--net.group", group, "--threads", "1",
            "--observation", "depth" if run_cfg.variant == "equirsac" else "voxel",
            "--max-env-steps", str(run_cfg.env_steps), "--seed", str(run_cfg.seed),
            "--run-dir", str(run_dir / "learner")]  # fmt: skip
    return args + (["--resume"] if run_cfg.resume is not None else [])


__all__ = ["Learner", "launch_args", "main", "run"]
