"""Process runtime shared by every service: graceful shutdown, parent-death watch, and the
service context (bus, liveliness token, /metrics, heartbeats) wired around a service's loop."""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from proto.control import Heartbeat
from proto.topics import STATUS
from services.common import logs, run_key
from services.common.bus.base import Bus, Credentials
from services.common.bus.zenoh_bus import ZenohBus
from services.common.config import ServiceConfig
from services.common.metrics import DEFAULT_PORTS, ServiceMetrics

log = logging.getLogger(__name__)
PR_SET_PDEATHSIG = 1
TRIM_SECONDS = 60.0
"""How often a service gives freed heap pages back to the OS (``trim_heap``)."""


_scope = threading.local()


@contextlib.contextmanager
def stopped_by(parent: Shutdown) -> Iterator[None]:
    """Every ``Shutdown`` created in this thread inside the block is set when ``parent`` is: the
    in-process topology stops its service threads with the launcher's one Shutdown."""
    previous = getattr(_scope, "parent", None)
    _scope.parent = parent
    try:
        yield
    finally:
        _scope.parent = previous


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op threads set to ``n`` inside the block (0: left as they are), the caller's
    setting back after it (services run in-process in tests and benches)."""
    import torch  # only the services that run a policy pay for the import

    threads = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


class Shutdown:
    """Set on SIGTERM/SIGINT (or by the owner, or by the parent given by ``stopped_by``); loops poll
    ``is_set`` or ``wait``."""

    def __init__(self, install_signals: bool = True) -> None:
        self._event = threading.Event()
        self._children: list[Shutdown] = []
        self._lock = threading.Lock()
        self.reason = ""
        if install_signals and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, self._on_signal)
            signal.signal(signal.SIGINT, self._on_signal)
        parent = getattr(_scope, "parent", None)
        if parent is not None:
            parent._adopt(self)

    def _adopt(self, child: Shutdown) -> None:
        with self._lock:
            self._children.append(child)
        if self.is_set():
            child.set(self.reason)

    def _on_signal(self, signum: int, _frame: object) -> None:
        self.set(signal.Signals(signum).name)

    def set(self, reason: str = "requested") -> None:
        if not self._event.is_set():
            self.reason = reason
            self._event.set()
        with self._lock:
            children = list(self._children)
        for child in children:
            child.set(reason)

    def is_set(self) -> bool:
        return self._event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self._event.wait(timeout)


_libc = None


def trim_heap() -> None:
    """Give the C heap's free pages back to the OS (glibc ``malloc_trim``; a no-op elsewhere).

    Long-running services allocate and free many episode-sized arrays; after a burst glibc keeps the
    freed arenas, which shows as RSS that steps up and never comes down (the soak benchmark saw
    +150 MB in the learner). Trimming now and then keeps RSS at what is in use."""
    global _libc
    try:
        _libc = _libc or ctypes.CDLL("libc.so.6")
        _libc.malloc_trim(0)
    except (OSError, AttributeError):
        pass


def die_with_parent() -> None:
    """Ask the kernel to SIGTERM this process when its parent dies (Linux), and watch getppid as
    a fallback, so a killed launcher leaves no orphans."""
    parent = os.getppid()
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass

    def watch() -> None:
        while True:
            if os.getppid() != parent:
                os.kill(os.getpid(), signal.SIGTERM)
                return
            time.sleep(0.5)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def subscribing_bus_factory(
    factory: Callable[[ServiceConfig], Bus] | None, declare: Callable[[Bus], None]
) -> Callable[[ServiceConfig], Bus]:
    """A bus factory (Zenoh unless ``factory`` is given) that runs ``declare(bus)`` (the service's
    subscriptions) before ServiceContext declares the liveliness token: once a peer sees the token,
    the subscriptions exist, so nothing published after that is missed."""

    def make(c: ServiceConfig) -> Bus:
        bus = factory(c) if factory is not None else ZenohBus(c.zenoh)
        declare(bus)
        return bus

    return make


@dataclass
class ServiceContext:
    """Everything a service shell needs around its core loop. Use as a context manager."""

    service: str
    cfg: ServiceConfig
    bus_factory: Callable[[ServiceConfig], Bus] = field(default=lambda c: ZenohBus(c.zenoh))
    counters: Callable[[], dict[str, float]] = field(default=dict)
    index: int = 0

    def __post_init__(self) -> None:
        self.instance = self.cfg.instance_id or f"{self.service}-{os.getpid()}"
        self.shutdown = Shutdown()
        self.policy_version = -1
        self.state = "starting"
        self.detail = ""
        self.started_at = time.time()
        self.metrics = ServiceMetrics(self.service, self.instance, self.cfg.zenoh.namespace)
        self.bus: Bus | None = None
        self._token = None
        self._hb_thread: threading.Thread | None = None

    def __enter__(self) -> ServiceContext:
        logs.setup(self.service, self.instance, self.cfg.log_format, self.cfg.log_level)
        try:
            key = run_key.load(self.cfg.run_key_file) if self.cfg.run_key_file else None
        except run_key.RunKeyError as exc:
            raise SystemExit(f"{self.service}: {exc}") from None
        port = self.cfg.metrics_port
        if port < 0:
            port = DEFAULT_PORTS.get(self.service, 0) + (self.index if self.service == "actor" else 0)
        try:
            self.metrics_port = self.metrics.serve(self.cfg.metrics_addr, port)
        except OSError as exc:
            raise SystemExit(
                f"{self.service}: cannot serve /metrics on {self.cfg.metrics_addr}:{port}: {exc}"
            ) from None
        self.bus = self.bus_factory(self.cfg)
        self.bus.limits, self.bus.caps = self.cfg.limits, self.cfg.caps()
        if key is not None:
            self.bus.authenticate(Credentials(key, self.service, self.instance))
        else:
            log.warning("bus not authenticated: any process on the Zenoh network can write to it")
        self.metrics.watch_bus(self.bus)
        self._token = self.bus.declare_alive(self.service, self.instance)
        self._hb_thread = threading.Thread(target=self._heartbeats, name="heartbeat", daemon=True)
        self._hb_thread.start()
        log.info("started", extra={"metrics_port": self.metrics_port, "namespace": self.cfg.zenoh.namespace,
                                   "run_key": run_key.describe(key) if key is not None else None})  # fmt: skip
        self.state = "running"
        return self

    def heartbeat(self) -> Heartbeat:
        return Heartbeat(
            service=self.service,
            instance_id=self.instance,
            pid=os.getpid(),
            state=self.state,
            started_at=self.started_at,
            created_at=time.time(),
            policy_version=self.policy_version,
            counters={k: float(v) for k, v in self.counters().items()},
            detail=self.detail[:512],
        )

    def _heartbeats(self) -> None:
        trimmed = time.monotonic()
        while not self.shutdown.wait(self.cfg.heartbeat_seconds):
            if time.monotonic() - trimmed > TRIM_SECONDS:
                trim_heap()
                trimmed = time.monotonic()
            try:
                self.metrics.policy_version.set(self.policy_version)
                self.bus.publish(STATUS, self.heartbeat(), service=self.service, instance=self.instance)
            except Exception:  # noqa: BLE001 - telemetry must never take the service down
                log.exception("heartbeat failed")

    def __exit__(self, *exc: object) -> None:
        self.state = "stopping"
        self.shutdown.set("exit")
        if self._hb_thread is not None:
            self._hb_thread.join(timeout=2.0)
        try:
            if self.bus is not None:
                self.bus.publish(STATUS, self.heartbeat(), service=self.service, instance=self.instance)
                self.bus.close()
        finally:
            self.metrics.close()
            log.info("stopped", extra={"reason": self.shutdown.reason})
