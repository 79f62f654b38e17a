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
import json
import logging
import multiprocessing as mp
import os
import re
import signal
import socket
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Collection, Mapping, MutableMapping, Sequence
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live

from proto.topics import EPISODES_RAW
from services.common import config, logs, run_key
from services.common.bus.base import Bus, Credentials, Delivery
from services.common.bus.inproc import Hub, InProcBus
from services.common.bus.zenoh_bus import ZenohBus
from services.common.inbox import Inbox, receive_into
from services.common.mcap_io import SegmentedRecorder
from services.common.metrics import ServiceMetrics
from services.common.runtime import Shutdown, die_with_parent, stopped_by
from services.evaluator import plot
from services.plan import ChildSpec, check_init_actor, child_specs, describe, restarted
from services.run_config import PRESETS, RunConfig, read_resume, recording_metadata, usable_cores
from services.run_zenoh import router_config, secure
from services.status_board import SUMMARY, StatusBoard, end_of_run, reached_env_steps, read_run_history
from services.supervision import RestartPolicy, RestartSettings
from services.tasks import DEPTH_IMAGE_REVISION
from services.tracking import Tracking
from services.tracking import check as check_tracking

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
    (``SegmentedRecorder``: rolled by size or age, the oldest deleted beyond a budget). One thread
    reads the router's subscription into an inbox of at most ``inbox_bytes`` and another writes from
    it, so a slow disk or a long compression never holds the router's reader (which would hold every
    link through the router: ``services.common.inbox``). An episode an actor publishes again (no ack
    yet) is recorded once: the ids of the last ``RECENT_IDS`` episodes are remembered (repeats come
    within minutes, never that many later)."""

    RECENT_IDS = 4096
    INBOX_BYTES = 256 << 20

    def __init__(self, router: Bus, directory: Path, run: int, metadata: dict[str, str], *,
                 segment_bytes: int = 0, segment_seconds: float = 0.0, max_bytes: int = 0,
                 inbox_bytes: int = INBOX_BYTES) -> None:  # fmt: skip
        self.sub = router.subscribe(EPISODES_RAW, capacity=256)
        self.inbox: Inbox[Delivery] = Inbox(inbox_bytes)
        self.written = 0
        self.repeats = 0
        self._recent: OrderedDict[str, None] = OrderedDict()
        self.recorder = SegmentedRecorder(directory, run, metadata=metadata, compression="zstd",
                                          segment_bytes=segment_bytes, segment_seconds=segment_seconds,
                                          max_bytes=max_bytes)  # fmt: skip
        self._stop_receive, self._stop_write = threading.Event(), threading.Event()
        self.threads = [threading.Thread(target=receive_into, args=(self.sub, self.inbox, self._stop_receive),
                                         name="recorder-receive", daemon=True),
                        threading.Thread(target=self._write_loop, name="recorder-write", daemon=True)]  # fmt: skip
        for t in self.threads:
            t.start()

    def _write_loop(self) -> None:
        while not self._stop_write.is_set() or len(self.inbox):
            d = self.inbox.get(timeout=0.25)
            try:
                if d is None:
                    self.recorder.tick()  # an idle segment still ends on time
                    continue
                self._write(d)
            except Exception:  # noqa: BLE001 - a recording problem must not stop training
                log.exception("recording an episode failed")

    def _write(self, d: Delivery) -> None:
        eid = d.message.episode_id
        if eid in self._recent:
            self.repeats += 1
            return
        self.recorder.write(d.message, topic=d.key)
        self.written += 1
        self._recent[eid] = None
        if len(self._recent) > self.RECENT_IDS:
            self._recent.popitem(last=False)

    def close(self, timeout: float = 120.0) -> None:
        """Stop receiving, write what was received (the inbox, then what the subscription still
        queued) and close the segment, waiting up to ``timeout`` s for the writes."""
        self.sub.close()
        self._stop_receive.set()
        self.threads[0].join(timeout=5.0)
        for d in self.sub.drain():  # the writer is still running: the inbox cannot stay full
            self.inbox.put(d, d.size)
        self._stop_write.set()
        self.threads[1].join(timeout=timeout)
        if self.threads[1].is_alive():  # a write that hangs (a dead disk): never two writers at once
            log.error("recording did not finish; its last segment stays open",
                      extra={"unwritten_episodes": len(self.inbox)})  # fmt: skip
            return
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
        plot.render(
            plot.group_runs([plot.load_run(run_dir, "variant")]), run_dir / "curves.png", title=run_dir.name
        )
    except Exception as exc:  # noqa: BLE001 - a missing plot must not fail a finished run
        log.warning("learning curves not rendered", extra={"error": str(exc)[:300]})


def _router(cfg: RunConfig) -> Bus:
    """The launcher's own bus: the embedded Zenoh router, or the hub of the in-process bus."""
    if cfg.in_process:
        return InProcBus(Hub(), namespace=cfg.namespace)
    return ZenohBus(router_config(cfg))  # --listen, --connect, --zenoh-config


