"""`mea run`: the whole stack on one machine, each service its own OS process, over Zenoh.

The launcher hosts the Zenoh router itself (so nothing external is needed), starts every service
that exists in this build with `spawn` (children never inherit a Zenoh session), shows a live
status table from liveliness tokens and heartbeats, restarts nothing silently, and on Ctrl-C /
SIGTERM stops every child within a few seconds (SIGTERM, then SIGKILL for stragglers). Children
also die with the launcher (PR_SET_PDEATHSIG), so no orphan survives it.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import multiprocessing as mp
import os
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.live import Live
from rich.table import Table

from proto.control import Heartbeat
from proto.topics import STATUS
from services.cli import available
from services.common import config, logs
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from services.common.metrics import ServiceMetrics
from services.common.runtime import Shutdown, die_with_parent

log = logging.getLogger(__name__)

SERVICE_ORDER = ("learner", "augmenter", "evaluator", "actor")
SERVICE_MODULES = {s: f"services.{s}.main" for s in SERVICE_ORDER}


@dataclass(frozen=True)
class RunConfig:
    """Run the full training stack locally."""

    task: str = "block_pull"
    """Task: block_pull, block_pick or drawer_open."""
    actors: int = 1
    """Number of actor processes."""
    demos: int = 2
    """Scripted demonstrations pre-filled before training."""
    run_dir: Path | None = None
    """Run directory (config, checkpoints, eval history, recordings); default runs/<time>-<task>."""
    listen: str = "tcp/127.0.0.1:7447"
    """Endpoint of the embedded Zenoh router; services connect to it."""
    namespace: str = "default"
    """Key namespace of this run (separates runs sharing a Zenoh network)."""
    metrics_port: int = 9100
    """Launcher /metrics port (router traffic, services alive); services use their own defaults
    (README). 0 disables every /metrics."""
    duration_seconds: float = 0.0
    """Stop after this many seconds (0: run until Ctrl-C / SIGTERM)."""
    stop_grace_seconds: float = 5.0
    """How long children get to exit after SIGTERM before SIGKILL."""
    stop_on_failure: bool = True
    """If a service exits unexpectedly, stop the whole stack (otherwise keep running without it)."""
    services: tuple[str, ...] = SERVICE_ORDER
    """Services to start (those not in this build are skipped, and listed)."""
    extra_services: tuple[str, ...] = ()
    """Additional `module:function` entries to start as services (plugins; used by tests)."""
    log_format: str = "text"
    """Log format of the launcher and its services: json or text."""

    def __post_init__(self) -> None:
        if self.actors < 0:
            raise ValueError("actors must be >= 0")
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
    """Latest heartbeat per instance plus liveliness, rendered as a table."""

    KEY_COUNTERS = 4

    def __init__(self, specs: list[ChildSpec]) -> None:
        self.expected = [(s.service, s.instance) for s in specs]
        self.beats: dict[tuple[str, str], Heartbeat] = {}
        self.exits: dict[str, int] = {}

    def update(self, hb: Heartbeat) -> None:
        self.beats[(hb.service, hb.instance_id)] = hb

    def table(self, alive: set[tuple[str, str]], started: float) -> Table:
        t = Table(title=f"mea run — {time.time() - started:,.0f} s")
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
                    f"{k}={v:,.0f}" for k, v in list(hb.counters.items())[: self.KEY_COUNTERS]
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
            if live:
                live.update(board.table(alive, started))
            elif time.time() - last_line > 10:
                last_line = time.time()
                log.info(
                    "status",
                    extra={"alive": f"{sum(w in alive for w in board.expected)}/{len(board.expected)}"},
                )
            shutdown.wait(0.25)
    finally:
        if live:
            live.stop()
    return failed


def run(cfg: RunConfig) -> int:
    logs.setup("launcher", "launcher", cfg.log_format, "INFO")
    run_dir = cfg.run_dir or Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{cfg.task}"
    run_dir.mkdir(parents=True, exist_ok=True)
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
    ctx = mp.get_context("spawn")
    procs: dict[str, mp.process.BaseProcess] = {}
    failed = False
    try:
        for s in specs:
            p = ctx.Process(target=_child_main, args=(s.entry, list(s.argv)), name=s.instance, daemon=False)
            p.start()
            procs[s.instance] = p
        log.info("started", extra={"run_dir": str(run_dir), "children": len(procs), "listen": cfg.listen})
        failed = _supervise(cfg, procs, StatusBoard(specs), router, metrics, shutdown)
        log.info("stopping", extra={"reason": shutdown.reason})
    finally:
        stop_children(procs, cfg.stop_grace_seconds)
        router.close()
        metrics.close()
    return 1 if failed else 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(RunConfig, PRESETS, argv, "mea run", RunConfig.__doc__ or ""))
