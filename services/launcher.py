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
from pathlib import Path

from rich.console import Console
from rich.live import Live
from rich.table import Table

from proto.control import EvalReport, Heartbeat
from proto.topics import EPISODES_RAW, EVAL_REPORTS, STATUS
from services.common import config, logs
from services.common.bus.base import Bus
from services.common.bus.inproc import Hub, InProcBus
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from services.common.mcap_io import McapRecorder
from services.common.metrics import ServiceMetrics
from services.common.runtime import Shutdown, die_with_parent, stopped_by
from services.plan import ChildSpec, child_specs
from services.run_config import PRESETS, RunConfig, resumed_config

log = logging.getLogger(__name__)


class ServiceThread(threading.Thread):
    """A service running in the launcher's process (``--in-process``), with a process's ``exitcode``
    (None while it runs; its return value, or 1 if it raised) so supervision treats both alike."""

    def __init__(self, spec: ChildSpec, bus_factory, parent: Shutdown) -> None:
        super().__init__(name=spec.instance, daemon=True)
        self.spec, self.bus_factory, self.parent = spec, bus_factory, parent
        self.exitcode: int | None = None

    def run(self) -> None:
        module_name, _, func = self.spec.entry.partition(":")
        try:
            with stopped_by(self.parent):  # the service's own Shutdown follows the launcher's
                fn = getattr(importlib.import_module(module_name), func)
                code = fn(self.spec.config, bus_factory=self.bus_factory)
            self.exitcode = int(code or 0)
        except BaseException:  # noqa: BLE001 - a failed service is reported like a dead process
            log.exception("service failed", extra={"child": self.spec.instance})
            self.exitcode = 1

    def kill(self) -> None:
        """Threads cannot be killed; a service that ignores its shutdown is left to the process exit."""


def _child_main(spec: ChildSpec) -> None:
    die_with_parent()
    module_name, _, func = spec.entry.partition(":")
    fn = getattr(importlib.import_module(module_name), func or "main")
    sys.exit(fn(spec.config if spec.config is not None else list(spec.argv)) or 0)


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


class StatusBoard:
    """Latest heartbeat per instance, liveliness and evaluation reports, rendered as a table with a
    progress line (env steps, augmented transitions, updates, weights version, success, ETA)."""

    KEY_COUNTERS = 4
    RATE_WINDOW = 120.0

    def __init__(self, specs: list[ChildSpec], budget: int = 0, bus: Bus | None = None) -> None:
        self.expected = [(s.service, s.instance) for s in specs]
        self.beats: dict[tuple[str, str], Heartbeat] = {}
        self.exits: dict[str, int] = {}
        self.budget = budget
        self.report: EvalReport | None = None
        self.reports = 0
        self._steps: list[tuple[float, float]] = []  # (time, env steps) for the rate
        self.started = time.time()
        self._subs = (
            (bus.subscribe(STATUS, capacity=1024), bus.subscribe(EVAL_REPORTS, capacity=256)) if bus else None
        )

    def take(self, settle: float = 0.0) -> None:
        """Take the heartbeats and reports received so far (waiting ``settle`` s for stragglers)."""
        if self._subs is None:
            return
        if settle:
            time.sleep(settle)
        beats, reports = self._subs
        for d in beats.drain():
            self.update(d.message)
        for d in reports.drain():
            self.add_report(d.message)

    def close(self) -> None:
        for sub in self._subs or ():
            sub.close()

    def summary(self, episodes_recorded: int | None = None) -> dict:
        """What the run did, from each instance's last heartbeat: counters per instance, evaluations,
        the newest report, and the raw episodes recorded (None: not recorded)."""
        return {
            "instances": {
                inst: {
                    "service": svc,
                    "exitcode": self.exits.get(inst),
                    "counters": dict(self.beats[(svc, inst)].counters) if (svc, inst) in self.beats else {},
                }
                for svc, inst in self.expected
            },  # fmt: skip
            "evaluations": self.reports,
            "last_report": None
            if self.report is None
            else {
                "env_steps": self.report.env_steps,
                "success_rate": self.report.success_rate,
                "policy_version": self.report.policy_version,
            },  # fmt: skip
            "episodes_recorded": episodes_recorded,
            "elapsed_seconds": round(time.time() - self.started, 1),
        }

    def save_summary(self, path: Path, episodes_recorded: int | None = None) -> None:
        try:
            path.write_text(json.dumps(self.summary(episodes_recorded), indent=2, sort_keys=True) + "\n")
        except OSError as exc:
            log.warning("run summary not written", extra={"path": str(path), "error": str(exc)})

    def update(self, hb: Heartbeat) -> None:
        self.beats[(hb.service, hb.instance_id)] = hb

    def add_report(self, r: EvalReport) -> None:
        self.reports += 1
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

    def __init__(self, router: Bus, path: Path, metadata: dict[str, str]) -> None:
        self.sub = router.subscribe(EPISODES_RAW, capacity=256)
        self.written = 0
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
                    self.written += 1
                except Exception:  # noqa: BLE001 - a recording problem must not stop training
                    log.exception("recording an episode failed")

    def close(self) -> None:
        self.sub.close()
        self._stop = True
        self.thread.join(timeout=5.0)
        for d in self.sub.drain():  # what was already received is still written
            self.recorder.write(d.message, topic=d.key)
            self.written += 1
        self.recorder.close()


