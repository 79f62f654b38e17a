"""Transport benchmark: episode codec speed, Zenoh pub/sub throughput and weight-pull latency.

Three measurements, all on this machine over 127.0.0.1:

1. **Episode codec**: encode and decode (with full validation) of a seeded 50-step ``Episode`` in
   three variants: point clouds only; plus 2x84x84 ``uint8`` images (the compact projected form);
   plus 2x84x84 ``float32`` images (what the public code would send).
2. **Episode pub/sub**: a Zenoh router opened in this process, a subscriber in a spawned process
   that decodes and validates every episode (``Subscription.recv``), and a publisher in this
   process. Readiness is the subscriber's liveliness token, never a sleep.
3. **Weights pull**: a spawned process serves ``WEIGHTS_LATEST`` from pre-encoded bytes; this
   process queries it with ``min_version`` (pull latency), and times announcement -> blob pulled
   (the server publishes ``WEIGHTS_ANNOUNCE``, this process receives it and then queries).

Every session is a Zenoh client of the in-process router (the deployed topology: producer ->
router -> consumer); multicast scouting stays off. MB means 10^6 bytes throughout. Cross-process
latencies use ``time.monotonic`` (CLOCK_MONOTONIC, one clock for every process on a Linux host).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.metadata
import math
import multiprocessing as mp
import os
import platform
import queue
import socket
import statistics
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from proto.episode import Episode
from proto.topics import EPISODES_RAW, WEIGHTS_ANNOUNCE, WEIGHTS_LATEST
from proto.weights import WeightsBlob
from services.bench.report import emit

MB = 1e6
SUB_SERVICE = "bench-transport-sub"
SERVER_SERVICE = "bench-transport-weights"
INSTANCE = "0"
SOURCE = "bench-transport"
SEGMENTS = ("gripper", "block", "goal")
VARIANTS = (("a", None), ("b", "uint8"), ("c", "float32"))  # (name, image dtype or no images)


@dataclass(frozen=True)
class TransportBenchConfig:
    """Transport benchmark: episode codec, Zenoh pub/sub throughput, weight-pull latency (127.0.0.1)."""

    episodes: int = 200
    """Episodes published for the pub/sub throughput measurement (variant b: uint8 images)."""
    repeats: int = 20
    """Encode/decode repetitions per episode variant (the median is reported)."""
    pulls: int = 50
    """Weight pulls per blob size for the latency percentiles (and as many announce->pulled rounds)."""
    warmup: int = 3
    """Untimed warm-up pulls and announce rounds per blob size (route and buffer set-up)."""
    blob_sizes_mb: tuple[float, ...] = (1.0, 10.0)
    """WeightsBlob sizes in MB (10^6 bytes of float32 tensors)."""
    steps: int = 50
    """Steps per episode (T actions, T+1 observations)."""
    points_per_segment: int = 1024
    """Points per point-cloud segment (3 segments: gripper and two objects)."""
    image_size: int = 84
    """Side of the square policy images (2 channels) in variants b and c."""
    subscriber_capacity: int = 16
    """Queue capacity of the subscriber (back-pressure on the publisher when full)."""
    encode_in_loop: bool = False
    """Encode each episode inside the publish loop (actor-like) instead of publishing pre-encoded bytes."""
    seed: int = 0
    """Seed of the synthetic episode and weight data."""
    timeout_s: float = 60.0
    """Give up waiting for a child process, a message or a reply after this many seconds."""
    json: bool = False
    """Print exactly one JSON object on stdout instead of tables."""

    def __post_init__(self) -> None:
        for name in ("episodes", "repeats", "pulls", "steps", "points_per_segment", "image_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1")
        if self.warmup < 0 or self.subscriber_capacity < 1 or not self.timeout_s > 0:
            raise ValueError("warmup must be >= 0, subscriber_capacity >= 1 and timeout_s > 0")
        if any(not (0 < mb <= 100) for mb in self.blob_sizes_mb):
            raise ValueError("blob sizes must be in (0, 100] MB")


def variant_label(cfg: TransportBenchConfig, name: str, image_dtype: str | None) -> str:
    if image_dtype is None:
        return f"{name}: points"
    short = {"uint8": "u8", "float32": "f32"}[image_dtype]
    return f"{name}: points+2x{cfg.image_size}x{cfg.image_size} {short}"


# --------------------------------------------------------------------------------------------
# Synthetic data
# --------------------------------------------------------------------------------------------


def make_episode(cfg: TransportBenchConfig, image_dtype: str | None, index: int = 0) -> Episode:
    """A seeded, plausible episode: smooth gripper path, objects, point clouds, optional heightmaps."""
    rng = np.random.default_rng((cfg.seed, index))
    T, S, P, H = cfg.steps, len(SEGMENTS), cfg.points_per_segment, cfg.image_size
    t = np.linspace(0.0, 1.0, T + 1)
    gripper = np.stack([0.45 + 0.1 * t, 0.08 * np.sin(2 * np.pi * t), 0.30 - 0.26 * t, 0.6 * t], axis=1)
    obj_xyz = np.empty((T + 1, S - 1, 3))
    obj_xyz[:, 0] = [0.55, 0.0, 0.02]  # block, pulled along x in the second half
    obj_xyz[:, 0, 0] -= 0.1 * np.clip(2 * t - 1, 0, 1)
    obj_xyz[:, 1] = [0.40, 0.05, 0.0]  # goal marker
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (T + 1, S - 1, 1))
    object_poses = np.concatenate([obj_xyz, quat], axis=2)

    # gripper-centric clouds: a fixed template per segment, moved by the relative position
    scale = np.array([0.02, 0.025, 0.03])[:, None, None]
    template = rng.standard_normal((S, P, 3)) * scale
    centres = np.zeros((T + 1, S, 3))
    centres[:, 1:] = obj_xyz - gripper[:, None, :3]
    points = centres[:, :, None, :] + template[None] + rng.standard_normal((T + 1, S, P, 3)) * 1e-3

    images = None
    if image_dtype is not None:
        lin = np.linspace(-0.3, 0.3, H)
        yy, xx = np.meshgrid(lin, lin, indexing="ij")
        rel = obj_xyz[:, 0, :2] - gripper[:, :2]  # block in the gripper-centred image
        d2 = (xx[None] - rel[:, 0, None, None]) ** 2 + (yy[None] - rel[:, 1, None, None]) ** 2
        height = 0.2 * np.exp(-d2 / (2 * 0.03**2)) + 0.02 * (xx[None] + 0.3)
        gripper_mask = np.exp(-(xx**2 + yy**2) / (2 * 0.02**2))[None] * (1 - 0.5 * t[:, None, None])
        imgs = np.stack([height / 0.25, np.broadcast_to(gripper_mask, height.shape)], axis=1)
        imgs = np.clip(imgs, 0.0, 1.0)
        images = np.round(imgs * 255).astype(np.uint8) if image_dtype == "uint8" else imgs.astype(np.float32)

    terminated = np.zeros(T, dtype=bool)
    terminated[-1] = True
    rewards = np.zeros(T, dtype=np.float32)
    rewards[-1] = 1.0
    actions = np.clip(np.cumsum(rng.normal(0, 0.2, (T, 5)), axis=0) / 3, -1, 1)
    contacts = np.zeros((T + 1, S - 1), dtype=bool)
    contacts[T // 2 :, 0] = True
    return Episode(
        episode_id=f"{SOURCE}-{cfg.seed}-{index}",
        task="block_pull",
        seed=cfg.seed,
        actor_id=SOURCE,
        policy_version=-1,
        policy_kind="expert_direct",
        is_demo=True,
        created_at=time.time(),
        segments=list(SEGMENTS),
        points=points.astype(np.float32),
        point_counts=rng.integers(200, 2000, (T + 1, S)).astype(np.int32),
        jaw=np.clip(1.0 - 1.5 * t, 0.0, 1.0).astype(np.float32),
        actions=actions.astype(np.float32),
        rewards=rewards,
        terminated=terminated,
        truncated=np.zeros(T, dtype=bool),
        gripper_pose=gripper.astype(np.float32),
        object_poses=object_poses.astype(np.float32),
        contacts=contacts,
        images=images,
    )


def make_tensors(size_mb: float, seed: int, parts: int = 8) -> dict[str, np.ndarray]:
    """float32 tensors totalling ``size_mb`` MB, split over a few named layers."""
    count = max(parts, int(size_mb * MB) // 4)
    rng = np.random.default_rng(seed)
    sizes = [count // parts] * parts
    sizes[-1] += count - sum(sizes)
    return {
        f"actor.layers.{i}.weight": (rng.standard_normal(n, dtype=np.float32) * 0.05)
        for i, n in enumerate(sizes)
    }


def make_blob(size_mb: float, seed: int, version: int) -> WeightsBlob:
    return WeightsBlob.create(version, "equi_rsac", SOURCE, make_tensors(size_mb, seed))


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _client_bus(endpoint: str):
    from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig

    return ZenohBus(ZenohConfig(mode="client", connect=(endpoint,)))


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q))


def _finite(x: float) -> float:
    x = float(x)
    if not math.isfinite(x):
        raise RuntimeError(f"non-finite measurement {x}")
    return x


def _log(msg: str) -> None:
    print(f"[bench transport] {msg}", file=sys.stderr, flush=True)


def _wait_alive(watch, who: tuple[str, str], proc, timeout: float) -> None:
    """Wait for a child's liveliness token, failing fast if the child dies first."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if watch.wait_for(lambda alive: who in alive, timeout=0.5):
            return
        if not proc.is_alive():
            raise RuntimeError(f"{who[0]} process exited (code {proc.exitcode}) before becoming ready")
    raise TimeoutError(f"{who[0]} not alive after {timeout:.0f} s")


