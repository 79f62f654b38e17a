"""`mea bench serve`: act() latency of the real-robot inference server, and weights swap -> first action.

Design notes: docs/architecture-notes.md, mea_tools/bench/serve.py."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import multiprocessing as mp
import os
import platform
import sys
import tempfile
import time
import uuid
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import tyro

from mea_tools.bench.harness import finite, free_port, host_meta, percentile, wait_alive
from mea_tools.bench.report import emit
from proto.inference import ActRequest, ResetRequest
from proto.topics import SERVE_ACT, SERVE_RESET
from proto.weights import WeightsBlob
from services.algorithms.networks import PRESETS as NET_PRESETS
from services.algorithms.networks import build_actor
from services.algorithms.policy import PolicySpec, actor_tensors
from services.common import run_key, weights_file
from services.common.bus.base import Credentials
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from services.common.config import parse
from services.common.runtime import die_with_parent
from services.common.weights import WeightsServer
from services.inference.adapter import SimRobot, observation_of, sim_limits
from services.inference.config import PRESETS as SERVE_PRESETS
from services.inference.config import ServeConfig
from services.inference.core.sessions import InferenceCore, ServeSettings
from services.inference.main import WEIGHTS_POLL_SECONDS
from services.inference.main import main as serve_main

TASK = "block_pull"
SESSION = "bench-robot"
LEARNER = "learner-bench"
RUN_ID = "bench-serve"
TARGET_MS = 10.0
"""The cpu-small act round trip p99 must stay under this."""

SECTION_ACT = (
    "act round trip (robot -> mea serve over Zenoh, sealed; server time includes the voxel projection)"
)

SECTION_LOCAL = "in process (InferenceCore.act, no transport), same observations"
SECTION_SWAP = "weights swap (mea serve following the learner)"
SECTION_SWAPS = "weights swap, each version"
SECTION_TARGET = "target"
SECTION_MACHINE = "machine"


@dataclass(frozen=True)
class ServeBenchConfig:
    """Inference server benchmark: act() round trip and server time per actor preset, weights swap -> first action."""

    requests: int = 500
    """Timed act requests per preset (sent one at a time)."""
    warmup: int = 20
    """Untimed act requests before them."""
    presets: str = "cpu-small,paper"
    """Actor presets to serve, comma-separated (services.algorithms.networks PRESETS)."""
    episode_steps: int = 50
    """Reset the session's episode every this many act requests."""
    observations: int = 300
    """Real Block Pull observations collected once (random actions) and cycled through."""
    swaps: int = 10
    """Weights versions timed from publish to first action (0: skip the swap measurement)."""
    swap_preset: str = "cpu-small"
    """Actor preset of the swap measurement."""
    torch_threads: int = 1
    """torch threads of the server (`mea serve --torch-threads`) and of the in-process measurement."""
    timeout_s: float = 60.0
    """Give up waiting for a server, a reply or a swap after this many seconds."""
    seed: int = 0
    """Seed of the observations' random actions and of the weights."""
    json: bool = False
    """Print exactly one JSON object on stdout instead of tables."""

    def __post_init__(self) -> None:
        if self.requests < 1 or self.warmup < 0 or self.episode_steps < 1 or self.observations < 1:
            raise ValueError("requests, episode_steps and observations must be >= 1, warmup >= 0")
        if self.swaps < 0 or self.torch_threads < 1 or not self.timeout_s > 0:
            raise ValueError("swaps must be >= 0, torch_threads >= 1 and timeout_s > 0")
        for p in (*self.preset_list, self.swap_preset):
            if p not in NET_PRESETS:
                raise ValueError(f"unknown preset {p!r}; choose from {sorted(NET_PRESETS)}")
        if not self.preset_list and self.swaps == 0:
            raise ValueError("nothing to measure: no presets and no swaps")

    @property
    def preset_list(self) -> tuple[str, ...]:
        return tuple(p.strip() for p in self.presets.split(",") if p.strip())


def _log(msg: str) -> None:
    print(f"[bench serve] {msg}", file=sys.stderr, flush=True)


def _ms(values: list[float], q: float) -> float:
    return finite(percentile(values, q) * 1e3)