def _launcher_metrics(cfg: RunConfig, router: Bus) -> ServiceMetrics:
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
    router: Bus,
    metrics: ServiceMetrics,
    shutdown: Shutdown,
) -> bool:
    """Show status until shutdown; returns True if a service failed."""
    alive_gauge = metrics.gauge(
        "mea_launcher_services_alive", "Service instances holding a liveliness token."
    )
    exited = metrics.counter("mea_launcher_service_exits", "Service processes that exited before shutdown.")
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


def _router(cfg: RunConfig) -> Bus:
    """The launcher's own bus: the embedded Zenoh router, or the hub of the in-process bus."""
    if cfg.in_process:
        return InProcBus(Hub(), namespace=cfg.namespace)
    return ZenohBus(ZenohConfig(mode="router", listen=(cfg.listen,), namespace=cfg.namespace))


def _start(cfg: RunConfig, specs: list[ChildSpec], router: Bus, shutdown: Shutdown) -> dict:
    """Start every instance: a spawned process over Zenoh, or a thread over the in-process bus."""
    procs: dict = {}
    if cfg.in_process:
        hub = router.hub  # type: ignore[attr-defined]

        def bus_factory(c):
            return InProcBus(hub, namespace=c.zenoh.namespace)

        for s in specs:
            procs[s.instance] = ServiceThread(s, bus_factory, shutdown)
            procs[s.instance].start()
        return procs
    ctx = mp.get_context("spawn")
    for s in specs:
        p = ctx.Process(target=_child_main, args=(s,), name=s.instance, daemon=False)
        p.start()
        procs[s.instance] = p
    return procs


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
    metrics = _launcher_metrics(cfg, router)
    recorder = None
    if cfg.record:
        meta = {"task": cfg.task, "variant": cfg.variant, "seed": str(cfg.seed), "resumes": str(cfg.resumes)}
        recorder = EpisodeRecorder(router, run_dir / "episodes" / f"raw-{cfg.resumes}.mcap", meta)
    board = StatusBoard(specs, budget=cfg.env_steps, bus=router)
    procs: dict = {}
    failed = False
    try:
        procs = _start(cfg, specs, router, shutdown)
        topology = "in-process" if cfg.in_process else cfg.listen
        log.info("started", extra={"run_dir": str(run_dir), "children": len(procs), "listen": topology})
        failed = _supervise(cfg, procs, board, router, metrics, shutdown)
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
