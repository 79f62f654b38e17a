"""`mea run --actors 2`: real actor processes publish valid episodes over Zenoh on 127.0.0.1."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from proto.episode import Episode
from proto.topics import EPISODES_RAW
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from tests.helpers import find_free_port, stop_process

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.timeout(180)
def test_two_actors_publish_episodes_that_decode(tmp_path):
    port = find_free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cmd = [
        sys.executable,
        "-m",
        "services.cli",
        "run",
        "--task",
        "block_pick",
        "--actors",
        "2",
        "--demos",
        "1",
        "--services",
        "actor",
        "--listen",
        endpoint,
        "--metrics-port",
        "0",
        "--run-dir",
        str(tmp_path / "run"),
    ]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)  # fmt: skip
    bus = None
    try:
        bus = ZenohBus(ZenohConfig(mode="client", connect=(endpoint,)))
        sub = bus.subscribe(EPISODES_RAW, capacity=64)
        sources, demos = set(), 0
        deadline = time.monotonic() + 150
        while (len(sources) < 2 or demos < 1) and time.monotonic() < deadline:
            d = sub.recv(timeout=1.0)
            if d is None:
                assert proc.poll() is None, proc.stdout.read()
                continue
            ep = d.message
            assert isinstance(ep, Episode) and ep.actor_id == d.parts["source"]
            sources.add(ep.actor_id)
            demos += ep.is_demo
        assert sources == {"actor-0", "actor-1"}, sources
        assert demos >= 1
        assert bus.stats.bad["episodes_raw"] == 0
    finally:
        if bus is not None:
            bus.close()
        stop_process(proc)
    assert proc.returncode == 0
