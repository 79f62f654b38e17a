"""Config presets, metrics exposition, structured logs and the service context (in-process bus)."""

from __future__ import annotations

import dataclasses
import json
import logging
import urllib.request

import pytest

from proto.topics import STATUS
from services.common import config, logs
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig
from services.common.runtime import ServiceContext

pytestmark = pytest.mark.unit


@dataclasses.dataclass(frozen=True)
class _Cfg:
    """A config for tests."""

    lr: float = 3e-4
    """Learning rate."""
    batch: int = 32
    """Batch size."""
    service: ServiceConfig = ServiceConfig()
    """Common service options."""


PRESETS = {"paper": _Cfg(), "cpu-small": _Cfg(lr=1e-3, batch=4)}


def test_preset_is_applied_then_flags_override_it():
    cfg = config.parse(_Cfg, PRESETS, ["--preset", "cpu-small", "--lr", "0.5"], "t", "d")
    assert cfg == _Cfg(lr=0.5, batch=4)
    assert config.parse(_Cfg, PRESETS, [], "t", "d") == PRESETS["paper"]


def test_nested_service_flags_parse():
    cfg = config.parse(
        _Cfg,
        PRESETS,
        ["--service.zenoh.connect", "tcp/10.1.2.3:7447", "--service.metrics-port", "0"],
        "t",
        "d",
    )
    assert cfg.service.zenoh.connect == ("tcp/10.1.2.3:7447",)
    assert cfg.service.metrics_port == 0


def test_bad_config_is_refused_with_a_clear_error():
    with pytest.raises(ValueError, match="log_format"):
        ServiceConfig(log_format="xml")


def test_saved_config_is_json(tmp_path):
    config.save(PRESETS["cpu-small"], tmp_path / "c.json")
    data = json.loads((tmp_path / "c.json").read_text())
    assert data["batch"] == 4 and data["service"]["zenoh"]["mode"] == "peer"


def test_json_logs_carry_identity_and_fields(capsys):
    logs.setup("learner", "learner-0", "json", "INFO")
    logging.getLogger("x").info("hello", extra={"updates": 7})
    line = capsys.readouterr().err.strip().splitlines()[-1]
    rec = json.loads(line)
    assert rec["service"] == "learner" and rec["instance"] == "learner-0"
    assert rec["msg"] == "hello" and rec["updates"] == 7


@pytest.mark.timeout(30)
def test_service_context_heartbeats_liveliness_and_metrics():
    hub = Hub()
    observer = InProcBus(hub)
    watch = observer.watch_alive()
    beats = observer.subscribe(STATUS)
    ticks = {"episodes": 3.0}
    cfg = ServiceConfig(instance_id="learner-0", metrics_port=0, heartbeat_seconds=0.05, log_format="text")
    ctx = ServiceContext("learner", cfg, bus_factory=lambda _c: InProcBus(hub), counters=lambda: ticks)
    with ctx:
        # a real /metrics endpoint on an ephemeral port
        port = ctx.metrics.serve("127.0.0.1", _free_port())
        assert ("learner", "learner-0") in watch.alive()
        hb = beats.recv(timeout=5.0)
        assert hb is not None and hb.message.counters == {"episodes": 3.0}
        assert hb.message.state == "running"
        ctx.bus.publish(STATUS, b"\x93garbage", service="learner", instance="x")
        beats.drain()  # the garbage payload is rejected, counted, and skipped
        body = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    assert ("learner", "learner-0") not in watch.alive()
    assert 'mea_bus_published_messages_total{topic="status"}' in body
    assert (
        "mea_policy_version" in body
        and 'service_instance="learner-0"' in body
        and "mea_service_info{" in body
        and 'namespace="default"' in body  # dashboards filter by it
        and 'instance="learner-0"' not in body.replace("service_instance", "")
    )
    assert observer.stats.bad["status"] == 1


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_shutdowns_made_under_stopped_by_follow_the_parent_and_only_downwards():
    import threading

    from services.common.runtime import Shutdown, stopped_by

    parent = Shutdown(install_signals=False)
    made: list[Shutdown] = []

    def service() -> None:
        with stopped_by(parent):
            made.extend([Shutdown(), Shutdown()])
        made.append(Shutdown())  # after the block: on its own

    t = threading.Thread(target=service)
    t.start()
    t.join()
    first, second, outside = made
    first.set("own")  # a service stopping itself stops neither the launcher nor its siblings
    assert not parent.is_set() and not second.is_set()
    parent.set("budget")
    assert second.is_set() and second.reason == "budget" and first.reason == "own"
    assert not outside.is_set()
    with stopped_by(parent):  # one made after the parent stopped starts stopped
        late = Shutdown(install_signals=False)
    assert late.is_set() and late.reason == "budget"


def test_trim_heap_gives_freed_pages_back():
    """After freeing many small arrays (kept by glibc's arenas), a trim lowers RSS."""
    import os

    import numpy as np

    from mea_tools.bench.soak import rss_bytes
    from services.common.runtime import trim_heap

    trim_heap()
    base = rss_bytes(os.getpid())
    blocks = [np.ones(20_000, np.uint8) for _ in range(20_000)]  # 400 MB in sub-threshold chunks
    blocks = blocks[-1:]  # free all but the last: the arenas stay mapped
    before = rss_bytes(os.getpid())
    trim_heap()
    after = rss_bytes(os.getpid())
    assert before - base > 200_000_000, (base, before)
    assert before - after > 200_000_000, (before, after)
    del blocks