# --------------------------------------------------------------------------------------------
# Inputs: observations, weights, the server's files
# --------------------------------------------------------------------------------------------


def collect_observations(n: int, seed: int):
    """``n`` real Block Pull observations (voxel: point clouds) under random actions, and the sim's limits."""
    robot = SimRobot(TASK)
    try:
        env = robot.env
        rng = np.random.default_rng([seed, 5])
        episode = 0
        obs = env.reset(seed)
        out = []
        while len(out) < n:
            out.append(observation_of(obs, "voxel", time.time()))
            obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 5).astype(np.float32))
            if terminated or truncated:
                episode += 1
                obs = env.reset(seed + episode)
        return out, sim_limits(env)
    finally:
        robot.close()


def make_blob(preset: str, version: int, seed: int):
    torch.manual_seed(seed)
    spec = PolicySpec(NET_PRESETS[preset])
    actor = build_actor(spec.net)
    params = sum(p.numel() for p in actor.parameters())
    return WeightsBlob.create(version, "equi_rsac", RUN_ID, actor_tensors(actor), spec.to_json()), params


def serve_argv(endpoint: str, namespace: str, instance: str, key_file: Path, limits_file: Path,
               weights: str, torch_threads: int) -> list[str]:  # fmt: skip
    """`mea serve` flags: a peer listening on ``endpoint`` (and connecting nowhere: connect == listen)."""
    return ["--weights", weights, "--limits-file", str(limits_file), "--torch-threads", str(torch_threads),
            "--service.instance-id", instance, "--service.metrics-port", "0", "--service.run-key-file",
            str(key_file), "--service.log-level", "WARNING", "--service.log-format", "text",
            "--service.zenoh.mode", "peer", "--service.zenoh.listen", endpoint, "--service.zenoh.connect",
            endpoint, "--service.zenoh.namespace", namespace]  # fmt: skip


def serve_child(argv: list[str]) -> None:
    """Spawned: `mea serve ARGV` (its Zenoh session opens here), ended by SIGTERM or the parent's death."""
    die_with_parent()
    raise SystemExit(serve_main(argv))


def stop_server(proc) -> None:
    if proc is None:
        return
    if proc.is_alive():
        proc.terminate()  # SIGTERM: the service's graceful shutdown
        proc.join(timeout=10.0)
    if proc.is_alive():
        proc.kill()
        proc.join(timeout=5.0)


@contextlib.contextmanager
def served(cfg: ServeBenchConfig, files: dict[str, Path], instance: str, weights: str, services=("robot",)):
    """A `mea serve` child and, opened after it, one bus per ``services`` entry connected to it
    (authenticated as that service); yields the buses once the server's liveliness token is seen."""
    ctx = mp.get_context("spawn")
    key = run_key.load(files["key"])
    last: Exception | None = None
    for _attempt in range(3):  # the port was free a moment ago; another process may have taken it since
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        namespace = f"bench-serve-{uuid.uuid4().hex[:10]}"
        argv = serve_argv(
            endpoint, namespace, instance, files["key"], files["limits"], weights, cfg.torch_threads
        )
        parse(ServeConfig, SERVE_PRESETS, argv, "mea serve", "")  # a bad flag fails here, not in the child
        proc = ctx.Process(target=serve_child, args=(argv,), name=f"mea-serve-{instance}", daemon=True)
        buses: list[Any] = []
        try:
            proc.start()
            for service in services:
                bus = ZenohBus(ZenohConfig(mode="peer", connect=(endpoint,), namespace=namespace))
                buses.append(bus)
                bus.authenticate(Credentials(key, service, LEARNER if service == "learner" else SESSION))
            watch = buses[0].watch_alive("inference")
            try:
                wait_alive(watch, ("inference", instance), proc, cfg.timeout_s)
            except RuntimeError as exc:  # died before it was up (port taken?): try another port
                last = exc
                continue
            finally:
                watch.close()
            yield buses
            return
        finally:
            for bus in reversed(buses):
                bus.close()
            stop_server(proc)
    raise RuntimeError(f"mea serve did not come up in 3 tries (its stderr is above): {last}")


