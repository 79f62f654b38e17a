"""`mea robot`: drive an arm through `mea serve` over Zenoh (``--sim``: one of the project's tasks).

Each episode resets the arm and the server's session, then sends observations and executes the
server's actions, while a guard thread holds the arm on the robot side's own safety rules.

Design notes: docs/architecture-notes.md, services/inference/robot.py."""

from __future__ import annotations

import dataclasses
import json
import logging
import secrets
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from proto.actions import ACTION_DIM, JAW
from proto.inference import ActRequest, ResetRequest
from proto.seeds import EVAL_SEED_BASE
from proto.topics import ESTOP, SERVE_ACT, SERVE_RESET
from services.common import config
from services.common.bus.base import Bus
from services.common.config import ServiceConfig
from services.common.mcap_io.recorder import McapRecorder
from services.common.metrics import ServiceMetrics
from services.common.runtime import ServiceContext, subscribing_bus_factory
from services.episodes.scores import EpisodeResult, episode_result, summarize
from services.inference.adapter import RobotAdapter, RobotObservation, SimRobot, sim_limits
from services.inference.core.envelope import Limits
from services.inference.core.robot_safety import ROBOT_HOLD_REASONS, RobotSafety
from services.tasks import TASK_CLASSES, EnvSettings
from services.tasks.camera import CameraSettings

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class RobotConfig:
    """Drive a robot through an inference server (`mea serve`); --sim drives one of the project's tasks."""

    sim: bool = False
    """Drive a simulated arm (the only arm this build drives)."""
    task: str = "block_pull"
    """Task the simulated arm performs."""
    robot_id: str = ""
    """Session id at the server; empty: sim-psm or sim-panda by task."""
    server: str = ""
    """Instance id of the inference server; empty: the first one whose liveliness token is seen."""
    episodes: int = 10
    """Episodes to run."""
    seed_base: int = EVAL_SEED_BASE
    """Episode k uses seed seed_base + k (default: the evaluator's held-out seeds)."""
    latency_ms: float = 0.0
    """Added delay of every request (ms)."""
    jitter_ms: float = 0.0
    """Standard deviation of a normal jitter added to it (ms; the delay is clipped at 0)."""
    jitter_seed: int = 0
    action_timeout: float = 1.0
    """A request with no reply within this (s) is a hold."""
    command_timeout: float = 2.0
    """Watchdog: hold when no command was executed for this long (s) during an episode."""
    require_operator: bool = False
    """Hold unless an operator (`mea operator`) holds a liveliness token."""
    wait_for_server: float = 60.0
    """How long to wait for a server (and for it to have weights) before giving up (s)."""
    record: str = ""
    """MCAP file of the session (requests, replies, outcomes); empty: not recorded."""
    out: str = ""
    """JSON summary file; empty: printed only."""
    write_limits: str = ""
    """Write the simulated arm's envelope as a limits file, and exit."""
    points_per_segment: int = 256
    """Points per segment the simulated camera gives (the evaluator's default)."""
    depth_image: bool = False
    """Render the depth image (for `depth` policies)."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""

    def __post_init__(self) -> None:
        if self.task not in TASK_CLASSES:
            raise ValueError(f"task must be one of {sorted(TASK_CLASSES)}, not {self.task!r}")
        if self.episodes < 1 or self.seed_base < 0:
            raise ValueError("episodes must be >= 1 and seed_base >= 0")
        if min(self.latency_ms, self.jitter_ms) < 0 or min(self.action_timeout, self.command_timeout) <= 0:
            raise ValueError("latency_ms and jitter_ms must be >= 0, action_timeout and command_timeout > 0")

    @property
    def session(self) -> str:
        return self.robot_id or ("sim-psm" if self.task == "surgical_grasp_any" else "sim-panda")

    def env_settings(self) -> EnvSettings:
        return EnvSettings(depth_image=self.depth_image,
                           camera=CameraSettings(points_per_segment=self.points_per_segment))  # fmt: skip


def robot_metrics(m: ServiceMetrics) -> dict:
    mx = {
        "round_trip": m.histogram(
            "mea_robot_round_trip_seconds",
            "Request to reply of one act, robot side (s).",
            (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0),
        ),  # fmt: skip
        "holds": m.counter(
            "mea_robot_holds", "Steps held, by reason (robot side or the server's).", ["reason"]
        ),
        "episodes": m.counter("mea_robot_episodes", "Episodes finished, by outcome.", ["outcome"]),
    }
    for r in ROBOT_HOLD_REASONS:
        mx["holds"].labels(r)
    return mx


class RobotLink:
    """The client side of one robot session: requests, the guard thread, the recording."""

    def __init__(self, cfg: RobotConfig, bus: Bus, adapter: RobotAdapter, recorder: McapRecorder | None = None,
                 clock: Callable[[], float] = time.monotonic, metrics: ServiceMetrics | None = None) -> None:  # fmt: skip
        self.cfg, self.bus, self.adapter, self.recorder, self.clock = cfg, bus, adapter, recorder, clock
        self.mx = robot_metrics(metrics) if metrics is not None else None
        self.safety = RobotSafety(cfg.command_timeout, cfg.require_operator)
        self.server = cfg.server
        self.rng = np.random.default_rng([cfg.jitter_seed, 11])
        self.holds: Counter = Counter()
        self.round_trips: list[float] = []
        self.compute: list[float] = []
        self.delays: list[float] = []
        self.versions: Counter = Counter()
        self.results: list[EpisodeResult] = []
        self._estop = bus.subscribe(ESTOP, capacity=16)
        self._servers = bus.watch_alive("inference")
        self._operators = bus.watch_alive("operator")
        self._holding: str | None = None
        self._estops: dict[str, bool] = {}  # operator -> its latest e-stop state
        self._stop = threading.Event()
        self._guard = threading.Thread(target=self._guard_loop, name="robot-guard", daemon=True)
        self._guard.start()

    # the guard -------------------------------------------------------------------------------
    def _update(self) -> None:
        for d in self._estop.drain():
            self._estops[d.message.operator_id] = bool(d.message.engaged)
        self.safety.estop = any(self._estops.values())
        servers = {inst for svc, inst in self._servers.alive() if svc == "inference"}
        self.safety.server_alive = (self.server in servers) if self.server else bool(servers)
        self.safety.operator_alive = any(svc == "operator" for svc, _ in self._operators.alive())

    def hold_reason(self) -> str | None:
        self._update()
        return self.safety.reason(self.clock())

    def _guard_loop(self) -> None:
        while not self._stop.wait(0.01):
            reason = self.hold_reason()
            if reason is not None and reason != self._holding:
                self.adapter.hold(reason)  # at once, not at the next step
                log.warning("robot holds", extra={"reason": reason})
            self._holding = reason

    # server ----------------------------------------------------------------------------------
    def find_server(self, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            servers = sorted(inst for svc, inst in self._servers.alive() if svc == "inference")
            if self.server and self.server in servers:
                return self.server
            if not self.server and servers:
                self.server = servers[0]
                return self.server
            self._servers.wait_for(lambda alive: bool(alive), 0.2)
        raise TimeoutError(f"no inference server {self.server or ''} came up within {timeout:.0f} s")

    def reset(self, timeout: float):
        """Start an episode at the server (waits while it has no weights yet); the ResetReply."""
        deadline = time.monotonic() + timeout
        while True:
            req = ResetRequest(session=self.cfg.session, task=self.cfg.task, created_at=time.time())
            d = self.bus.call(SERVE_RESET, req, timeout=min(5.0, timeout), source=self.server)
            if d is not None and d.message.accepted:
                return d.message
            why = "no reply" if d is None else d.message.reason
            if time.monotonic() >= deadline:
                raise TimeoutError(f"the server would not start an episode: {why}")
            log.info("waiting for the server", extra={"reason": why})
            time.sleep(0.5)

    # one step --------------------------------------------------------------------------------
    def request(self, obs: RobotObservation, episode: int, step: int, executed: np.ndarray | None):
        """The server's reply to one observation, or None (no reply in time)."""
        req = ActRequest(session=self.cfg.session, episode=episode, step=step, stamp=obs.stamp, state=obs.state,
                         executed=executed, points=obs.points, point_counts=obs.point_counts,
                         image=obs.image, nonce=secrets.randbits(63))  # fmt: skip
        delay = max(0.0, self.cfg.latency_ms + self.cfg.jitter_ms * float(self.rng.standard_normal())) / 1000
        if delay > 0:
            time.sleep(delay)
        self.delays.append(delay)
        t0 = time.perf_counter()
        if self.recorder is not None:
            self.recorder.write(req)
        d = self.bus.call(SERVE_ACT, req, timeout=self.cfg.action_timeout, source=self.server)
        rtt = time.perf_counter() - t0
        if d is None:
            return None
        reply = d.message
        if reply.nonce != req.nonce or reply.session != req.session:
            log.warning("a reply that does not answer this request was ignored", extra={"step": step})
            return None
        self.round_trips.append(rtt)
        if self.mx is not None:
            self.mx["round_trip"].observe(rtt)
        self.compute.append(reply.compute_seconds)
        if self.recorder is not None:
            self.recorder.write(reply)
        return reply

    def episode(self, seed: int) -> dict:
        """One episode on ``seed``; its outcome."""
        reply = self.reset(self.cfg.wait_for_server)
        obs = self.adapter.reset(seed, reply.observation)
        rewards, terminated, holds = [], [], Counter()
        executed: np.ndarray | None = None
        jaw = 1.0
        self.safety.last_command = self.clock()
        for step in range(self.adapter.max_steps):
            reason = self.hold_reason()
            answer = None if reason is not None else self.request(obs, reply.episode, step, executed)
            if reason is None and answer is None:
                reason = "no_reply"
            if answer is not None and (answer.episode != reply.episode or answer.step != step):
                answer, reason = None, "bad_reply"
            if answer is None:
                action = np.zeros(ACTION_DIM, np.float32)
                action[JAW] = jaw
                holds[reason] += 1
            else:
                action = answer.action
                self.versions[answer.policy_version] += 1
                for r in answer.reasons if answer.held else ():
                    holds[r] += 1
            out = self.adapter.execute(action)
            self.safety.last_command = self.clock()
            executed, obs, jaw = out.executed, out.observation, float(out.executed[JAW] >= 0) * 2 - 1
            rewards.append(out.reward)
            terminated.append(out.terminated)
            if out.terminated or out.truncated:
                break
        self.safety.last_command = None  # between episodes nothing is commanded
        r = episode_result(rewards, terminated, seed)
        self.holds.update(holds)
        if self.mx is not None:
            self.mx["episodes"].labels("success" if r.success else "failure").inc()
            for reason, n in holds.items():
                self.mx["holds"].labels(reason).inc(n)
        self.results.append(r)
        return {"seed": seed, "success": bool(r.success), "length": r.length, "return": r.ret,
                "policy_version": reply.policy_version, "holds": dict(holds)}  # fmt: skip

    def close(self) -> None:
        self._stop.set()
        self._guard.join(timeout=1.0)
        self._estop.close()
        self._servers.close()
        self._operators.close()


