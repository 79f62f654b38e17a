"""Transport benchmark: episode codec speed, Zenoh pub/sub throughput and weight-pull latency.

Three measurements on this machine over 127.0.0.1, through the deployed topology (producer ->
router -> consumer): what the bus costs the services.

Design notes: docs/architecture-notes.md, mea_tools/bench/transport.py."""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import statistics
import sys
import time
from dataclasses import dataclass
from typing import Any

import tyro

from mea_tools.bench.harness import (
    client_bus,
    finite,
    free_port,
    host_meta,
    next_result,
    percentile,
    stop_child,
    wait_alive,
)
from mea_tools.bench.report import emit
from mea_tools.bench.transport_data import MB, SOURCE, make_blob, make_episode
from mea_tools.bench.transport_peers import (
    INSTANCE,
    SERVER_SERVICE,
    SUB_SERVICE,
    subscriber_main,
    weights_server_main,
)
from proto.episode import Episode
from proto.topics import EPISODES_RAW, WEIGHTS_ANNOUNCE, WEIGHTS_LATEST
from proto.weights import WeightsBlob
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig

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


def _log(msg: str) -> None:
    print(f"[bench transport] {msg}", file=sys.stderr, flush=True)


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
                "encoded_mb": finite(size / MB),
                "encode_ms": finite(e * 1e3),
                "decode_ms": finite(d * 1e3),
                "encode_mb_s": finite(size / MB / e),
                "decode_mb_s": finite(size / MB / d),
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
        wait_alive(watch, (SUB_SERVICE, INSTANCE), proc, cfg.timeout_s)
        sent = sent_bytes = 0
        t0 = time.monotonic()
        for i in range(cfg.episodes):
            msg = pool[i % len(pool)] if cfg.encode_in_loop else payloads[i % len(payloads)]
            sent_bytes += client.publish(EPISODES_RAW, msg, source=SOURCE)
            sent += 1
        t_pub = time.monotonic()
        _, rep = next_result(results, proc, cfg.timeout_s + 30.0)
    finally:
        watch.close()
        stop_child(proc)
        results.close()
    received = rep["received"]
    elapsed = (rep["t_last"] - t0) if rep["t_last"] is not None else float("nan")
    if received == 0 or not elapsed > 0:
        raise RuntimeError(f"pub/sub: subscriber received {received} of {sent} episodes")
    return [
        {
            "variant": label + (" (encoded in loop)" if cfg.encode_in_loop else ""),
            "episode_mb": finite(sent_bytes / sent / MB),
            "sent": sent,
            "received": received,
            "all_received": received == sent,
            "rejected": rep["bad"],
            "seconds": finite(elapsed),
            "episodes_per_s": finite(received / elapsed),
            "mb_per_s": finite(rep["bytes"] / MB / elapsed),
            "publish_episodes_per_s": finite(sent / max(t_pub - t0, 1e-9)),
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
        wait_alive(watch, (SERVER_SERVICE, INSTANCE), proc, cfg.timeout_s)
        for i, size_mb in enumerate(cfg.blob_sizes_mb):
            seed = cfg.seed * 1000 + i
            commands.put(("load", float(size_mb), seed))
            _, version, nbytes = next_result(results, proc, cfg.timeout_s)
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
                _, v_sent, t_ann = next_result(results, proc, cfg.timeout_s)
                if v_sent != v:
                    raise RuntimeError(f"announcement for version {v}, server announced {v_sent}")
                if k >= cfg.warmup:
                    announce.append(t1 - t_ann)
            p50 = percentile(pulls, 50)
            rows.append(
                {
                    "blob_mb": float(size_mb),
                    "encoded_mb": finite(nbytes / MB),
                    "pulls": len(pulls),
                    "pull_p50_ms": finite(p50 * 1e3),
                    "pull_p99_ms": finite(percentile(pulls, 99) * 1e3),
                    "pull_mb_s_at_p50": finite(nbytes / MB / p50),
                    "announce_to_pulled_p50_ms": finite(percentile(announce, 50) * 1e3),
                    "announce_to_pulled_p99_ms": finite(percentile(announce, 99) * 1e3),
                    "local_decode_ms": finite(_local_decode_ms(size_mb, seed, min(cfg.repeats, 10))),
                }
            )
    finally:
        stop_child(proc, commands)
        watch.close()
        ann_sub.close()
        commands.close()
        results.close()
    return rows


def _meta(cfg: TransportBenchConfig, elapsed: float) -> dict[str, Any]:
    return {
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(cfg).items()},
        "units": "MB = 1e6 bytes; ms per message; medians for the codec",
        "topology": "router in the bench process; publisher/querier (client) in the bench process; "
        "subscriber and weights server (clients) in spawned processes; tcp 127.0.0.1",
        "clock": "time.monotonic across processes (CLOCK_MONOTONIC)",
        **host_meta(),
        "elapsed_s": round(elapsed, 2),
    }


def run(cfg: TransportBenchConfig) -> dict:
    """Run all three measurements, print them (table or one JSON object) and return the result."""
    started = time.monotonic()
    sections: dict[str, list[dict[str, Any]]] = {}
    _log("episode codec ...")
    sections["episode_codec"] = bench_codec(cfg)

    ctx = mp.get_context("spawn")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = client = None
    try:
        router = ZenohBus(ZenohConfig(mode="router", listen=(endpoint,), connect=()))
        client = client_bus(endpoint)
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
    run(tyro.cli(TransportBenchConfig))
