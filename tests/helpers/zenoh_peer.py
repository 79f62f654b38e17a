"""Child-process entry points and process handling for the Zenoh end-to-end tests.

Children are started with ``multiprocessing.get_context("spawn")`` only and open their own Zenoh
session inside the child. They report to the parent as ``(tag, payload)`` tuples on a
multiprocessing Queue (an exception is reported as ``("error", traceback)`` and exits with code
1), and every wait inside a child is bounded so that nothing outlives a failed test for long.
The :class:`Child` context manager always kills and joins its process.

Readiness protocol used by the entry points: a side declares its subscriptions and queryables
first and its liveliness token (service ``test``) last, so once the other side sees the token,
it also knows those declarations.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import queue
import signal
import sys
import time
import traceback
from collections.abc import Callable
from typing import Any, Literal

from proto.topics import EPISODES_RAW, WEIGHTS_ANNOUNCE, WEIGHTS_LATEST
from proto.weights import tensors_digest
from services.common.bus.base import AliveWatch, Bus, Delivery
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from tests.helpers import build_episode, build_weights

CTX = mp.get_context("spawn")
SERVICE = "test"
"""Liveliness service kind used by test processes."""
STEP_TIMEOUT = 15.0
"""Bound of every single wait inside a child."""
MAX_LIFETIME = 120.0
"""A child waiting for its stop signal gives up after this long."""

Mode = Literal["peer", "client"]


# ------------------------------------------------------------------------------------------------
# configuration
# ------------------------------------------------------------------------------------------------


def endpoint_for(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def router_config(endpoint: str, namespace: str = "default") -> ZenohConfig:
    """A router listening on ``endpoint`` only (no outgoing connections, no multicast)."""
    return ZenohConfig(mode="router", listen=(endpoint,), connect=(), namespace=namespace)


def peer_config(endpoint: str, mode: Mode = "peer", namespace: str = "default") -> ZenohConfig:
    """A peer or client connecting to the router at ``endpoint`` (peers listen on 127.0.0.1:0)."""
    return ZenohConfig(mode=mode, connect=(endpoint,), namespace=namespace)


# ------------------------------------------------------------------------------------------------
# weights helpers shared by both sides of the exchange
# ------------------------------------------------------------------------------------------------


def weights_handler(payload: bytes, version: int) -> Callable[[dict[str, str]], bytes | None]:
    """Queryable handler serving a pre-encoded blob unless ``min_version`` asks for a newer one."""

    def handler(params: dict[str, str]) -> bytes | None:
        try:
            wanted = int(params.get("min_version", "0"))
        except ValueError:
            return None
        return payload if wanted <= version else None

    return handler


def fetch_if_newer(bus: Bus, announcement: Delivery, have_version: int, timeout: float) -> dict[str, Any]:
    """What a weights consumer does on an announcement; returns a plain, picklable report.

    If the announced version is newer than ``have_version``: query the announcing source with
    ``min_version=<announced>`` and check the blob against the announcement, then ask again with
    ``min_version=<announced + 1>``, which must be answered by nothing.
    """
    ann = announcement.message
    source = announcement.parts["source"]
    report: dict[str, Any] = {
        "source": source,
        "ann_version": ann.version,
        "ann_digest": ann.digest,
        "ann_byte_size": ann.byte_size,
        "newer": ann.version > have_version,
    }
    if not report["newer"]:
        return report
    t0 = time.monotonic()
    reply = bus.query(WEIGHTS_LATEST, {"min_version": str(ann.version)}, timeout=timeout, source=source)
    report["fetch_s"] = time.monotonic() - t0
    if reply is None:
        report["blob"] = None
    else:
        blob = reply.message
        report["blob"] = {
            "key": reply.key,
            "size": reply.size,
            "version": blob.version,
            "digest": blob.digest,
            "recomputed_digest": tensors_digest(blob.tensors),
            "run_id": blob.run_id,
        }
    too_new = bus.query(WEIGHTS_LATEST, {"min_version": str(ann.version + 1)}, timeout=timeout, source=source)
    report["too_new_reply"] = None if too_new is None else too_new.message.version
    return report


# ------------------------------------------------------------------------------------------------
# child side
# ------------------------------------------------------------------------------------------------


def _entry(target: Callable[..., None], results: Any, stop: Any, args: tuple) -> None:
    try:
        target(results, stop, *args)
    except BaseException:  # noqa: BLE001 - report everything to the parent, then fail
        results.put(("error", traceback.format_exc()))
        sys.exit(1)


def _wait_token(watch: AliveWatch, instance: str, timeout: float = STEP_TIMEOUT) -> None:
    if not watch.wait_for(lambda alive: (SERVICE, instance) in alive, timeout):
        raise TimeoutError(f"liveliness token of {instance!r} not seen within {timeout} s")


def _wait_stop(stop) -> None:
    """Block until the parent asks us to stop (bounded by MAX_LIFETIME)."""
    with contextlib.suppress(queue.Empty):
        stop.get(timeout=MAX_LIFETIME)


def _recv(sub, what: str, timeout: float = STEP_TIMEOUT) -> Delivery:
    d = sub.recv(timeout=timeout)
    if d is None:
        raise TimeoutError(f"no {what} within {timeout} s")
    return d


def episode_echo(
    results, stop, endpoint: str, mode: Mode, namespace: str, me: str, other: str, seed: int, T: int
) -> None:
    """Receive one episode from ``other`` and report it; then publish our own (seeded) episode."""
    with ZenohBus(peer_config(endpoint, mode, namespace)) as bus:
        sub = bus.subscribe(EPISODES_RAW, source=other)
        _wait_token(bus.watch_alive(SERVICE), other)
        bus.declare_alive(SERVICE, me)
        d = _recv(sub, f"episode from {other}")
        results.put(("episode", (d.key, d.parts, d.size, d.message)))
        ep = build_episode(T=T, seed=seed, with_images=True, actor_id=me)
        results.put(("published", bus.publish(EPISODES_RAW, ep, source=me)))
        _wait_stop(stop)


def weights_exchange(
    results,
    stop,
    endpoint: str,
    mode: Mode,
    namespace: str,
    me: str,
    other: str,
    version: int,
    nbytes: int,
    seed: int,
) -> None:
    """Serve our blob; fetch ``other``'s announced blob (we hold none of its versions); announce ours."""
    blob = build_weights(version, nbytes=nbytes, seed=seed, run_id=f"run-{me}")
    payload = blob.encode()
    with ZenohBus(peer_config(endpoint, mode, namespace)) as bus:
        bus.serve(WEIGHTS_LATEST, weights_handler(payload, version), source=me)
        anns = bus.subscribe(WEIGHTS_ANNOUNCE, source=other)
        _wait_token(bus.watch_alive(SERVICE), other)
        bus.declare_alive(SERVICE, me)
        d = _recv(anns, f"weights announcement from {other}")
        results.put(("fetched", fetch_if_newer(bus, d, have_version=0, timeout=STEP_TIMEOUT)))
        bus.publish(WEIGHTS_ANNOUNCE, blob.announcement(len(payload)), source=me)
        results.put(("announced", {"version": version, "digest": blob.digest, "byte_size": len(payload)}))
        _wait_stop(stop)