def percentiles(values: Sequence[float]) -> dict[str, float]:
    if not values:
        return {"n": 0}
    a = np.asarray(values) * 1000
    return {"n": len(a), "p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max())}  # fmt: skip


def drive(cfg: RobotConfig, link: RobotLink) -> dict:
    """Run ``cfg.episodes`` episodes; the summary."""
    t0 = time.monotonic()
    server = link.find_server(cfg.wait_for_server)
    episodes = [link.episode(cfg.seed_base + k) for k in range(cfg.episodes)]
    s = summarize(link.results, link.adapter.max_steps)
    return {
        "task": cfg.task, "session": cfg.session, "server": server, "episodes": episodes,
        "success_rate": s.success_rate, "grasp_score": s.grasp_score, "mean_return": s.mean_return,
        "seeds": [e["seed"] for e in episodes], "holds": dict(link.holds),
        "versions": {str(k): v for k, v in sorted(link.versions.items())},
        "round_trip": percentiles(link.round_trips), "server_compute": percentiles(link.compute),
        "injected_delay": percentiles(link.delays), "latency_ms": cfg.latency_ms, "jitter_ms": cfg.jitter_ms,
        "wall_seconds": round(time.monotonic() - t0, 3),
    }  # fmt: skip


def run(cfg: RobotConfig, bus_factory: Callable[[ServiceConfig], Bus] | None = None,
        adapter: RobotAdapter | None = None) -> dict:  # fmt: skip
    """Drive the robot; the summary (also written to ``cfg.out``)."""
    if adapter is None and not cfg.sim:
        raise SystemExit("robot: only --sim is built in; a real arm runs through a RobotAdapter (see "
                         "services/inference/adapter.py)")  # fmt: skip
    make_bus = subscribing_bus_factory(bus_factory, lambda bus: None)
    adapter = adapter or SimRobot(cfg.task, cfg.env_settings())
    recorder = None
    if cfg.record:
        recorder = McapRecorder(cfg.record, overwrite=True, metadata={
            "task": cfg.task, "session": cfg.session, "latency_ms": str(cfg.latency_ms),
            "jitter_ms": str(cfg.jitter_ms), "seed_base": str(cfg.seed_base)})  # fmt: skip
    try:
        with ServiceContext("robot", cfg.service, bus_factory=make_bus) as ctx:
            assert ctx.bus is not None
            link = RobotLink(cfg, ctx.bus, adapter, recorder, metrics=ctx.metrics)
            try:
                summary = drive(cfg, link)
            finally:
                link.close()
        if recorder is not None:
            recorder.add_metadata("summary", {"json": json.dumps(summary, sort_keys=True)})
    finally:
        if recorder is not None:
            recorder.close()
        adapter.close()
    text = json.dumps(summary, indent=2, sort_keys=True)
    if cfg.out:
        Path(cfg.out).write_text(text + "\n")
    return summary


def limits_entry(limits: Limits) -> dict:
    """``limits`` as a limits-file entry (JSON-able)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(limits).items()}


def write_limits(cfg: RobotConfig) -> Path:
    """The simulated arm's envelope as a limits file (``services.inference.config``) for its robot id
    (added to the file's robots when it is one already); ValueError if the file is something else."""
    path = Path(cfg.write_limits)
    try:  # before the simulator starts: a file that is not a limits file is refused as it is
        data = json.loads(path.read_text()) if path.exists() else {}
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"--write-limits {path}: not a limits file ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("robots", {}), dict):
        raise ValueError(f"--write-limits {path}: not a limits file (an object with `robots` expected)")
    robot = SimRobot(cfg.task, cfg.env_settings())
    try:
        entry = limits_entry(sim_limits(robot.env))
    finally:
        robot.close()
    data.setdefault("robots", {})[cfg.session] = entry
    path.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    return path


def main(argv: Sequence[str]) -> int:
    cfg = config.parse(RobotConfig, {"default": RobotConfig()}, argv, "mea robot", RobotConfig.__doc__ or "")
    if cfg.write_limits:
        try:
            path = write_limits(cfg)
        except ValueError as exc:
            config.refuse("mea robot", str(exc))
        print(f"wrote the envelope of {cfg.session} ({cfg.task}) to {path}")
        return 0
    try:
        summary = run(cfg)
    except TimeoutError as exc:
        print(f"robot: {exc}")
        return 1
    print(f"{cfg.task}: success {summary['success_rate']:.2f} over {len(summary['episodes'])} episodes; "
          f"round trip p50 {summary['round_trip'].get('p50_ms', float('nan')):.2f} ms, "
          f"p99 {summary['round_trip'].get('p99_ms', float('nan')):.2f} ms; holds {summary['holds']}")  # fmt: skip
    return 0


__all__ = ["RobotConfig", "RobotLink", "drive", "main", "run"]
