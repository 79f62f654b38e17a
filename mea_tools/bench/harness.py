"""What the benchmarks share: a free port, Zenoh client buses, the spawned-child protocol (readiness by
liveliness token, reports on a queue, shutdown), percentiles, finite checks and host metadata.

A child reports ``(tag, ...)`` tuples on a ``multiprocessing`` queue and ``("error", repr(exc))`` when
it fails (:func:`run_with_bus` does that); the parent reads them with :func:`next_result`, which raises
for a failed, dead or silent child instead of hanging.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import math
import os
import platform
import queue
import socket
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def client_bus(endpoint: str) -> ZenohBus:
    """A Zenoh client session of the router at ``endpoint`` (the deployed topology)."""
    return ZenohBus(ZenohConfig(mode="client", connect=(endpoint,)))


def run_with_bus(endpoint: str, results: Any, body: Callable[[ZenohBus], None]) -> None:
    """In a spawned child: run ``body`` with a client bus of ``endpoint``, closed afterwards. Whatever
    opening the bus or the body raises is put on ``results`` as ``("error", repr(exc))`` for the
    parent to raise (:func:`next_result`), not re-raised here."""
    bus = None
    try:
        bus = client_bus(endpoint)
        body(bus)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises
        results.put(("error", repr(exc)))
    finally:
        if bus is not None:
            bus.close()


def wait_alive(watch: Any, who: tuple[str, str], proc: Any, timeout: float) -> None:
    """Wait for a child's liveliness token, failing fast if the child dies first."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if watch.wait_for(lambda alive: who in alive, timeout=0.5):
            return
        if not proc.is_alive():
            raise RuntimeError(f"{who[0]} process exited (code {proc.exitcode}) before becoming ready")
    raise TimeoutError(f"{who[0]} not alive after {timeout:.0f} s")


def next_result(results: Any, proc: Any, timeout: float) -> Any:
    """Next item a child put on ``results``; raises if the child failed, died or timed out."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            item = results.get(timeout=0.5)
        except queue.Empty:
            if not proc.is_alive():
                raise RuntimeError(f"{proc.name} exited (code {proc.exitcode}) without reporting") from None
            if time.monotonic() > deadline:
                raise TimeoutError(f"no report from {proc.name} after {timeout:.0f} s") from None
            continue
        if isinstance(item, tuple) and item and item[0] == "error":
            raise RuntimeError(f"{proc.name} failed: {item[1]}")
        return item


def stop_child(proc: Any, commands: Any = None) -> None:
    """Stop a child: send ``("stop",)`` on ``commands`` if given, give it 5 s to exit, then
    terminate and at last kill it."""
    if proc is None:
        return
    if commands is not None and proc.is_alive():
        with contextlib.suppress(OSError, ValueError):
            commands.put(("stop",))
    proc.join(timeout=5.0)
    if proc.is_alive():
        proc.terminate()
        proc.join(timeout=3.0)
    if proc.is_alive():
        proc.kill()
        proc.join(timeout=3.0)


def percentile(values: Sequence[float] | np.ndarray, q: float) -> float:
    """The ``q``-th percentile of ``values`` (numpy's linear interpolation, in float64)."""
    return float(np.percentile(np.asarray(values, dtype=np.float64), q))


def finite(x: float) -> float:
    """``x`` as a float; RuntimeError if it is NaN or infinite (a broken measurement)."""
    x = float(x)
    if not math.isfinite(x):
        raise RuntimeError(f"non-finite measurement {x}")
    return x


def host_meta() -> dict[str, Any]:
    """Python, Zenoh and numpy versions, CPU count and machine: what a result was measured on."""
    try:
        zenoh_version = importlib.metadata.version("eclipse-zenoh")
    except importlib.metadata.PackageNotFoundError:
        zenoh_version = "unknown"
    return {
        "python": platform.python_version(),
        "zenoh": zenoh_version,
        "numpy": np.__version__,
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
    }