def hold_token(results, stop, endpoint: str, mode: Mode, namespace: str, me: str) -> None:
    """Hold a liveliness token until stopped (or killed)."""
    with ZenohBus(peer_config(endpoint, mode, namespace)) as bus:
        bus.declare_alive(SERVICE, me)
        results.put(("ready", os.getpid()))
        _wait_stop(stop)


# ------------------------------------------------------------------------------------------------
# parent side
# ------------------------------------------------------------------------------------------------


class ChildError(AssertionError):
    """The child reported an exception or exited early."""


class Child:
    """One spawned child running ``target(results, stop, *args)``; always killed and joined on exit."""

    def __init__(self, target: Callable[..., None], *args: Any, name: str | None = None) -> None:
        self.results = CTX.Queue()
        # a Queue, not an Event: setting an Event blocks forever once a waiter was SIGKILLed
        self.stop = CTX.Queue()
        self._stopped = False
        self.proc = CTX.Process(
            target=_entry, args=(target, self.results, self.stop, args), name=name, daemon=True
        )
        self._pending: list[tuple[str, Any]] = []

    def __enter__(self) -> Child:
        self.proc.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def pid(self) -> int:
        assert self.proc.pid is not None
        return self.proc.pid

    def _check_alive(self) -> None:
        if not self.proc.is_alive():
            self._poll(0.5)  # a last report (e.g. the traceback) may still be in flight
            for tag, payload in self._pending:
                if tag == "error":
                    raise ChildError(f"child failed:\n{payload}")
            raise ChildError(f"child exited with code {self.proc.exitcode}")

    def _poll(self, timeout: float) -> None:
        try:
            item = self.results.get(timeout=timeout)
        except queue.Empty:
            return
        if item[0] == "error":
            raise ChildError(f"child failed:\n{item[1]}")
        self._pending.append(item)

    def expect(self, tag: str, timeout: float) -> Any:
        """Wait (bounded) for the child's next report tagged ``tag`` and return its payload."""
        deadline = time.monotonic() + timeout
        while True:
            for i, (t, payload) in enumerate(self._pending):
                if t == tag:
                    del self._pending[i]
                    return payload
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"child sent no {tag!r} within {timeout} s (got {self._pending!r})")
            self._poll(min(0.25, remaining))
            if not any(t == tag for t, _ in self._pending):
                self._check_alive()

    def wait_token(self, watch: AliveWatch, instance: str, timeout: float) -> float:
        """Wait (bounded) until ``watch`` sees the child's token; returns the seconds waited."""
        t0 = time.monotonic()
        deadline = t0 + timeout
        while not watch.wait_for(
            lambda alive: (SERVICE, instance) in alive, min(0.25, deadline - time.monotonic())
        ):
            if time.monotonic() >= deadline:
                raise TimeoutError(f"liveliness token of {instance!r} not seen within {timeout} s")
            self._poll(0.0)
            self._check_alive()
        return time.monotonic() - t0

    def finish(self, timeout: float = 10.0) -> int | None:
        """Ask the child to stop, wait for it (bounded) and return its exit code."""
        self._signal_stop()
        self.proc.join(timeout)
        if self.proc.is_alive():
            raise TimeoutError(f"child did not exit within {timeout} s")
        return self.proc.exitcode

    def _signal_stop(self) -> None:
        if not self._stopped:
            self._stopped = True
            self.stop.put(None)

    def kill(self) -> None:
        """SIGKILL the child and reap it."""
        if self.proc.is_alive():
            os.kill(self.pid, signal.SIGKILL)
        self.proc.join(10.0)

    def close(self) -> None:
        try:
            if self.proc.pid is not None:
                self._signal_stop()
                self.proc.join(5.0)
                if self.proc.is_alive():
                    self.kill()
        finally:
            for q in (self.results, self.stop):
                q.cancel_join_thread()
                q.close()
