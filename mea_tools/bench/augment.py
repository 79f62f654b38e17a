"""`mea bench augment`: augmented transitions/s per core, and raw-in to augmented-out latency.

Design notes: docs/architecture-notes.md, mea_tools/bench/augment.py."""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import statistics
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import tyro

from mea_tools.bench.harness import finite, free_port, host_meta, percentile, wait_alive
from mea_tools.bench.report import emit
from proto.actions import DELTA_THETA, DELTA_XYZ
from proto.episode import Episode
from proto.topics import EPISODES_AUGMENTED, EPISODES_RAW
from services.augmenter.config import AugmenterConfig
from services.augmenter.core.isometric import compose_with_mea
from services.augmenter.core.pipeline import (
    AugmentSettings,
    augment_episode,
    episode_seed,
    isometric_copies,
    mea_copies,
    shared_rotation,
    with_images,
)
from services.augmenter.main import run as run_augmenter
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from services.common.config import ServiceConfig
from services.common.runtime import die_with_parent

TARGET_PER_CORE = 5_000.0
"""Augmented transitions/s per core this project requires (re-projection included)."""
SEGMENTS = ("gripper", "object_0", "object_1")
INSTANCE = "augmenter-bench"
ACTOR = "bench-actor"


@dataclass(frozen=True)
class AugmentBenchConfig:
    """Augmenter benchmark: transitions/s per core (with re-projection) and service latency (127.0.0.1)."""

    episodes: int = 40
    """Synthetic raw demonstrations per throughput pass."""
    rounds: int = 3
    """Throughput passes over the episodes (the median pass is reported)."""
    latency_episodes: int = 100
    """Raw episodes sent one at a time through the service for the latency percentiles."""
    warmup: int = 3
    """Untimed episodes before each measurement (imports, buffers, Zenoh routes)."""
    points_per_segment: int = 256
    """Points per segment (3 segments), as the actors' default camera."""
    min_steps: int = 20
    """Shortest synthetic episode (steps)."""
    max_steps: int = 50
    """Longest synthetic episode (steps; the envs' time limit)."""
    seed: int = 0
    """Seed of the synthetic episodes."""
    augment: AugmentSettings = field(default_factory=AugmentSettings)
    """Augmentation settings (default: 4 isometric + 6 MEA copies of every demo, re-projected)."""
    service: bool = True
    """Also measure the latency through the real service over Zenoh (part 2)."""
    timeout_s: float = 60.0
    """Give up waiting for the service, or for an episode's outputs, after this many seconds."""
    json: bool = False
    """Print exactly one JSON object on stdout instead of tables."""

    def __post_init__(self) -> None:
        for name in ("episodes", "rounds", "latency_episodes", "points_per_segment"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1")
        if not 2 <= self.min_steps <= self.max_steps:
            raise ValueError("need 2 <= min_steps <= max_steps")
        if self.warmup < 0 or not self.timeout_s > 0:
            raise ValueError("warmup must be >= 0 and timeout_s > 0")


# --------------------------------------------------------------------------------------------
# Synthetic raw episodes
# --------------------------------------------------------------------------------------------


def synthetic_episode(seed: int, P: int = 256, T: int = 40, actor_id: str = ACTOR, index: int = 0) -> Episode:
    """A successful scripted-looking demonstration obeying MEA's transition prior exactly.

    Two object clouds fixed in the world, a rigid gripper cloud turning with the yaw, a pivot that
    moves by a * Delta and turns by a^theta * Delta_theta per step from (x, y, 0.39 m); it drifts
    while high, descends below L_z part-way through, then stays low (the contact phase)."""
    rng = np.random.default_rng([seed, index, 7])
    objects = np.stack([
        rng.normal([0.45, -0.08, 0.025], [0.015, 0.015, 0.012], (P, 3)),
        rng.normal([0.55, 0.10, 0.025], [0.015, 0.015, 0.012], (P, 3)),
    ])  # fmt: skip
    grip = rng.normal(0.0, [0.012, 0.04, 0.025], (P, 3))
    grip -= grip.mean(0)
    actions = rng.uniform(-0.5, 0.5, (T, 5)).astype(np.float32)
    actions[:, 0] = np.sign(rng.uniform(-1, 1, T))
    down = int(rng.integers(max(1, T // 4), max(2, T // 2)))
    actions[:down, 3] = rng.uniform(-0.4, 0.2, down)  # drift while high
    actions[down : down + 3, 3] = -1.0  # descend below L_z
    actions[down + 3 :, 3] = 0.0
    a = actions.astype(np.float64)
    pose = np.empty((T + 1, 4))
    pose[0] = [rng.uniform(0.45, 0.55), rng.uniform(-0.05, 0.05), 0.39, rng.uniform(-1, 1)]
    pose[1:, :3] = pose[0, :3] + np.cumsum(a[:, 1:4] * DELTA_XYZ, axis=0)
    pose[1:, 3] = pose[0, 3] + np.cumsum(a[:, 4] * DELTA_THETA)
    c, s = np.cos(pose[:, 3])[:, None], np.sin(pose[:, 3])[:, None]
    points = np.empty((T + 1, 3, P, 3), np.float32)
    points[:, 0, :, 0] = c * grip[:, 0] - s * grip[:, 1]
    points[:, 0, :, 1] = s * grip[:, 0] + c * grip[:, 1]
    points[:, 0, :, 2] = grip[:, 2]
    points[:, 1:] = objects[None] - pose[:, None, None, :3]
    terminated = np.zeros(T, bool)
    terminated[-1] = True
    object_poses = np.zeros((T + 1, 2, 7), np.float32)
    object_poses[:, :, :3] = objects.mean(1)
    object_poses[:, :, 6] = 1.0
    contacts = np.zeros((T + 1, 2), bool)
    contacts[down + 3 :, 0] = True
    return Episode(
        episode_id=f"{actor_id}-{seed}-{index}", task="block_pull", seed=seed, actor_id=actor_id,
        policy_version=-1, policy_kind="expert_direct", is_demo=True, created_at=time.time(),
        segments=list(SEGMENTS), points=points,
        point_counts=rng.integers(300, 1500, (T + 1, 3)).astype(np.int32),
        jaw=np.clip(np.linspace(1.2, -0.2, T + 1), 0, 1).astype(np.float32), actions=actions,
        rewards=np.r_[np.zeros(T - 1), 1.0].astype(np.float32), terminated=terminated,
        truncated=np.zeros(T, bool), gripper_pose=pose.astype(np.float32), object_poses=object_poses,
        contacts=contacts,
    )  # fmt: skip


def make_episodes(cfg: AugmentBenchConfig, n: int, offset: int = 0) -> list[Episode]:
    rng = np.random.default_rng([cfg.seed, offset])
    steps = rng.integers(cfg.min_steps, cfg.max_steps + 1, n)
    return [
        synthetic_episode(cfg.seed, cfg.points_per_segment, int(T), index=offset + i)
        for i, T in enumerate(steps)
    ]


# --------------------------------------------------------------------------------------------
# Throughput
# --------------------------------------------------------------------------------------------


def _log(msg: str) -> None:
    print(f"[bench augment] {msg}", file=sys.stderr, flush=True)


def staged(raw: Episode, s: AugmentSettings) -> tuple[list[Episode], dict[str, float]]:
    """``augment_episode`` step by step (same calls, same order), timing each stage."""
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    seed = episode_seed(s.seed, raw.episode_id)
    out = [raw, *isometric_copies(raw, s.isometric_count(raw), seed)]
    t1 = time.perf_counter()
    if s.applies_mea(raw):
        made = [copy for copy, _ in mea_copies(raw, s.mea, s.mea_copies, seed) if copy is not None]
        if s.isometric_on_mea and made:
            phi = shared_rotation(seed, made)
            made = [compose_with_mea(copy, phi) for copy in made]
        out += made
    t2 = time.perf_counter()
    if s.reproject:
        out = [with_images(e, s.projection) for e in out]
    t3 = time.perf_counter()
    times["isometric"], times["mea"], times["reproject"] = t1 - t0, t2 - t1, t3 - t2
    return out, times


def bench_throughput(cfg: AugmentBenchConfig) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    s = cfg.augment
    episodes = make_episodes(cfg, cfg.episodes)
    for ep in make_episodes(cfg, cfg.warmup, offset=10_000):
        augment_episode(ep, s)

    passes = []
    for _ in range(cfg.rounds):
        transitions = outputs = made = empty = cuts = rejections = 0
        w0, c0 = time.perf_counter(), time.process_time()
        for ep in episodes:
            out, st = augment_episode(ep, s)
            transitions += st.transitions
            outputs += st.outputs
            made, empty, cuts, rejections = made + st.mea_made, empty + st.mea_empty, cuts + st.cuts, rejections + st.rejections  # fmt: skip
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        passes.append((wall, cpu, transitions, outputs, made, empty, cuts, rejections))
    wall, cpu, transitions, outputs, made, empty, cuts, rejections = sorted(passes)[len(passes) // 2]
    per_core = transitions / cpu
    n = len(episodes)
    headline = [
        {
            "what": "augment_episode",
            "raw_episodes": n,
            "mean_steps": float(np.mean([e.num_steps for e in episodes])),
            "outputs_per_raw": outputs / n,
            "mea_made": made,
            "mea_empty": empty,
            "mea_cut": cuts,
            "guard_rejections": rejections,
            "ms_per_raw": finite(wall / n * 1e3),
            "transitions_per_s_wall": finite(transitions / wall),
            "transitions_per_s_per_core": finite(per_core),
            "target_per_core": TARGET_PER_CORE,
            "met": per_core >= TARGET_PER_CORE,
        }
    ]

    # stage by stage (one more pass), plus the wire codec the service adds around the pipeline
    stage = {"isometric": [], "mea": [], "reproject": [], "decode": [], "encode": []}
    for ep in episodes:
        raw_bytes = ep.encode()
        t0 = time.perf_counter()
        Episode.decode(raw_bytes)
        stage["decode"].append(time.perf_counter() - t0)
        out, times = staged(ep, s)
        for k, v in times.items():
            stage[k].append(v)
        t0 = time.perf_counter()
        for e in out:
            e.encode()
        stage["encode"].append(time.perf_counter() - t0)
    pipeline_s = sum(sum(stage[k]) for k in ("isometric", "mea", "reproject"))
    labels = {
        "isometric": f"isometric copies ({s.isometric_copies}: rotate points, actions, poses)",
        "mea": f"MEA math ({s.mea_copies} copies: backward pass, observations, shared rotation)",
        "reproject": "re-projection (voxel projection + uint8 images, every output)",
        "decode": "service only: decode + validate the raw message",
        "encode": "service only: encode + validate every output message",
    }
    breakdown = []
    for key, label in labels.items():
        total = sum(stage[key])
        in_pipeline = key in ("isometric", "mea", "reproject")
        breakdown.append(
            {
                "stage": label,
                "ms_per_raw": finite(total / n * 1e3),
                "share_of_pipeline_pct": finite(100 * total / pipeline_s) if in_pipeline else None,
                "transitions_per_s_if_alone": finite(transitions / total) if total > 0 else None,
            }
        )
    service_s = pipeline_s + sum(stage["decode"]) + sum(stage["encode"])
    breakdown.append(
        {
            "stage": "service path per core (decode + pipeline + encode)",
            "ms_per_raw": finite(service_s / n * 1e3),
            "share_of_pipeline_pct": None,
            "transitions_per_s_if_alone": finite(transitions / service_s),
        }
    )
    return headline, breakdown


# --------------------------------------------------------------------------------------------
# Latency through the service
# --------------------------------------------------------------------------------------------


def service_main(service_cfg) -> None:
    """Spawned child: the augmenter service itself (dies with the bench process)."""
    die_with_parent()
    sys.exit(run_augmenter(service_cfg))


def _stop(proc) -> None:
    if proc is None or proc.pid is None:
        return
    if proc.is_alive():
        proc.terminate()  # SIGTERM: the service shuts down cleanly
        proc.join(timeout=10.0)
    if proc.is_alive():
        proc.kill()
        proc.join(timeout=5.0)


def bench_latency(cfg: AugmentBenchConfig) -> list[dict[str, Any]]:
    s = cfg.augment
    episodes = make_episodes(cfg, cfg.warmup + cfg.latency_episodes, offset=20_000)
    # what the service must send back for each episode (ids, in order), from the local pipeline
    expected = {}
    for ep in episodes:
        out, _ = augment_episode(
            dataclasses.replace(ep, images=None), dataclasses.replace(s, reproject=False)
        )
        expected[ep.episode_id] = [e.episode_id for e in out]
    payloads = [ep.encode() for ep in episodes]

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    service_cfg = AugmenterConfig(
        augment=s,
        queue=4,
        service=ServiceConfig(
            instance_id=INSTANCE,
            zenoh=ZenohConfig(mode="client", connect=(endpoint,)),
            metrics_port=0,
            log_format="text",
            log_level="WARNING",
        ),
    )
    ctx = mp.get_context("spawn")
    router = client = proc = watch = None
    first, last, augment_local = [], [], []
    try:
        router = ZenohBus(ZenohConfig(mode="router", listen=(endpoint,), connect=()))
        client = ZenohBus(ZenohConfig(mode="client", connect=(endpoint,)))
        outputs = client.subscribe(EPISODES_AUGMENTED, capacity=64)
        watch = client.watch_alive("augmenter")
        proc = ctx.Process(target=service_main, args=(service_cfg,), name=INSTANCE, daemon=True)
        proc.start()
        wait_alive(watch, ("augmenter", INSTANCE), proc, cfg.timeout_s)
        for i, (ep, payload) in enumerate(zip(episodes, payloads, strict=True)):
            ids = expected[ep.episode_id]
            t0 = time.monotonic()
            client.publish(EPISODES_RAW, payload, source=ep.actor_id)
            got: list[str] = []
            t_first = None
            while len(got) < len(ids):
                d = outputs.recv(timeout=cfg.timeout_s)
                if d is None:
                    alive = "alive" if proc.is_alive() else f"exited ({proc.exitcode})"
                    raise TimeoutError(
                        f"{len(got)} of {len(ids)} outputs of {ep.episode_id}; service {alive}"
                    )
                if t_first is None:
                    t_first = time.monotonic()
                got.append(d.message.episode_id)
                if d.message.images is None and s.reproject:
                    raise RuntimeError(f"{d.message.episode_id} arrived without images")
            t_last = time.monotonic()
            if got != ids:
                raise RuntimeError(f"outputs of {ep.episode_id}: {got} != {ids}")
            if i >= cfg.warmup:
                first.append(t_first - t0)
                last.append(t_last - t0)
                t1 = time.perf_counter()
                augment_episode(ep, s)
                augment_local.append(time.perf_counter() - t1)
        bad = int(sum(client.stats.bad.values()))
    finally:
        if watch is not None:
            watch.close()
        _stop(proc)
        if client is not None:
            client.close()
        if router is not None:
            router.close()
    if bad:
        raise RuntimeError(f"{bad} messages rejected by the subscriber")
    n_out = statistics.mean(len(v) for v in list(expected.values())[cfg.warmup :])
    return [
        {
            "episodes": len(last),
            "outputs_per_raw": float(n_out),
            "first_output_p50_ms": finite(percentile(first, 50) * 1e3),
            "all_outputs_p50_ms": finite(percentile(last, 50) * 1e3),
            "all_outputs_p99_ms": finite(percentile(last, 99) * 1e3),
            "all_outputs_max_ms": finite(max(last) * 1e3),
            "local_augment_p50_ms": finite(percentile(augment_local, 50) * 1e3),
            "transport_overhead_p50_ms": finite((percentile(last, 50) - percentile(augment_local, 50)) * 1e3),
        }
    ]


def _meta(cfg: AugmentBenchConfig, elapsed: float) -> dict[str, Any]:
    conf = {k: v for k, v in dataclasses.asdict(cfg).items() if k != "augment"}
    s = cfg.augment
    return {
        "config": conf,
        "augment": {
            "mea_copies": s.mea_copies,
            "mea_on": s.mea_on,
            "isometric_copies": s.isometric_copies,
            "isometric_on_mea": s.isometric_on_mea,
            "reproject": s.reproject,
            "image": f"2x{s.projection.size}x{s.projection.size} uint8",
        },
        "units": "transitions = steps of every output episode, raw included; per core = per CPU second "
        "of the single-threaded process; latency = publish of the raw -> last output received and "
        "decoded by the subscriber",
        "topology": "router, publisher and subscriber (clients) in the bench process; the augmenter "
        "service (client) in a spawned process; tcp 127.0.0.1",
        "episodes": f"synthetic demos, 3 segments x {cfg.points_per_segment} points, "
        f"T in [{cfg.min_steps}, {cfg.max_steps}]",
        **host_meta(),
        "elapsed_s": round(elapsed, 2),
    }


def run(cfg: AugmentBenchConfig) -> dict:
    """Run both measurements, print them (tables or one JSON object) and return the result."""
    started = time.monotonic()
    sections: dict[str, list[dict[str, Any]]] = {}
    _log("throughput (single process) ...")
    sections["throughput"], sections["throughput_breakdown"] = bench_throughput(cfg)
    if cfg.service:
        _log("latency through the service over Zenoh ...")
        sections["service_latency"] = bench_latency(cfg)
    return emit(
        "augment", sections, measured={}, as_json=cfg.json, meta=_meta(cfg, time.monotonic() - started)
    )


if __name__ == "__main__":
    run(tyro.cli(AugmentBenchConfig))