def _get(results, proc, timeout: float) -> Any:
    """Next item a child put on ``results``; raises if the child failed, died or timed out."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            item = results.get(timeout=0.5)
        except queue.Empty:
            if not proc.is_alive():
                raise RuntimeError(f"{proc.name} exited (code {proc.exitcode}) without reporting") from None
            if time.monotonic() > deadline:
                raise TimeoutError(f"no report from {proc.name} after {timeout:.0f} s") from None
            continue
        if isinstance(item, tuple) and item and item[0] == "error":
            raise RuntimeError(f"{proc.name} failed: {item[1]}")
        return item


def _stop(proc, commands=None) -> None:
    if proc is None:
        return
    if commands is not None and proc.is_alive():
        with contextlib.suppress(OSError, ValueError):
            commands.put(("stop",))
    proc.join(timeout=5.0)
    if proc.is_alive():
        proc.terminate()
        proc.join(timeout=3.0)
    if proc.is_alive():
        proc.kill()
        proc.join(timeout=3.0)


# --------------------------------------------------------------------------------------------
# Child processes (module-level: they are started with the spawn method)
# --------------------------------------------------------------------------------------------


def subscriber_main(endpoint: str, expected: int, capacity: int, idle_timeout: float, results) -> None:
    """Receive (decode and validate) ``expected`` episodes, then report count, bytes and times."""
    bus = None
    try:
        bus = _client_bus(endpoint)
        sub = bus.subscribe(EPISODES_RAW, capacity=capacity)
        bus.declare_alive(SUB_SERVICE, INSTANCE)  # after the subscription: the parent's go signal
        count = nbytes = 0
        t_first = t_last = None
        ids: set[str] = set()
        while count < expected:
            d = sub.recv(timeout=idle_timeout)
            if d is None:
                break
            t_last = time.monotonic()
            if t_first is None:
                t_first = t_last
            count += 1
            nbytes += d.size
            ids.add(d.message.episode_id)
        results.put(
            (
                "done",
                {
                    "received": count,
                    "bytes": nbytes,
                    "t_first": t_first,
                    "t_last": t_last,
                    "distinct_ids": len(ids),
                    "bad": int(sum(bus.stats.bad.values())),
                },
            )
        )
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises
        results.put(("error", repr(exc)))
    finally:
        if bus is not None:
            bus.close()


def weights_server_main(endpoint: str, commands, results) -> None:
    """Serve WEIGHTS_LATEST from pre-encoded bytes; on command load a blob or announce a new version."""
    bus = None
    try:
        bus = _client_bus(endpoint)
        current: list[tuple[int, bytes]] = [(-1, b"")]

        def handler(params: dict[str, str]) -> bytes | None:
            version, payload = current[0]
            try:
                wanted = int(params.get("min_version", "0"))
            except ValueError:
                return None
            return payload if version >= 0 and version >= wanted else None

        bus.serve(WEIGHTS_LATEST, handler, source=SOURCE)
        bus.declare_alive(SERVER_SERVICE, INSTANCE)
        blob: WeightsBlob | None = None
        version = 0
        while True:
            cmd = commands.get()
            if cmd[0] == "stop":
                break
            version += 1
            if cmd[0] == "load":
                _, size_mb, seed = cmd
                blob = make_blob(size_mb, seed, version)
                payload = blob.encode()
                current[0] = (version, payload)
                results.put(("loaded", version, len(payload)))
            elif cmd[0] == "announce" and blob is not None:
                # same tensors, new version: the digest stays valid; encode before timing starts
                blob = dataclasses.replace(blob, version=version, created_at=time.time())
                payload = blob.encode()
                current[0] = (version, payload)
                ann = blob.announcement(len(payload))
                t0 = time.monotonic()
                bus.publish(WEIGHTS_ANNOUNCE, ann, source=SOURCE)
                results.put(("announced", version, t0))
            else:
                results.put(("error", f"bad command {cmd!r}"))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises
        results.put(("error", repr(exc)))
    finally:
        if bus is not None:
            bus.close()


# --------------------------------------------------------------------------------------------
# Measurements
# --------------------------------------------------------------------------------------------


def bench_codec(cfg: TransportBenchConfig) -> list[dict[str, Any]]:
    rows = []
    episodes = {name: make_episode(cfg, image_dtype) for name, image_dtype in VARIANTS}
    # Warm every variant first: the first multi-MB buffers of a process cost page faults (and
    # glibc raises its mmap threshold only after freeing some), which would penalise variant a.
    for _ in range(3):
        for ep in episodes.values():
            Episode.decode(ep.encode())
    for name, image_dtype in VARIANTS:
        ep = episodes[name]
        enc, dec = [], []
        for _ in range(max(1, cfg.repeats)):
            t0 = time.perf_counter()
            data = ep.encode()
            t1 = time.perf_counter()
            Episode.decode(data)
            t2 = time.perf_counter()
            enc.append(t1 - t0)
            dec.append(t2 - t1)
        e, d = statistics.median(enc), statistics.median(dec)
        size = len(data)
        rows.append(
            {
                "variant": variant_label(cfg, name, image_dtype),
                "encoded_mb": _finite(size / MB),
                "encode_ms": _finite(e * 1e3),
                "decode_ms": _finite(d * 1e3),
                "encode_mb_s": _finite(size / MB / e),
                "decode_mb_s": _finite(size / MB / d),
            }
        )
    return rows


def bench_pubsub(cfg: TransportBenchConfig, ctx, client, endpoint: str) -> list[dict[str, Any]]:
    name, image_dtype = VARIANTS[1]
    label = variant_label(cfg, name, image_dtype)
    pool = [make_episode(cfg, image_dtype, index=i) for i in range(4)]
    payloads = [ep.encode() for ep in pool]
    watch = client.watch_alive(SUB_SERVICE)
    results = ctx.Queue()
    proc = ctx.Process(
        target=subscriber_main,
        args=(endpoint, cfg.episodes, cfg.subscriber_capacity, cfg.timeout_s, results),
        name="bench-transport-subscriber",
        daemon=True,
    )
    try:
        proc.start()
        _wait_alive(watch, (SUB_SERVICE, INSTANCE), proc, cfg.timeout_s)
        sent = sent_bytes = 0
        t0 = time.monotonic()
        for i in range(cfg.episodes):
            msg = pool[i % len(pool)] if cfg.encode_in_loop else payloads[i % len(payloads)]
            sent_bytes += client.publish(EPISODES_RAW, msg, source=SOURCE)
            sent += 1
        t_pub = time.monotonic()
        _, rep = _get(results, proc, cfg.timeout_s + 30.0)
    finally:
        watch.close()
        _stop(proc)
        results.close()
    received = rep["received"]
    elapsed = (rep["t_last"] - t0) if rep["t_last"] is not None else float("nan")
    if received == 0 or not elapsed > 0:
        raise RuntimeError(f"pub/sub: subscriber received {received} of {sent} episodes")
    return [
        {
            "variant": label + (" (encoded in loop)" if cfg.encode_in_loop else ""),
            "episode_mb": _finite(sent_bytes / sent / MB),
            "sent": sent,
            "received": received,
            "all_received": received == sent,
            "rejected": rep["bad"],
            "seconds": _finite(elapsed),
            "episodes_per_s": _finite(received / elapsed),
            "mb_per_s": _finite(rep["bytes"] / MB / elapsed),
            "publish_episodes_per_s": _finite(sent / max(t_pub - t0, 1e-9)),
        }
    ]


def _local_decode_ms(size_mb: float, seed: int, repeats: int) -> float:
    data = make_blob(size_mb, seed, 1).encode()
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        WeightsBlob.decode(data)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def _pull(client, min_version: int, timeout: float) -> WeightsBlob:
    d = client.query(WEIGHTS_LATEST, {"min_version": str(min_version)}, timeout=timeout, source=SOURCE)
    if d is None:
        raise RuntimeError(f"weights pull (min_version={min_version}) got no valid reply")
    if d.message.version < min_version:
        raise RuntimeError(f"weights pull returned version {d.message.version} < {min_version}")
    return d.message


def bench_weights(cfg: TransportBenchConfig, ctx, client, endpoint: str) -> list[dict[str, Any]]:
    rows = []
    # declared before the server exists, so the router knows it before any announcement
    ann_sub = client.subscribe(WEIGHTS_ANNOUNCE, capacity=8, source=SOURCE)
    watch = client.watch_alive(SERVER_SERVICE)
    commands, results = ctx.Queue(), ctx.Queue()
    proc = ctx.Process(
        target=weights_server_main,
        args=(endpoint, commands, results),
        name="bench-transport-weights-server",
        daemon=True,
    )
    try:
        proc.start()
        _wait_alive(watch, (SERVER_SERVICE, INSTANCE), proc, cfg.timeout_s)
        for i, size_mb in enumerate(cfg.blob_sizes_mb):
            seed = cfg.seed * 1000 + i
            commands.put(("load", float(size_mb), seed))
            _, version, nbytes = _get(results, proc, cfg.timeout_s)
            pulls = []
            for k in range(cfg.warmup + cfg.pulls):
                t0 = time.perf_counter()
                _pull(client, version, cfg.timeout_s)
                if k >= cfg.warmup:
                    pulls.append(time.perf_counter() - t0)
            announce = []
            for k in range(cfg.warmup + cfg.pulls):
                commands.put(("announce",))
                d = ann_sub.recv(timeout=cfg.timeout_s)
                if d is None:
                    raise RuntimeError("weights announcement not received")
                v = d.message.version
                _pull(client, v, cfg.timeout_s)
                t1 = time.monotonic()
                _, v_sent, t_ann = _get(results, proc, cfg.timeout_s)
                if v_sent != v:
                    raise RuntimeError(f"announcement for version {v}, server announced {v_sent}")
                if k >= cfg.warmup:
                    announce.append(t1 - t_ann)
            p50 = _pct(pulls, 50)
            rows.append(
                {
                    "blob_mb": float(size_mb),
                    "encoded_mb": _finite(nbytes / MB),
                    "pulls": len(pulls),
                    "pull_p50_ms": _finite(p50 * 1e3),
                    "pull_p99_ms": _finite(_pct(pulls, 99) * 1e3),
                    "pull_mb_s_at_p50": _finite(nbytes / MB / p50),
                    "announce_to_pulled_p50_ms": _finite(_pct(announce, 50) * 1e3),
                    "announce_to_pulled_p99_ms": _finite(_pct(announce, 99) * 1e3),
                    "local_decode_ms": _finite(_local_decode_ms(size_mb, seed, min(cfg.repeats, 10))),
                }
            )
    finally:
        _stop(proc, commands)
        watch.close()
        ann_sub.close()
        commands.close()
        results.close()
    return rows


def _meta(cfg: TransportBenchConfig, elapsed: float) -> dict[str, Any]:
    try:
        zenoh_version = importlib.metadata.version("eclipse-zenoh")
    except importlib.metadata.PackageNotFoundError:
        zenoh_version = "unknown"
    return {
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(cfg).items()},
        "units": "MB = 1e6 bytes; ms per message; medians for the codec",
        "topology": "router in the bench process; publisher/querier (client) in the bench process; "
        "subscriber and weights server (clients) in spawned processes; tcp 127.0.0.1",
        "clock": "time.monotonic across processes (CLOCK_MONOTONIC)",
        "python": platform.python_version(),
        "zenoh": zenoh_version,
        "numpy": np.__version__,
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
        "elapsed_s": round(elapsed, 2),
    }


def run(cfg: TransportBenchConfig) -> dict:
    """Run all three measurements, print them (table or one JSON object) and return the result."""
    from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig

    started = time.monotonic()
    sections: dict[str, list[dict[str, Any]]] = {}
    _log("episode codec ...")
    sections["episode_codec"] = bench_codec(cfg)

    ctx = mp.get_context("spawn")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = client = None
    try:
        router = ZenohBus(ZenohConfig(mode="router", listen=(endpoint,), connect=()))
        client = _client_bus(endpoint)
        _log(f"episode pub/sub via router {endpoint} ...")
        sections["episode_pubsub"] = bench_pubsub(cfg, ctx, client, endpoint)
        _log("weights pull ...")
        sections["weights_pull"] = bench_weights(cfg, ctx, client, endpoint)
    finally:
        if client is not None:
            client.close()
        if router is not None:
            router.close()
    meta = _meta(cfg, time.monotonic() - started)
    return emit("transport", sections, measured={}, as_json=cfg.json, meta=meta)


if __name__ == "__main__":
    import tyro

    run(tyro.cli(TransportBenchConfig))