# --------------------------------------------------------------------------------------------
# Requests
# --------------------------------------------------------------------------------------------


class Robot:
    """The bench's robot session: reset and act over the bus, checking every reply."""

    def __init__(self, bus, server: str, timeout: float) -> None:
        self.bus, self.server, self.timeout = bus, server, timeout
        self.episode = 0
        self.step = 0
        self.prev: np.ndarray | None = None

    def reset(self, deadline: float | None = None):
        """Start an episode; retries (until ``deadline``) while the server has no weights or no queryable yet."""
        deadline = deadline or time.monotonic() + self.timeout
        while True:
            req = ResetRequest(session=SESSION, task=TASK, created_at=time.time())
            d = self.bus.call(SERVE_RESET, req, timeout=self.timeout, source=self.server)
            if d is not None and d.message.accepted:
                self.episode, self.step, self.prev = d.message.episode, 0, None
                return d.message
            if time.monotonic() > deadline:
                why = "no reply" if d is None else d.message.reason
                raise TimeoutError(f"{self.server} would not start an episode: {why}")
            time.sleep(0.02)

    def request(self, obs):
        return ActRequest(session=SESSION, episode=self.episode, step=self.step, stamp=time.time(),
                          state=obs.state, executed=self.prev if self.step > 0 else None,
                          points=obs.points, point_counts=obs.point_counts)  # fmt: skip

    def act(self, obs):
        """(reply, round trip s) for one observation, stamped now."""
        req = self.request(obs)
        t0 = time.perf_counter()
        d = self.bus.call(SERVE_ACT, req, timeout=self.timeout, source=self.server)
        rtt = time.perf_counter() - t0
        if d is None:
            raise RuntimeError(f"no ActReply from {self.server} (episode {self.episode}, step {self.step})")
        reply = d.message
        if reply.episode != self.episode or reply.step != self.step:
            raise RuntimeError(
                f"reply for episode {reply.episode} step {reply.step}, sent {self.episode}/{self.step}"
            )
        self.step += 1
        self.prev = reply.action
        return reply, rtt


def bench_preset(cfg: ServeBenchConfig, preset: str, observations, files: dict[str, Path]) -> dict[str, Any]:
    """Round trips and server times of one preset's pinned server."""
    instance = f"serve-bench-{preset}"
    rtts, compute, versions, holds, clamps = [], [], Counter(), Counter(), Counter()
    with served(cfg, files, instance, str(files[f"weights:{preset}"])) as (bus,):
        robot = Robot(bus, instance, cfg.timeout_s)
        request_bytes = len(robot.request(observations[0]).encode())
        for i in range(cfg.warmup + cfg.requests):
            if i % cfg.episode_steps == 0:
                robot.reset()
            reply, rtt = robot.act(observations[i % len(observations)])
            if i < cfg.warmup:
                continue
            rtts.append(rtt)
            compute.append(reply.compute_seconds)
            versions[reply.policy_version] += 1
            (holds if reply.held else clamps).update(reply.reasons)
    return {
        "preset": preset, "requests": len(rtts), "request bytes": request_bytes,
        "round trip p50 ms": _ms(rtts, 50), "round trip p99 ms": _ms(rtts, 99),
        "round trip max ms": finite(max(rtts) * 1e3),
        "server p50 ms": _ms(compute, 50), "server p99 ms": _ms(compute, 99),
        "transport p50 ms": finite((percentile(rtts, 50) - percentile(compute, 50)) * 1e3),
        "holds": sum(holds.values()), "clamps": sum(clamps.values()),
        "hold reasons": dict(holds), "versions": {str(k): v for k, v in sorted(versions.items())},
    }  # fmt: skip


