"""`mea run`: the whole stack on one machine, each service its own OS process, over Zenoh.

The launcher hosts the Zenoh router itself (so nothing external is needed), starts every service
that exists in this build with `spawn` (children never inherit a Zenoh session), shows a live
status table from liveliness tokens and heartbeats, restarts a service that exits on its own (with
backoff, logged, counted in ``mea_launcher_service_restarts_total`` and the status line; a restarted
actor takes fresh seeds and records no demos again, a restarted learner resumes its checkpoint) and
stops the stack when one keeps exiting (``--restart-limit`` within ``--restart-window-seconds``), and
on Ctrl-C / SIGTERM stops every child within a few seconds (SIGTERM, then SIGKILL for stragglers).
Children also die with the launcher (PR_SET_PDEATHSIG), so no orphan survives it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import logging
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live

from proto.topics import EPISODES_RAW
from services.common import config, logs, run_key
from services.common.bus.base import Bus, Credentials
from services.common.bus.inproc import Hub, InProcBus
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from services.common.mcap_io import SegmentedRecorder
from services.common.metrics import ServiceMetrics
from services.common.runtime import Shutdown, die_with_parent, stopped_by
from services.plan import ChildSpec, child_specs, restarted
from services.run_config import PRESETS, RunConfig, recording_metadata, resumed_config
from services.status_board import StatusBoard
from services.supervision import RestartPolicy, RestartSettings

log = logging.getLogger(__name__)


def _entry(spec: ChildSpec) -> Callable:
    """The function ``spec.entry`` ("module:function"; function main when omitted) names."""
    module_name, _, func = spec.entry.partition(":")
    return getattr(importlib.import_module(module_name), func or "main")


class ServiceThread(threading.Thread):
    """A service running in the launcher's process (``--in-process``), with a process's ``exitcode``
    (None while it runs; its return value, or 1 if it raised) so supervision treats both alike."""

    def __init__(self, spec: ChildSpec, bus_factory, parent: Shutdown) -> None:
        super().__init__(name=spec.instance, daemon=True)
        self.spec, self.bus_factory, self.parent = spec, bus_factory, parent
        self.exitcode: int | None = None

    def run(self) -> None:
        try:
            with stopped_by(self.parent):  # the service's own Shutdown follows the launcher's
                code = _entry(self.spec)(self.spec.config, bus_factory=self.bus_factory)
            self.exitcode = int(code or 0)
        except BaseException:  # noqa: BLE001 - a failed service is reported like a dead process
            log.exception("service failed", extra={"child": self.spec.instance})
            self.exitcode = 1

    def kill(self) -> None:
        """Threads cannot be killed; a service that ignores its shutdown is left to the process exit."""


def _child_main(spec: ChildSpec) -> None:
    die_with_parent()
    sys.exit(_entry(spec)(spec.config if spec.config is not None else list(spec.argv)) or 0)


def stop_children(procs: dict, grace: float) -> None:
    """SIGTERM each child process (service threads follow the launcher's Shutdown instead), wait up
    to ``grace`` seconds, then kill what is left."""
    for p in procs.values():
        if p.is_alive() and getattr(p, "pid", None):
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


class EpisodeRecorder:
    """Writes every raw episode the router sees to numbered MCAP segments in ``directory``
    (``SegmentedRecorder``: rolled by size or age, the oldest deleted beyond a budget), in a thread
    of the launcher. An episode an actor publishes again (no ack yet) is recorded once: the ids of the
    last ``RECENT_IDS`` episodes are remembered (repeats come within minutes, never that many later)."""

    RECENT_IDS = 4096

    def __init__(self, router: Bus, directory: Path, run: int, metadata: dict[str, str], *,
                 segment_bytes: int = 0, segment_seconds: float = 0.0, max_bytes: int = 0) -> None:  # fmt: skip
        self.sub = router.subscribe(EPISODES_RAW, capacity=256)
        self.written = 0
        self.repeats = 0
        self._recent: OrderedDict[str, None] = OrderedDict()
        self.recorder = SegmentedRecorder(directory, run, metadata=metadata, compression="zstd",
                                          segment_bytes=segment_bytes, segment_seconds=segment_seconds,
                                          max_bytes=max_bytes)  # fmt: skip
        self._stop = False
        self.thread = threading.Thread(target=self._loop, name="recorder", daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while not self._stop:
            d = self.sub.recv(timeout=0.25)
            try:
                if d is None:
                    self.recorder.tick()  # an idle segment still ends on time
                    continue
                self._write(d)
            except Exception:  # noqa: BLE001 - a recording problem must not stop training
                log.exception("recording an episode failed")

    def _write(self, d) -> None:
        eid = d.message.episode_id
        if eid in self._recent:
            self.repeats += 1
            return
        self.recorder.write(d.message, topic=d.key)
        self.written += 1
        self._recent[eid] = None
        if len(self._recent) > self.RECENT_IDS:
            self._recent.popitem(last=False)

    def close(self) -> None:
        self.sub.close()
        self._stop = True
        self.thread.join(timeout=5.0)
        try:
            for d in self.sub.drain():  # what was already received is still written
                self._write(d)
        finally:
            self.recorder.close()


def _launcher_metrics(cfg: RunConfig, router: Bus) -> ServiceMetrics:
    metrics = ServiceMetrics("launcher", "launcher", cfg.namespace)
    metrics.watch_bus(router)
    if cfg.metrics_port:
        try:
            metrics.serve(cfg.metrics_addr, cfg.metrics_port)
        except OSError as exc:
            log.warning("launcher /metrics not served", extra={"port": cfg.metrics_port, "error": str(exc)})
    return metrics


class Supervisor:
    """Restarts instances that exit on their own (``services.supervision``): with backoff, from the
    plan's restart spec; gives up on one that keeps exiting, which stops the stack if the run says so."""

    def __init__(self, cfg: RunConfig, specs: dict[str, ChildSpec], procs: dict, start, board: StatusBoard,
                 metrics: ServiceMetrics) -> None:  # fmt: skip
        self.cfg, self.specs, self.procs, self.start, self.board = cfg, specs, procs, start, board
        self.policy = RestartPolicy(
            RestartSettings(limit=cfg.restart_limit, window_seconds=cfg.restart_window_seconds)
        )
        self.due: dict[str, float] = {}  # instance -> monotonic time of its restart
        self.exits = metrics.counter(
            "mea_launcher_service_exits", "Service processes that exited before shutdown.", ["service"]
        )
        self.restarts = metrics.counter(
            "mea_launcher_service_restarts", "Service restarts, by service.", ["service"]
        )

    def check(self, shutdown: Shutdown) -> bool:
        """Handle exits and due restarts; returns True if the run must stop because a service failed."""
        now = time.monotonic()
        for name, p in self.procs.items():
            if p.exitcode is None or name in self.due or name in self.board.exits:
                continue
            spec = self.specs[name]
            self.exits.labels(spec.service).inc()
            self.board.mark_exited(name, p.exitcode, getattr(p, "pid", None))
            delay = self.policy.on_exit(name, now)
            if delay is None:
                log.error("service exited; not restarted", extra={"child": name, "exitcode": p.exitcode,
                                                                  "restarts": self.policy.restarts[name]})  # fmt: skip
                if self.cfg.stop_on_failure:
                    shutdown.set(f"{name} exited with {p.exitcode}")
                    return True
                continue
            log.error("service exited; restarting", extra={"child": name, "exitcode": p.exitcode,
                                                           "in_seconds": delay})  # fmt: skip
            self.due[name] = now + delay
        for name, at in list(self.due.items()):
            if now >= at and not shutdown.is_set():
                del self.due[name]
                n = self.policy.restarts[name]
                self.procs[name] = self.start(restarted(self.specs[name], n))
                self.board.restarted(name, n)
                self.restarts.labels(self.specs[name].service).inc()
        return False


def _supervise(
    cfg: RunConfig,
    supervisor: Supervisor,
    board: StatusBoard,
    router: Bus,
    metrics: ServiceMetrics,
    shutdown: Shutdown,
) -> bool:
    """Show status until shutdown; returns True if a service failed."""
    alive_gauge = metrics.gauge(
        "mea_launcher_services_alive", "Service instances holding a liveliness token."
    )
    watch = router.watch_alive()
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
            board.take()
            failed = supervisor.check(shutdown) or failed
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


def _router(cfg: RunConfig) -> Bus:
    """The launcher's own bus: the embedded Zenoh router, or the hub of the in-process bus."""
    if cfg.in_process:
        return InProcBus(Hub(), namespace=cfg.namespace)
    return ZenohBus(
        ZenohConfig(mode="router", listen=(cfg.listen,), connect=cfg.connect, namespace=cfg.namespace)
    )


def _starter(cfg: RunConfig, router: Bus, shutdown: Shutdown) -> Callable[[ChildSpec], Any]:
    """How instances start: a spawned process over Zenoh, or a thread over the in-process bus."""
    if cfg.in_process:
        hub = router.hub  # type: ignore[attr-defined]

        def bus_factory(c):
            return InProcBus(hub, namespace=c.zenoh.namespace)

        def start_thread(spec: ChildSpec) -> ServiceThread:
            t = ServiceThread(spec, bus_factory, shutdown)
            t.start()
            return t

        return start_thread
    ctx = mp.get_context("spawn")

    def start_process(spec: ChildSpec) -> mp.process.BaseProcess:
        p = ctx.Process(target=_child_main, args=(spec,), name=spec.instance, daemon=False)
        p.start()
        return p

    return start_process


def _save_plan(specs: list[ChildSpec], run_dir: Path) -> None:
    """Each service's resolved config beside the run's: RUN_DIR/services/<instance>.json."""
    for s in specs:
        if s.config is not None:
            config.save(s.config, run_dir / "services" / f"{s.instance}.json")


def run(cfg: RunConfig) -> int:
    if cfg.in_process:
        logs.setup_in_process(cfg.log_format, "INFO")
        if cfg.extra_services:
            print(
                "mea run: --extra-services start their own processes; not with --in-process", file=sys.stderr
            )
            return 2
    else:
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
    _save_plan(specs, run_dir)
    try:
        router = _router(cfg)
    except Exception as exc:  # noqa: BLE001 - zenoh raises ZError; turn it into a clear message
        print(f"mea run: cannot start the Zenoh router on {cfg.listen}: {exc}", file=sys.stderr)
        return 2
    if cfg.authenticate:  # the launcher reads heartbeats, reports and episodes as the run's own
        key = run_key.create(run_dir / run_key.FILE_NAME)
        router.authenticate(Credentials(key, "launcher", "launcher"))
        log.info("bus authenticated", extra={"run_key": run_key.describe(key)})
    metrics = _launcher_metrics(cfg, router)
    recorder = None
    if cfg.record:
        recorder = EpisodeRecorder(router, run_dir / "episodes", cfg.resumes, recording_metadata(cfg),
                                   segment_bytes=cfg.recording_segment_bytes,
                                   segment_seconds=cfg.recording_segment_seconds,
                                   max_bytes=cfg.recording_max_bytes)  # fmt: skip
    board = StatusBoard(specs, budget=cfg.env_steps, bus=router)
    procs: dict = {}
    failed = False
    start = _starter(cfg, router, shutdown)
    try:
        procs = {s.instance: start(s) for s in specs}
        topology = "in-process" if cfg.in_process else cfg.listen
        log.info("started", extra={"run_dir": str(run_dir), "children": len(procs), "listen": topology})
        supervisor = Supervisor(cfg, {s.instance: s for s in specs}, procs, start, board, metrics)
        failed = _supervise(cfg, supervisor, board, router, metrics, shutdown)
        log.info(
            "stopping", extra={"reason": shutdown.reason, "progress": board.progress_line(board.started)}
        )
    finally:
        shutdown.set("stopping")
        stop_children(procs, cfg.stop_grace_seconds)
        board.take(settle=0.2)  # the services' last heartbeats
        board.save_summary(run_dir / "summary.json", recorder.written if recorder else None)
        if recorder is not None:
            recorder.close()
        board.close()
        router.close()
        render_curves(run_dir)
        metrics.close()
    return 1 if failed else 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(RunConfig, PRESETS, argv, "mea run", RunConfig.__doc__ or ""))
