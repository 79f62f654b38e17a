"""The benchmarks' shared harness: percentiles, finite checks, ports and the spawned-child protocol."""

from __future__ import annotations

import math
import queue
import socket

import numpy as np
import pytest

from mea_tools.bench import harness

pytestmark = pytest.mark.unit


def test_percentile_is_numpys_in_float64() -> None:
    values = [3.0, 1.0, 2.0, 10.0]
    assert harness.percentile(values, 50) == 2.5
    assert harness.percentile(values, 100) == 10.0
    samples = np.random.default_rng(0).random(101).astype(np.float32)
    got = harness.percentile(samples, 99)
    assert type(got) is float
    assert got == float(np.percentile(samples.astype(np.float64), 99))


def test_finite_passes_numbers_and_refuses_nan_and_inf() -> None:
    assert harness.finite(np.float32(1.5)) == 1.5 and type(harness.finite(2)) is float
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(RuntimeError, match="non-finite"):
            harness.finite(bad)


def test_free_port_can_be_bound() -> None:
    port = harness.free_port()
    assert 0 < port < 65536
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", port))


class FakeBus:
    def __init__(self) -> None:
        self.closed = False

    def close(self) -> None:
        self.closed = True


def test_run_with_bus_reports_a_failure_and_closes_the_bus(monkeypatch: pytest.MonkeyPatch) -> None:
    bus = FakeBus()
    monkeypatch.setattr(harness, "client_bus", lambda endpoint: bus)
    results: queue.Queue = queue.Queue()
    seen = []

    def body(got: FakeBus) -> None:
        seen.append(got)
        raise ValueError("boom")

    harness.run_with_bus("tcp/127.0.0.1:1", results, body)
    assert seen == [bus] and bus.closed
    assert results.get_nowait() == ("error", "ValueError('boom')")
    assert results.empty()


def test_run_with_bus_reports_nothing_when_the_body_succeeds(monkeypatch: pytest.MonkeyPatch) -> None:
    bus = FakeBus()
    monkeypatch.setattr(harness, "client_bus", lambda endpoint: bus)
    results: queue.Queue = queue.Queue()
    harness.run_with_bus("tcp/127.0.0.1:1", results, lambda got: results.put(("done", got is bus)))
    assert bus.closed
    assert results.get_nowait() == ("done", True) and results.empty()


def test_run_with_bus_reports_a_bus_that_cannot_open(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(endpoint: str) -> FakeBus:
        raise ConnectionError(endpoint)

    def body(bus: FakeBus) -> None:
        raise AssertionError("the body must not run without a bus")

    monkeypatch.setattr(harness, "client_bus", refuse)
    results: queue.Queue = queue.Queue()
    harness.run_with_bus("tcp/127.0.0.1:1", results, body)
    assert results.get_nowait() == ("error", "ConnectionError('tcp/127.0.0.1:1')")
    assert results.empty()


class FakeProc:
    name = "child"
    exitcode = 3

    def __init__(self, alive: bool = True) -> None:
        self.alive = alive

    def is_alive(self) -> bool:
        return self.alive


def test_next_result_returns_reports_and_raises_for_errors_and_dead_children() -> None:
    results: queue.Queue = queue.Queue()
    results.put(("loaded", 1, 10))
    results.put(("error", "RuntimeError('x')"))
    assert harness.next_result(results, FakeProc(), 1.0) == ("loaded", 1, 10)
    with pytest.raises(RuntimeError, match=r"child failed: RuntimeError\('x'\)"):
        harness.next_result(results, FakeProc(), 1.0)
    with pytest.raises(RuntimeError, match=r"child exited \(code 3\) without reporting"):
        harness.next_result(results, FakeProc(alive=False), 1.0)
    with pytest.raises(TimeoutError, match="no report from child"):
        harness.next_result(results, FakeProc(), 0.0)


def test_stop_child_of_nothing_does_nothing() -> None:
    harness.stop_child(None)