def bench_local(cfg: ServeBenchConfig, preset: str, blob, limits, observations) -> dict[str, Any]:
    """The same requests through ``InferenceCore.act`` in this process, and split into projection and policy."""
    previous = torch.get_num_threads()
    torch.set_num_threads(cfg.torch_threads)
    try:
        core = InferenceCore(ServeSettings(), lambda _session: limits)
        loaded = core.offer(blob)
        robot = Robot(None, "", cfg.timeout_s)
        acts, project, policy = [], [], []
        runtime = loaded.runtime.fresh(seed=1)
        for i in range(cfg.warmup + cfg.requests):
            obs = observations[i % len(observations)]
            if i % cfg.episode_steps == 0:
                r = core.reset(
                    ResetRequest(session=SESSION, task=TASK, created_at=time.time()), time.monotonic()
                )
                robot.episode, robot.step, robot.prev = r.episode, 0, None
                runtime.reset()
            req = robot.request(obs)
            t0 = time.perf_counter()
            reply = core.act(req, time.monotonic(), time.time())
            t1 = time.perf_counter()
            if reply.held:
                raise RuntimeError(f"in-process act held: {reply.reasons}")
            image = InferenceCore._policy_input(req, loaded)
            t2 = time.perf_counter()
            if req.executed is not None:
                runtime.executed(req.executed)
            runtime.act(image)
            t3 = time.perf_counter()
            robot.step, robot.prev = robot.step + 1, reply.action
            if i >= cfg.warmup:
                acts.append(t1 - t0)
                project.append(t2 - t1)
                policy.append(t3 - t2)
    finally:
        torch.set_num_threads(previous)
    return {
        "preset": preset, "requests": len(acts), "act p50 ms": _ms(acts, 50), "act p99 ms": _ms(acts, 99),
        "projection p50 ms": _ms(project, 50), "projection p99 ms": _ms(project, 99),
        "policy p50 ms": _ms(policy, 50), "policy p99 ms": _ms(policy, 99),
    }  # fmt: skip


def bench_swap(cfg: ServeBenchConfig, observations, files: dict[str, Path]) -> list[dict[str, Any]]:
    """Per version: publish() -> the first ActReply carrying it, the client resetting before every act."""
    instance = "serve-bench-follow"
    blobs = [make_blob(cfg.swap_preset, v, cfg.seed + v)[0] for v in range(1, cfg.swaps + 2)]
    rows = []
    with served(cfg, files, instance, "", services=("robot", "learner")) as (bus, learner_bus):
        learner = WeightsServer(learner_bus, LEARNER)
        try:
            watch = learner_bus.watch_alive("inference")  # the announcement must find the server's subscriber
            try:
                if not watch.wait_for(lambda alive: ("inference", instance) in alive, cfg.timeout_s):
                    raise TimeoutError("the learner's bus does not see the server")
            finally:
                watch.close()
            robot = Robot(bus, instance, cfg.timeout_s)
            learner.publish(blobs[0])
            reply = robot.reset(time.monotonic() + cfg.timeout_s)
            if reply.policy_version != blobs[0].version:
                raise RuntimeError(f"server serves v{reply.policy_version}, published v{blobs[0].version}")
            for i in range(cfg.warmup):
                if i:
                    robot.reset()
                robot.act(observations[i % len(observations)])
            for blob in blobs[1:]:
                seen: Counter = Counter()
                t0 = time.perf_counter()
                learner.publish(blob)
                deadline = time.monotonic() + cfg.timeout_s
                k = 0
                while True:
                    robot.reset()
                    reply, _ = robot.act(observations[k % len(observations)])
                    k += 1
                    seen[reply.policy_version] += 1
                    if reply.policy_version == blob.version:
                        break
                    if time.monotonic() > deadline:
                        raise TimeoutError(f"v{blob.version} not served {cfg.timeout_s:.0f} s after publish")
                ms = (time.perf_counter() - t0) * 1e3
                rows.append({"version": blob.version, "publish -> first action ms": finite(ms),
                             "reset+act loops": k, "replies by version": {str(v): n for v, n in sorted(seen.items())}})  # fmt: skip
        finally:
            learner.close()
    return rows


# --------------------------------------------------------------------------------------------
# Run
# --------------------------------------------------------------------------------------------


