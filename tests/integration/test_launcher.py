"""`mea run` as a user runs it: separate processes, live status, clean and forced shutdown."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig

pytestmark = [pytest.mark.integration, pytest.mark.slow]
ROOT = Path(__file__).resolve().parents[2]


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _launch(tmp_path: Path, port: int, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [
        sys.executable,
        "-m",
        "services.cli",
        "run",
        "--listen",
        f"tcp/127.0.0.1:{port}",
        "--metrics-port",
        "0",
        "--run-dir",
        str(tmp_path / "run"),
        "--extra-services",
        "tests.helpers.dummy_service:main",
        *extra,
    ]
    return subprocess.Popen(
        cmd,
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie still answers kill(0); treat it as gone
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


def _ends_within(pid: int, timeout: float) -> bool:
    """Whether process ``pid`` is gone within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while _pid_alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    return not _pid_alive(pid)


@pytest.fixture
def launch(tmp_path):
    """``launch(*extra)`` starts `mea run` (``_launch``) on a free port and returns (process, port);
    a launcher still running when the test ends is killed with its process group."""
    procs: list[subprocess.Popen] = []

    def start(*extra: str) -> tuple[subprocess.Popen, int]:
        port = _port()
        procs.append(_launch(tmp_path, port, *extra))
        return procs[-1], port

    yield start
    for proc in procs:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)


def _wait_for_service(port: int, timeout: float = 60.0) -> int:
    """Wait for the dummy service's liveliness token and heartbeat; return its pid."""
    from proto.topics import STATUS

    bus = ZenohBus(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        watch = bus.watch_alive("test")
        assert watch.wait_for(lambda alive: ("test", "extra-0") in alive, timeout), (
            "service never became alive"
        )
        beats = bus.subscribe(STATUS, service="test")
        hb = beats.recv(timeout=10.0)
        assert hb is not None, "no heartbeat"
        return hb.message.pid
    finally:
        bus.close()


@pytest.mark.timeout(120)
def test_sigterm_stops_every_process_within_seconds(tmp_path, launch):
    proc, port = launch()
    child = _wait_for_service(port)
    assert _pid_alive(child)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    rc = proc.wait(timeout=15)
    elapsed = time.monotonic() - t0
    assert rc == 0, proc.stdout.read()
    assert elapsed < 8.0, f"shutdown took {elapsed:.1f} s"
    assert _ends_within(child, 5), "service process outlived the launcher"
    assert (tmp_path / "run" / "config.json").exists()


@pytest.mark.timeout(120)
def test_sigkilled_launcher_leaves_no_orphans(launch):
    proc, port = launch()
    child = _wait_for_service(port)
    proc.kill()
    proc.wait(timeout=10)
    assert _ends_within(child, 10), "orphaned service survived a SIGKILLed launcher"


@pytest.mark.timeout(120)
def test_a_failed_service_is_reported_and_stops_the_stack(launch):
    proc, port = launch("--restart-limit", "0")
    child = _wait_for_service(port)
    os.kill(child, signal.SIGKILL)
    rc = proc.wait(timeout=20)
    out = proc.stdout.read()
    assert rc == 1, out
    assert "service exited" in out and "exitcode=-9" in out, out


def _wait_for_new_pid(port: int, old: int, timeout: float = 60.0) -> int:
    """The pid of the dummy service's next heartbeat from a process other than ``old``."""
    from proto.topics import STATUS

    bus = ZenohBus(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        beats = bus.subscribe(STATUS, service="test")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            d = beats.recv(timeout=1.0)
            if d is not None and d.message.pid != old:
                return d.message.pid
        raise AssertionError("the service was not restarted")
    finally:
        bus.close()


@pytest.mark.timeout(180)
def test_a_killed_service_is_restarted_and_a_service_that_keeps_dying_stops_the_stack(tmp_path, launch):
    proc, port = launch("--restart-limit", "1", "--restart-window-seconds", "300")
    first = _wait_for_service(port)
    os.kill(first, signal.SIGKILL)
    second = _wait_for_new_pid(port, first)  # restarted after the 1 s backoff
    assert _pid_alive(second) and proc.poll() is None
    os.kill(second, signal.SIGKILL)  # the second exit within the window: give up, stop the stack
    rc = proc.wait(timeout=30)
    out = proc.stdout.read()
    assert rc == 1, out
    assert "restarting" in out and "not restarted" in out, out
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["instances"]["extra-0"]["restarts"] == 1
    assert summary["instances"]["extra-0"]["exitcode"] == -signal.SIGKILL
