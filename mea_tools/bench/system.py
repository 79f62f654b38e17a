"""`mea bench system`: what the whole stack costs and delivers on this machine.

The raw simulator's steps/s beside the full `mea run` stack's rates and weights latency, so the
pipeline's overhead shows.

Design notes: docs/architecture-notes.md, mea_tools/bench/system.py."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mea_tools.bench.harness import free_port, percentile
from mea_tools.bench.report import emit
from proto.topics import STATUS, WEIGHTS_ANNOUNCE
from services.actor.config import MAX_ENVS
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig


@dataclass(frozen=True)
class SystemBenchConfig:
    """Raw simulator vs full-stack env steps/s, augmenter and learner rates, weights latency."""

    task: str = "block_pull"
    actors: int = 1
    """Actor processes (raw and full stack alike)."""
    envs_per_actor: int = 1
    """Envs each actor process steps (raw: in turn; full stack: `mea run --envs-per-actor`)."""
    seconds: float = 120.0
    """Measurement window of each part."""
    warmup_seconds: float = 60.0
    """Full stack: time before the window (start-up, demos, first weights)."""
    run_dir: Path = Path("runs/bench-system")
    json: bool = False
    """Print exactly one JSON object instead of tables."""

    def __post_init__(self) -> None:
        if self.actors < 1 or not 1 <= self.envs_per_actor <= MAX_ENVS:
            raise ValueError(f"--actors must be >= 1 and --envs-per-actor in 1..{MAX_ENVS}")
        if self.seconds <= 0 or self.warmup_seconds < 0:
            raise ValueError("--seconds must be > 0 and --warmup-seconds >= 0")


def _log(msg: str) -> None:
    print(f"[bench system] {msg}", file=sys.stderr, flush=True)


def raw_sim_main(task: str, index: int, envs: int, seconds: float, results) -> None:
    try:
        from services.tasks import EnvSettings, make_env  # deferred: pybullet; only children simulate

        sims = [make_env(task, EnvSettings()) for _ in range(envs)]
        rng = np.random.default_rng(index)
        for j, env in enumerate(sims):
            env.reset(index * 1000 + j)
        steps, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < seconds:
            for env in sims:  # in turn, as an actor with several envs steps them
                _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 5))
                steps += 1
                if terminated or truncated:
                    env.reset(index * 1_000_000 + steps)
        results.put(("done", steps, time.monotonic() - t0))
        for env in sims:
            env.close()
    except BaseException as exc:  # noqa: BLE001 - reported to the parent
        results.put(("error", repr(exc)))


def bench_raw(cfg: SystemBenchConfig) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    results = ctx.Queue()
    args = [(cfg.task, i, cfg.envs_per_actor, cfg.seconds, results) for i in range(cfg.actors)]
    procs = [ctx.Process(target=raw_sim_main, args=a, daemon=True) for a in args]
    for p in procs:
        p.start()
    rates = []
    for _ in procs:
        item = results.get(timeout=cfg.seconds + 120)
        if item[0] == "error":
            raise RuntimeError(f"raw simulator process failed: {item[1]}")
        rates.append(item[1] / item[2])
    for p in procs:
        p.join(10)
    return {"actors": cfg.actors, "envs per actor": cfg.envs_per_actor, "env steps/s (total)": sum(rates),
            "per process": sum(rates) / len(rates)}  # fmt: skip


def connect_to_run(port: int, proc: subprocess.Popen, timeout: float = 60.0):
    """A Zenoh client of the router inside a `mea run` subprocess, retried until it listens
    (bounded; fails at once if the launcher exits)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return ZenohBus(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
        except Exception:  # noqa: BLE001 - the launcher's router is not up yet
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("mea run did not come up") from None
            time.sleep(0.5)


def stop_run(proc: subprocess.Popen, grace: float) -> None:
    """Stop a `mea run` subprocess started in its own session: SIGTERM to its group (the launcher
    stops its services), SIGKILL to the group if it is still there after ``grace`` seconds."""
    if proc.poll() is not None:
        return
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(grace)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


class Collector:
    """First and last heartbeat of each instance inside the window; weights creation and loads."""

    def __init__(self, start: float) -> None:
        self.start = start
        self.first: dict[tuple[str, str], tuple[float, dict]] = {}
        self.last: dict[tuple[str, str], tuple[float, dict]] = {}
        self.created: dict[int, float] = {}
        self.loads: dict[tuple[str, str], dict[int, float]] = defaultdict(dict)

    def beat(self, hb, now: float) -> None:
        who = (hb.service, hb.instance_id)
        c = hb.counters
        if "weights_version" in c and "weights_loaded_at" in c:
            self.loads[who].setdefault(int(c["weights_version"]), c["weights_loaded_at"])
        if now >= self.start:
            self.first.setdefault(who, (hb.created_at, dict(c)))
            self.last[who] = (hb.created_at, dict(c))

    def rate(self, service: str, key: str) -> float | None:
        total, found = 0.0, False
        for who, (t1, c1) in self.last.items():
            if who[0] == service and key in c1 and self.first[who][0] < t1:
                t0, c0 = self.first[who]
                total += (c1[key] - c0.get(key, 0.0)) / (t1 - t0)
                found = True
        return total if found else None

    def latencies(self) -> list[float]:
        return [t - self.created[v] for per in self.loads.values() for v, t in per.items()
                if v in self.created and v > 0]  # fmt: skip


def bench_stack(cfg: SystemBenchConfig) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    port = free_port()
    cmd = [sys.executable, "-m", "services.cli", "run", "--task", cfg.task, "--actors", str(cfg.actors),
           "--envs-per-actor", str(cfg.envs_per_actor), "--demos", "2", "--env-steps", "0", "--no-follow-gate",
           "--listen", f"tcp/127.0.0.1:{port}",
           "--metrics-port", "0", "--run-dir", str(cfg.run_dir / f"stack-{int(time.time())}"),
           "--duration-seconds", str(cfg.warmup_seconds + cfg.seconds + 5), "--log-format", "json"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    bus = None
    col = Collector(time.monotonic() + cfg.warmup_seconds)
    try:
        bus = connect_to_run(port, proc)
        beats = bus.subscribe(STATUS, capacity=8192)
        announces = bus.subscribe(WEIGHTS_ANNOUNCE, capacity=8192)
        _log(f"full stack: warm-up {cfg.warmup_seconds:.0f} s, then {cfg.seconds:.0f} s measured ...")
        while time.monotonic() < col.start + cfg.seconds:
            if proc.poll() is not None:
                raise RuntimeError(f"mea run exited early ({proc.returncode})")
            for d in announces.drain():
                col.created[d.message.version] = d.message.created_at
            now = time.monotonic()
            for d in beats.drain():
                col.beat(d.message, now)
            time.sleep(0.2)
    finally:
        if bus is not None:
            bus.close()
        stop_run(proc, 60.0)
    learner = [w for w in col.last if w[0] == "learner"]
    wait_fraction = None
    if learner:
        (t0, c0), (t1, c1) = col.first[learner[0]], col.last[learner[0]]
        if t1 > t0:
            wait_fraction = (c1.get("wait_seconds", 0.0) - c0.get("wait_seconds", 0.0)) / (t1 - t0)
    latencies = col.latencies()
    row = {
        "actors": cfg.actors, "envs per actor": cfg.envs_per_actor, "env steps/s": col.rate("actor", "env_steps"),
        "augmented transitions/s": col.rate("augmenter", "transitions_out"),
        "learner updates/s": col.rate("learner", "updates"), "learner waiting (fraction of wall time)": wait_fraction,
    }  # fmt: skip
    lat = [{
        "consumers": len(col.loads), "versions loaded": sum(len(v) for v in col.loads.values()),
        "publish -> loaded p50 ms": 1e3 * percentile(latencies, 50) if latencies else None,
        "p99 ms": 1e3 * percentile(latencies, 99) if latencies else None,
    }]  # fmt: skip
    return row, lat


POLICY_PRESETS = ("cpu-small", "paper")
"""Actor networks timed by ``bench_policy_step``."""


def bench_policy_step(cfg: SystemBenchConfig, repeats: int = 30) -> list[dict[str, Any]]:
    """An actor's policy step alone (one torch thread, as in a spawned actor): one env per forward
    pass against the batch of ``envs_per_actor`` envs an actor with that many steps at once."""
    import torch  # deferred: the raw simulator's children need none

    from services.algorithms.networks import PRESETS, build_actor

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    rows = []
    try:
        for preset in POLICY_PRESETS:
            torch.manual_seed(0)
            actor = build_actor(PRESETS[preset]).eval()
            ms = {}
            for k in sorted({1, cfg.envs_per_actor}):
                x, prev = torch.rand(k, 2, 84, 84), torch.zeros(k, 5)
                with torch.no_grad():
                    actor.step(x, prev)  # warm-up
                    times = []
                    for _ in range(repeats):
                        t0 = time.perf_counter()
                        actor.step(x, prev)
                        times.append(time.perf_counter() - t0)
                ms[k] = 1e3 * statistics.median(times)
            k = cfg.envs_per_actor
            rows.append({"actor network": preset, "ms per step, 1 env": ms[1], "envs per actor": k,
                         f"ms per batch of {k}": ms[k], "ms per env": ms[k] / k,
                         "per-env cost ratio": ms[1] / (ms[k] / k)})  # fmt: skip
    finally:
        torch.set_num_threads(threads)
    return rows


def run(cfg: SystemBenchConfig) -> dict:
    started = time.monotonic()
    _log(f"raw simulator: {cfg.actors} process(es), {cfg.seconds:.0f} s ...")
    raw = bench_raw(cfg)
    stack, latency = bench_stack(cfg)
    if stack["env steps/s"]:
        stack["overhead vs raw %"] = 100.0 * (1.0 - stack["env steps/s"] / raw["env steps/s (total)"])
    sections = {"raw simulator": [raw], "full stack (mea run)": [stack], "weights publish -> loaded": latency,
                "policy step per env (batched over an actor's envs)": bench_policy_step(cfg)}  # fmt: skip
    meta = {"task": cfg.task, "seconds": cfg.seconds, "warmup_seconds": cfg.warmup_seconds,
            "total_minutes": round((time.monotonic() - started) / 60, 1),
            "stack": "mea variant, cpu-small learner (1 thread), evaluator, actors ignoring the replay gate"}  # fmt: skip
    return emit(
        "system", sections, measured={"env_steps_per_second": raw["per process"]}, as_json=cfg.json, meta=meta
    )