def write_files(cfg: ServeBenchConfig, directory: Path, limits, presets: tuple[str, ...]):
    """The run key, the limits file and one sealed weights file per preset; and the blobs and sizes."""
    files = {"key": directory / "run.key", "limits": directory / "limits.json"}
    key = run_key.create(files["key"])
    files["limits"].write_text(json.dumps({"default": dataclasses.asdict(limits)}))
    blobs, params = {}, {}
    for preset in presets:
        blob, params[preset] = make_blob(preset, 1, cfg.seed)
        blobs[preset] = blob
        files[f"weights:{preset}"] = weights_file.write(directory / preset, blob, key, instance=LEARNER)
    return files, blobs, params


def machine_row(cfg: ServeBenchConfig) -> dict[str, Any]:
    meta = host_meta()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    return {"cores": meta["cpus"], "server torch threads": cfg.torch_threads,
            "bench torch threads (default)": torch.get_num_threads(), "load avg 1 min": load,
            "python": meta["python"], "zenoh": meta["zenoh"], "torch": torch.__version__,
            "cpu": platform.processor() or meta["machine"]}  # fmt: skip


def run(cfg: ServeBenchConfig) -> dict:
    started = time.monotonic()
    presets = cfg.preset_list
    _log(f"collecting {cfg.observations} {TASK} observations")
    observations, limits = collect_observations(cfg.observations, cfg.seed)
    act_rows, local_rows, swap_rows = [], [], []
    with tempfile.TemporaryDirectory(prefix="mea-bench-serve-") as tmp:
        files, blobs, params = write_files(cfg, Path(tmp), limits, presets)
        for preset in presets:
            _log(f"{preset}: {cfg.warmup} + {cfg.requests} act requests to mea serve")
            row = bench_preset(cfg, preset, observations, files)
            act_rows.append({"preset": preset, "actor params": params[preset], **row})
            _log(
                f"{preset}: round trip p50 {row['round trip p50 ms']:.2f} ms, p99 {row['round trip p99 ms']:.2f} ms"
            )
            local_rows.append(bench_local(cfg, preset, blobs[preset], limits, observations))
        if cfg.swaps:
            _log(f"swap: {cfg.swaps} versions of {cfg.swap_preset} through a following server")
            swap_rows = bench_swap(cfg, observations, files)
    swap_ms = [r["publish -> first action ms"] for r in swap_rows]
    summary = []
    if swap_rows:
        summary = [{"preset": cfg.swap_preset, "swaps": len(swap_rows),
                    "publish -> first action p50 ms": finite(float(np.percentile(swap_ms, 50))),
                    "max ms": finite(max(swap_ms)), "server weights poll period ms": WEIGHTS_POLL_SECONDS * 1e3,
                    "note": "client resets before every act: a new version is pinned at episode start"}]  # fmt: skip
    small = next((r for r in act_rows if r["preset"] == "cpu-small"), None)
    machine = machine_row(cfg)
    target = [{
        "target": f"cpu-small act round trip p99 < {TARGET_MS:g} ms",
        "measured ms": None if small is None else small["round trip p99 ms"],
        "server p99 ms": None if small is None else small["server p99 ms"],
        "result": "not measured" if small is None else ("PASS" if small["round trip p99 ms"] < TARGET_MS else "FAIL"),
        "load avg 1 min": machine["load avg 1 min"], "cores": machine["cores"],
    }]  # fmt: skip
    sections = {SECTION_ACT: act_rows, SECTION_LOCAL: local_rows, SECTION_SWAP: summary,
                SECTION_SWAPS: swap_rows, SECTION_TARGET: target, SECTION_MACHINE: [machine]}  # fmt: skip
    meta = {
        "config": dataclasses.asdict(cfg), "task": TASK, "seconds": round(time.monotonic() - started, 1),
        "observations": "real Block Pull point clouds (3 segments x 256 points, random actions); the server "
                        "projects them (voxel policy), so its time includes the projection",
        "topology": "mea serve in a spawned process, Zenoh peer listening on 127.0.0.1 (multicast scouting off); "
                    "this process connects as robot (and as learner for the swap); run key: every message sealed",
        **host_meta(),
    }  # fmt: skip
    return emit("serve", sections, measured={}, as_json=cfg.json, meta=meta)


if __name__ == "__main__":
    run(tyro.cli(ServeBenchConfig))