CHILD_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
"""The thread pools of torch, MKL and OpenBLAS in each service process: one thread each unless the
user's environment sets them. A run is many processes (actors, augmenter, evaluator, learner), and each
library's default of a thread per core oversubscribes the machine: on 16 cores, three runs of 7
processes made 2.9 env steps/s each with the defaults and 32 with one thread (docs/gpu.md)."""


def one_thread_per_child(environ: MutableMapping[str, str]) -> None:
    """``CHILD_THREAD_VARS`` set to 1 in ``environ`` where unset (spawned children inherit it)."""
    for var in CHILD_THREAD_VARS:
        environ.setdefault(var, "1")


def child_threads(environ: Mapping[str, str]) -> str:
    """The thread pools each spawned service process gets (``one_thread_per_child``), for the plan,
    naming those the environment sets."""
    if not any(var in environ for var in CHILD_THREAD_VARS):
        return "1 OpenMP, MKL and OpenBLAS thread per process (mea run's default)"
    pools = ", ".join(f"{var} {environ[var]} (environment)" if var in environ else f"{var} 1"
                      for var in CHILD_THREAD_VARS)  # fmt: skip
    return f"{pools} per process"


def log_plan(cfg: RunConfig, specs: Sequence[ChildSpec], environ: Mapping[str, str]) -> None:
    """The run's plan, before anything starts: every instance with what it is given, the cores this
    machine lends the run, and each process's thread pools (threads of this process: --in-process)."""
    threads = "one process, a thread per instance" if cfg.in_process else child_threads(environ)
    log.info("plan", extra={"instances": describe(specs), "cores": usable_cores(), "threads": threads})


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
    one_thread_per_child(os.environ)

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


@dataclasses.dataclass(frozen=True)
class Prepared:
    """A run checked and planned, nothing written yet: its settings (a resume's read back), its run
    directory, the instances to start, config.json's history of resumes, and, for a resume with
    nothing left to do, why (``finished``)."""

    cfg: RunConfig
    run_dir: Path
    specs: list[ChildSpec]
    missing: list[str]
    history: tuple[dict, ...] = ()
    finished: str = ""


def _check_run_dir(run_dir: Path, fresh: bool) -> None:
    """ValueError naming --run-dir unless the run's files can go there: a directory or a path to one
    (no file on the way), and, for a fresh run, no run there already."""
    for p in (run_dir, *run_dir.parents):
        if not p.exists():
            continue
        if not p.is_dir():
            raise ValueError(f"--run-dir {run_dir}: {p} is a file, not a directory")
        if not os.access(p, os.W_OK | os.X_OK):
            raise ValueError(f"--run-dir {run_dir}: {p} is not writable")
        break
    if fresh and (run_dir / "config.json").exists():
        raise ValueError(f"--run-dir {run_dir} holds a run already: continue it with --resume {run_dir}, "
                         "or give another directory")  # fmt: skip


def finished(cfg: RunConfig, run_dir: Path) -> str:
    """Why a resumed run has nothing left to do: its learner reached the budget (``env_steps``) in an
    earlier sitting and the budget was evaluated (or the run has no evaluator); "" otherwise."""
    if not cfg.env_steps:
        return ""
    reached = reached_env_steps(run_dir)
    at_budget = [r for r in read_run_history(run_dir) if _int(r.get("env_steps")) >= cfg.env_steps]
    if reached < cfg.env_steps or not (at_budget or "evaluator" not in cfg.services):
        return ""
    evaluated = "" if not at_budget else f", evaluated at {_int(at_budget[-1]['env_steps']):,}"
    return (f"{run_dir} is finished: {reached:,} env steps of its {cfg.env_steps:,}-step budget{evaluated}. "
            f"Nothing to do; give a larger --env-steps to train on.")  # fmt: skip


def _int(v: object) -> int:
    return v if isinstance(v, int) and not isinstance(v, bool) else -1


def prepare(cfg: RunConfig, given: Collection[str] = ()) -> Prepared:
    """Everything `mea run` checks before it starts anything, writing nothing: the resumed settings
    (``given``: the run settings named on the command line), the run directory and every service's
    config. ValueError, one line naming the option, on bad input."""
    if cfg.in_process and cfg.extra_services:
        raise ValueError("--extra-services start their own processes; not with --in-process")
    history: tuple[dict, ...] = ()
    if cfg.resume is not None:
        resumed = read_resume(cfg, given)
        cfg, history = resumed.config, resumed.history
    run_dir = cfg.run_dir or Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{cfg.task}-{cfg.variant}"
    _check_run_dir(run_dir, fresh=cfg.resume is None)
    cfg = dataclasses.replace(cfg, run_dir=run_dir)
    check_tracking(cfg)
    try:  # before anything is written: a clone that does not fit the learner stops the run here
        check_init_actor(cfg)
    except ValueError as exc:
        raise ValueError(f"--init-actor: {exc}") from None
    specs, missing = child_specs(cfg, run_dir)
    done = finished(cfg, run_dir) if cfg.resume is not None else ""
    return Prepared(cfg, run_dir, specs, missing, history, done)


