"""`mea run`: the whole stack on one machine, each service its own OS process, over Zenoh.

The launcher hosts the Zenoh router itself (so nothing external is needed), starts every service
that exists in this build with `spawn` (children never inherit a Zenoh session), shows a live
status table from liveliness tokens and heartbeats, restarts nothing silently, and on Ctrl-C /
SIGTERM stops every child within a few seconds (SIGTERM, then SIGKILL for stragglers). Children
also die with the launcher (PR_SET_PDEATHSIG), so no orphan survives it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import json
import logging
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.live import Live
from rich.table import Table

from proto.control import EvalReport, Heartbeat
from proto.topics import EPISODES_RAW, EVAL_REPORTS, STATUS
from services.cli import available
from services.common import config, logs
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from services.common.mcap_io import McapRecorder
from services.common.metrics import ServiceMetrics
from services.common.runtime import Shutdown, die_with_parent

log = logging.getLogger(__name__)

SERVICE_ORDER = ("learner", "augmenter", "evaluator", "actor")
SERVICE_MODULES = {s: f"services.{s}.main" for s in SERVICE_ORDER}


VARIANTS = ("mea", "equiobs", "equirsac")
MEA_ON = ("", "demos", "successes", "all")
CPU_LEARNER_PRESETS = ("cpu-small", "cpu-small-state")
"""Learner presets for two CPU cores: MEA on online successes too, 64 rotated copies of successes."""


@dataclass(frozen=True)
class RunConfig:
    """Run the full training stack locally."""

    task: str = "block_pull"
    """Task: block_pull, block_pick or drawer_open."""
    variant: str = "mea"
    """What the paper compares: equirsac (rendered depth image, isometric x4), equiobs (voxel
    projection, isometric x4), mea (voxel projection, isometric x4 + MEA x6 on the demos, and with the
    cpu-small learner on online successes too: see mea_on)."""
    mea_on: str = ""
    """mea variant only: which episodes get MEA (demos: the paper; successes: the demos and every online
    success; all). Empty: successes with the cpu-small learner preset, demos with the others."""
    env_steps: int = 40_000
    """Env-step budget (the paper: 40K, demos included); the run stops after the evaluation at the
    budget. 0: run until Ctrl-C."""
    learner_preset: str = "cpu-small"
    """Learner preset: cpu-small (two CPU cores), cpu-small-state (the same with a critic on the
    simulator's state), paper (a GPU workstation), smoke (tests)."""
    seed: int = 0
    """Run seed: actors' training seeds, augmentation, networks (evaluation seeds are fixed)."""
    eval_every: int = 1000
    """Evaluate the newest weights every this many env steps (Equi-RSAC: 250-500; raise it on CPU)."""
    eval_episodes: int = 20
    """Evaluation episodes per evaluation (held-out seeds from 1e9, the same every time; deterministic
    policy)."""
    final_eval_episodes: int = 50
    """Episodes of the evaluation at the env-step budget (the same held-out seed sequence, its first
    final_eval_episodes seeds)."""
    record: bool = True
    """Record every raw episode to RUN_DIR/episodes/raw-<n>.mcap."""
    follow_gate: bool = True
    """Actors wait for the learner's replay gate (off: actors run flat out; for benchmarks)."""
    resume: Path | None = None
    """Continue the run in this directory (its saved config; learner checkpoint; no new demos)."""
    resumes: int = 0
    """How many times the run was resumed (set by --resume; moves the actors' seed streams on)."""
    actors: int = 1
    """Number of actor processes."""
    demos: int = 2
    """Scripted demonstrations pre-filled before training."""
    run_dir: Path | None = None
    """Run directory (config, checkpoints, eval history, recordings); default runs/<time>-<task>-<variant>."""
    listen: str = "tcp/127.0.0.1:7447"
    """Endpoint of the embedded Zenoh router; services connect to it."""
    namespace: str = "default"
    """Key namespace of this run (separates runs sharing a Zenoh network)."""
    metrics_port: int = 9100
    """Launcher /metrics port (router traffic, services alive); services use their own defaults
    (README). 0 disables every /metrics."""
    duration_seconds: float = 0.0
    """Stop after this many seconds (0: run until Ctrl-C / SIGTERM)."""
    stop_grace_seconds: float = 30.0
    """How long children get to exit after SIGTERM before SIGKILL (the learner writes its final
    checkpoint then; others exit within a second or two)."""
    stop_on_failure: bool = True
    """If a service exits unexpectedly, stop the whole stack (otherwise keep running without it)."""
    services: tuple[str, ...] = SERVICE_ORDER
    """Services to start (those not in this build are skipped, and listed)."""
    extra_services: tuple[str, ...] = ()
    """Additional `module:function` entries to start as services (plugins; used by tests)."""
    log_format: str = "text"
    """Log format of the launcher and its services: json or text."""
    final_eval_seconds: float = 900.0
    """At the budget, how long to wait for the evaluation of the last weights (final_eval_episodes
    episodes) before stopping."""

    success_rotations: int | None = None
    """Rotated copies of each demonstration and online success (every variant; other episodes get
    4). None: the learner preset's default (cpu-small: 64, the paper: 4 like every episode)."""

    def resolved_success_rotations(self) -> int:
        """``success_rotations``, else the learner preset's default: the CPU recipe clones its few
        successes, and BC of 2 Block Pull demos reached 0.23-0.33 with 64 rotated copies against
        0.05-0.10 with 4 (30 held-out seeds, 3000 updates)."""
        if self.success_rotations is not None:
            return self.success_rotations
        return 64 if self.learner_preset in CPU_LEARNER_PRESETS else 0

    def resolved_mea_on(self) -> str:
        """What the mea variant runs MEA on: ``mea_on``, else the learner preset's default (the CPU
        recipe adds online successes: beyond the two demos, they are the only other layouts)."""
        return self.mea_on or ("successes" if self.learner_preset in CPU_LEARNER_PRESETS else "demos")

    def __post_init__(self) -> None:
        if self.actors < 0:
            raise ValueError("actors must be >= 0")
        if self.success_rotations is not None and self.success_rotations < 0:
            raise ValueError("success_rotations must be >= 0")
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, not {self.variant!r}")
        if self.mea_on not in MEA_ON:
            raise ValueError(f"mea_on must be one of {MEA_ON[1:]}, not {self.mea_on!r}")
        if self.mea_on and self.variant != "mea":
            raise ValueError("--mea-on applies to --variant mea only")
        if self.env_steps < 0 or min(self.eval_every, self.eval_episodes, self.final_eval_episodes) < 1:
            raise ValueError("env_steps must be >= 0, eval_every, eval_episodes and final_eval_episodes >= 1")
        unknown = set(self.services) - set(SERVICE_ORDER)
        if unknown:
            raise ValueError(f"unknown services {sorted(unknown)}; choose from {SERVICE_ORDER}")


PRESETS = {"default": RunConfig()}


@dataclass(frozen=True)
class ChildSpec:
    service: str
    instance: str
    entry: str  # "module:function", called with argv
    argv: tuple[str, ...]


def _common_args(cfg: RunConfig, instance: str, metrics_port: int | None) -> list[str]:
    args = [
        "--service.instance-id",
        instance,
        "--service.zenoh.connect",
        cfg.listen,
        "--service.zenoh.namespace",
        cfg.namespace,
        "--service.log-format",
        cfg.log_format,
    ]
    if metrics_port is not None:
        args += ["--service.metrics-port", str(metrics_port)]
    return args


def child_specs(cfg: RunConfig, run_dir: Path) -> tuple[list[ChildSpec], list[str]]:
    """Children to start, and the names of requested services missing from this build."""
    specs, missing = [], []
    no_metrics = 0 if cfg.metrics_port == 0 else None
    for service in SERVICE_ORDER:
        if service not in cfg.services:
            continue
        if not available(service):
            missing.append(service)
            continue
        module = importlib.import_module(SERVICE_MODULES[service])
        count = cfg.actors if service == "actor" else 1
        for i in range(count):
            instance = f"{service}-{i}"
            argv = _common_args(cfg, instance, no_metrics) + list(module.launch_args(cfg, run_dir, i))
            specs.append(ChildSpec(service, instance, f"{SERVICE_MODULES[service]}:main", tuple(argv)))
    for i, entry in enumerate(cfg.extra_services):
        instance = f"extra-{i}"
        specs.append(ChildSpec("test", instance, entry, tuple(_common_args(cfg, instance, no_metrics))))
    return specs, missing


def _child_main(entry: str, argv: list[str]) -> None:
    die_with_parent()
    module_name, _, func = entry.partition(":")
    fn = getattr(importlib.import_module(module_name), func or "main")
    sys.exit(fn(argv) or 0)


def stop_children(procs: dict[str, mp.process.BaseProcess], grace: float) -> None:
    for p in procs.values():
        if p.is_alive() and p.pid:
            with contextlib.suppress(ProcessLookupError):
                os.kill(p.pid, signal.SIGTERM)
    deadline = time.monotonic() + grace
    for p in procs.values():
        p.join(timeout=max(0.0, deadline - time.monotonic()))
    for name, p in procs.items():
        if p.is_alive():
            log.warning("child did not stop in time; killing", extra={"child": name})
            p.kill()
            p.join(timeout=2.0)


class StatusBoard:
    """Latest heartbeat per instance, liveliness and evaluation reports, rendered as a table with a
    progress line (env steps, augmented transitions, updates, weights version, success, ETA)."""

    KEY_COUNTERS = 4
    RATE_WINDOW = 120.0

    def __init__(self, specs: list[ChildSpec], budget: int = 0) -> None:
        self.expected = [(s.service, s.instance) for s in specs]
        self.beats: dict[tuple[str, str], Heartbeat] = {}
        self.exits: dict[str, int] = {}
        self.budget = budget
        self.report: EvalReport | None = None
        self._steps: list[tuple[float, float]] = []  # (time, env steps) for the rate
        self.started = time.time()

    def update(self, hb: Heartbeat) -> None:
        self.beats[(hb.service, hb.instance_id)] = hb

    def add_report(self, r: EvalReport) -> None:
        if self.report is None or r.policy_version >= self.report.policy_version:
            self.report = r

    def _sum(self, service: str, key: str) -> float | None:
        values = [
            hb.counters[key] for (svc, _), hb in self.beats.items() if svc == service and key in hb.counters
        ]
        return sum(values) if values else None

    def env_steps(self) -> float | None:
        """The learner's count of inserted env steps (else the actors' own)."""
        learner = self._sum("learner", "env_steps")
        return learner if learner is not None else self._sum("actor", "env_steps")

    def progress(self, started: float, now: float | None = None) -> dict[str, float | str | None]:
        now = time.time() if now is None else now
        steps = self.env_steps()
        eta = None
        if steps is not None:
            self._steps = [(t, v) for t, v in self._steps if now - t <= self.RATE_WINDOW] + [(now, steps)]
            (t0, v0), (t1, v1) = self._steps[0], self._steps[-1]
            if self.budget and v1 > v0 and t1 > t0:
                eta = max(0.0, (self.budget - v1) / ((v1 - v0) / (t1 - t0)))
        r = self.report
        return {
            "env_steps": steps,
            "augmented": self._sum("augmenter", "transitions_out"),
            "updates": self._sum("learner", "updates"),
            "version": self._sum("learner", "version"),
            "success": None if r is None else r.success_rate,
            "success_at": None if r is None else r.env_steps,
            "elapsed": now - started,
            "eta": eta,
        }

    def progress_line(self, started: float) -> str:
        p = self.progress(started)

        def n(v) -> str:
            return "—" if v is None else f"{v:,.0f}"

        budget = f"/{self.budget:,}" if self.budget else ""
        success = "—" if p["success"] is None else f"{p['success']:.0%} (at {n(p['success_at'])} steps)"
        eta = "—" if p["eta"] is None else f"{p['eta'] / 60:,.0f} min"
        return (f"env steps {n(p['env_steps'])}{budget} · augmented transitions {n(p['augmented'])} · "
                f"updates {n(p['updates'])} · weights v{n(p['version'])} · success {success} · "
                f"elapsed {p['elapsed'] / 60:,.1f} min · ETA {eta}")  # fmt: skip

    def table(self, alive: set[tuple[str, str]], started: float) -> Table:
        t = Table(title=f"mea run — {time.time() - started:,.0f} s", caption=self.progress_line(started))
        for col in ("service", "instance", "alive", "state", "policy", "counters"):
            t.add_column(col)
        for who in self.expected:
            hb = self.beats.get(who)
            if who[1] in self.exits:
                state = f"exited ({self.exits[who[1]]})"
            else:
                state = hb.state if hb else "starting"
            counters = ""
            if hb:
                counters = "  ".join(
                    f"{k}={v:,.3g}" if abs(v) < 10 else f"{k}={v:,.0f}"
                    for k, v in list(hb.counters.items())[: self.KEY_COUNTERS]
                )
            t.add_row(
                who[0],
                who[1],
                "yes" if who in alive else "no",
                state,
                str(hb.policy_version) if hb else "—",
                counters,
            )
        return t


class EpisodeRecorder:
    """Writes every raw episode the router sees to an MCAP file, in a thread of the launcher."""

    def __init__(self, router: ZenohBus, path: Path, metadata: dict[str, str]) -> None:
        self.sub = router.subscribe(EPISODES_RAW, capacity=256)
        self.recorder = McapRecorder(path, metadata=metadata, compression="zstd")
        self._stop = False
        self.thread = threading.Thread(target=self._loop, name="recorder", daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while not self._stop:
            d = self.sub.recv(timeout=0.25)
            if d is not None:
                try:
                    self.recorder.write(d.message, topic=d.key)
                except Exception:  # noqa: BLE001 - a recording problem must not stop training
                    log.exception("recording an episode failed")

    def close(self) -> None:
        self.sub.close()
        self._stop = True
        self.thread.join(timeout=5.0)
        for d in self.sub.drain():  # what was already received is still written
            self.recorder.write(d.message, topic=d.key)
        self.recorder.close()


def _launcher_metrics(cfg: RunConfig, router: ZenohBus) -> ServiceMetrics:
    metrics = ServiceMetrics("launcher", "launcher")
    metrics.watch_bus(router)
    if cfg.metrics_port:
        try:
            metrics.serve("127.0.0.1", cfg.metrics_port)
        except OSError as exc:
            log.warning("launcher /metrics not served", extra={"port": cfg.metrics_port, "error": str(exc)})
    return metrics


def _supervise(
    cfg: RunConfig,
    procs: dict,
    board: StatusBoard,
    router: ZenohBus,
    metrics: ServiceMetrics,
    shutdown: Shutdown,
) -> bool:
    """Show status until shutdown; returns True if a service failed."""
    alive_gauge = metrics.gauge(
        "mea_launcher_services_alive", "Service instances holding a liveliness token."
    )
    exited = metrics.counter("mea_launcher_service_exits", "Service processes that exited before shutdown.")
    watch = router.watch_alive()
    beats = router.subscribe(STATUS, capacity=1024)
    reports = router.subscribe(EVAL_REPORTS, capacity=256)
    budget_reached_at: float | None = None
    started = time.time()
    console = Console()
    live = (
        Live(board.table(watch.alive(), started), console=console, refresh_per_second=2)
        if console.is_terminal
        else None
    )
    failed, last_line = False, 0.0
    if live:
        live.start()
    try:
        while not shutdown.is_set():
            for d in beats.drain():
                board.update(d.message)
            for d in reports.drain():
                board.add_report(d.message)
            for name, p in procs.items():
                if p.exitcode is not None and name not in board.exits:
                    board.exits[name] = p.exitcode
                    exited.inc()
                    log.error("service exited", extra={"child": name, "exitcode": p.exitcode})
                    if cfg.stop_on_failure:
                        failed = True
                        shutdown.set(f"{name} exited with {p.exitcode}")
            alive = watch.alive()
            alive_gauge.set(sum(w in alive for w in board.expected))
            if cfg.duration_seconds and time.time() - started >= cfg.duration_seconds:
                shutdown.set("duration reached")
            steps = board.env_steps()
            if cfg.env_steps and steps is not None and steps >= cfg.env_steps:
                budget_reached_at = budget_reached_at or time.time()
                evaluated = board.report is not None and board.report.env_steps >= cfg.env_steps
                has_evaluator = any(svc == "evaluator" for svc, _ in board.expected)
                if evaluated or not has_evaluator or time.time() - budget_reached_at > cfg.final_eval_seconds:
                    shutdown.set("env-step budget reached")
            if live:
                live.update(board.table(alive, started))
            elif time.time() - last_line > 10:
                last_line = time.time()
                log.info(
                    "status",
                    extra={
                        "alive": f"{sum(w in alive for w in board.expected)}/{len(board.expected)}",
                        "progress": board.progress_line(started),
                    },
                )
            shutdown.wait(0.25)
    finally:
        if live:
            live.stop()
    return failed


def render_curves(run_dir: Path) -> None:
    """RUN_DIR/curves.png from the run's evaluation history (what `mea plot RUN_DIR` draws)."""
    if not (run_dir / "eval" / "history.jsonl").exists():
        return
    try:
        from services.evaluator.plot import group_runs, load_run, render

        render(group_runs([load_run(run_dir, "variant")]), run_dir / "curves.png", title=run_dir.name)
    except Exception as exc:  # noqa: BLE001 - a missing plot must not fail a finished run
        log.warning("learning curves not rendered", extra={"error": str(exc)[:300]})


_MACHINE_FIELDS = ("listen", "metrics_port", "duration_seconds", "stop_grace_seconds", "log_format",
                   "final_eval_seconds")  # fmt: skip
"""Fields a resumed run takes from the command line rather than from the run's saved config."""


def resumed_config(cfg: RunConfig) -> RunConfig:
    """``--resume RUN_DIR``: the run's saved config, with this machine's settings, resumes + 1."""
    path = Path(cfg.resume) / "config.json"
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"mea run: cannot resume from {path}: {exc}") from None
    known = {f.name: f for f in dataclasses.fields(RunConfig)}
    values = {k: v for k, v in saved.items() if k in known and k not in _MACHINE_FIELDS}
    for k in ("services", "extra_services"):
        if k in values:
            values[k] = tuple(values[k])
    values.update(run_dir=Path(cfg.resume), resume=Path(cfg.resume), resumes=int(saved.get("resumes", 0)) + 1)
    values.update({k: getattr(cfg, k) for k in _MACHINE_FIELDS})
    return RunConfig(**values)


def run(cfg: RunConfig) -> int:
    logs.setup("launcher", "launcher", cfg.log_format, "INFO")
    if cfg.resume is not None:
        cfg = resumed_config(cfg)
        log.info("resuming", extra={"run_dir": str(cfg.run_dir), "resumes": cfg.resumes})
    run_dir = cfg.run_dir or Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{cfg.task}-{cfg.variant}"
    run_dir.mkdir(parents=True, exist_ok=True)
    cfg = dataclasses.replace(cfg, run_dir=run_dir)
    config.save(cfg, run_dir / "config.json")
    shutdown = Shutdown()
    specs, missing = child_specs(cfg, run_dir)
    if missing:
        log.warning("services not in this build are skipped", extra={"missing": ",".join(missing)})
    try:
        router = ZenohBus(ZenohConfig(mode="router", listen=(cfg.listen,), namespace=cfg.namespace))
    except Exception as exc:  # noqa: BLE001 - zenoh raises ZError; turn it into a clear message
        print(f"mea run: cannot start the Zenoh router on {cfg.listen}: {exc}", file=sys.stderr)
        return 2
    metrics = _launcher_metrics(cfg, router)
    recorder = None
    if cfg.record:
        meta = {"task": cfg.task, "variant": cfg.variant, "seed": str(cfg.seed), "resumes": str(cfg.resumes)}
        recorder = EpisodeRecorder(router, run_dir / "episodes" / f"raw-{cfg.resumes}.mcap", meta)
    ctx = mp.get_context("spawn")
    procs: dict[str, mp.process.BaseProcess] = {}
    failed = False
    try:
        for s in specs:
            p = ctx.Process(target=_child_main, args=(s.entry, list(s.argv)), name=s.instance, daemon=False)
            p.start()
            procs[s.instance] = p
        log.info("started", extra={"run_dir": str(run_dir), "children": len(procs), "listen": cfg.listen})
        board = StatusBoard(specs, budget=cfg.env_steps)
        failed = _supervise(cfg, procs, board, router, metrics, shutdown)
        log.info(
            "stopping", extra={"reason": shutdown.reason, "progress": board.progress_line(board.started)}
        )
    finally:
        stop_children(procs, cfg.stop_grace_seconds)
        if recorder is not None:
            recorder.close()
        router.close()
        render_curves(run_dir)
        metrics.close()
    return 1 if failed else 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(RunConfig, PRESETS, argv, "mea run", RunConfig.__doc__ or ""))