def _check_metrics_ports(cfg: RunConfig, specs: list[ChildSpec]) -> None:
    """ValueError naming the first /metrics port of the run that is taken on ``metrics_addr`` (a
    second run on this host with the same base), before anything starts: else its services would
    exit and restart until the supervisor gives up."""
    ports = [("the launcher", cfg.metrics_port)] + [
        (s.instance, s.config.service.metrics_port) for s in specs if hasattr(s.config, "service")
    ]
    for who, port in ports:
        if not port:
            continue
        with socket.socket() as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the HTTP server binds
            try:
                probe.bind((cfg.metrics_addr, port))
            except OSError as exc:
                raise ValueError(
                    f"--metrics-port {cfg.metrics_port}: port {port} ({who}'s /metrics) on {cfg.metrics_addr} is "
                    f"unavailable ({exc.strerror}; another run on this host?): give this run another base, "
                    "e.g. --metrics-port 9200, or 0 for none"
                ) from None


def _zenoh_reason(exc: Exception) -> str:
    """Zenoh's error without the Rust source locations it carries (one readable line)."""
    text = str(exc)
    os_error = re.search(r"([A-Za-z][^:\[\]]*\(os error \d+\))", text)
    if os_error:
        return os_error.group(1).strip()
    text = re.sub(r"\s+at /\S+?\.rs:\d+\.?", "", text)
    return " ".join(text.split())[:300]


def run(cfg: RunConfig | Prepared, given: Collection[str] = ()) -> int:
    """Run the stack until the budget, the duration, a failure or a signal stops it."""
    p = cfg if isinstance(cfg, Prepared) else prepare(cfg, given)
    cfg, run_dir, specs = p.cfg, p.run_dir, p.specs
    if cfg.in_process:
        logs.setup_in_process(cfg.log_format, "INFO")
    else:
        logs.setup("launcher", "launcher", cfg.log_format, "INFO")
    if cfg.resume is not None:
        log.info("resuming", extra={"run_dir": str(run_dir), "resumes": cfg.resumes,
                                    "changed": json.dumps(p.history[-1]["changed"])})  # fmt: skip
    try:  # before anything is written: a taken /metrics or --listen port leaves no run directory
        _check_metrics_ports(cfg, specs)
    except ValueError as exc:
        config.refuse("mea run", str(exc))
    try:
        router = _router(cfg)
    except Exception as exc:  # noqa: BLE001 - zenoh raises ZError; turn it into a clear message
        config.refuse(
            "mea run", f"--listen {cfg.listen}: cannot start the Zenoh router there: {_zenoh_reason(exc)}"
        )
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        saved = {
            **config.to_jsonable(cfg),
            "history": list(p.history),
            "depth_image_revision": DEPTH_IMAGE_REVISION,
        }
        config.save(saved, run_dir / "config.json")
        specs = secure(specs, cfg, run_dir)  # --zenoh-config: the services join with its client config
        _save_plan(specs, run_dir)
    except BaseException:
        router.close()
        raise
    if p.missing:
        log.warning("services not in this build are skipped", extra={"missing": ",".join(p.missing)})
    shutdown = Shutdown()
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
    log_plan(cfg, specs, os.environ)  # before _starter gives the children their thread defaults
    start = _starter(cfg, router, shutdown)
    summary: dict = {}
    tracking = None
    try:
        tracking = Tracking(cfg, run_dir, [s.instance for s in specs])  # RUN_DIR/tb; W&B with --track
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
        if recorder is not None:
            recorder.close()
        summary = board.save_summary(run_dir / SUMMARY, recorder.written if recorder else None, cfg.resumes)
        board.close()
        router.close()
        render_curves(run_dir)
        metrics.close()
        if tracking is not None:
            tracking.close()
    print(end_of_run(run_dir, summary, shutdown.reason, authenticated=cfg.authenticate), flush=True)
    return 1 if failed else 0


def given_fields(argv: Sequence[str]) -> set[str]:
    """The RunConfig fields named on a command line (``--env-steps 5``, ``--no-record``, ``--x=1``)."""
    fields = {f.name for f in dataclasses.fields(RunConfig)}
    out = set()
    for token in argv:
        if not token.startswith("--"):
            continue
        name = token[2:].partition("=")[0].replace("-", "_")
        if name not in fields and name.startswith("no_"):
            name = name[3:]
        if name in fields:
            out.add(name)
    return out


def main(argv: Sequence[str]) -> int:
    cfg = config.parse(RunConfig, PRESETS, argv, "mea run", RunConfig.__doc__ or "")
    try:
        prepared = prepare(cfg, given_fields(argv))
    except ValueError as exc:
        config.refuse("mea run", str(exc))
    if prepared.finished:
        print(f"mea run: {prepared.finished}")
        return 0
    return run(prepared)
