"""Per-topic message caps: a message over its topic's cap is refused (counted) before decoding, and
every cap leaves room for the largest legitimate message of its topic."""

from __future__ import annotations

import time

from proto.control import Heartbeat
from proto.msgpack_wire import pack
from proto.topics import EPISODE_MAX_BYTES, EPISODES_RAW, STATUS, TOPICS
from services.common.bus.inproc import InProcBus
from tests.helpers import build_episode


def beat(detail: str = "") -> Heartbeat:
    return Heartbeat(service="test", instance_id="i-0", pid=1, state="running", started_at=0.0,
                     created_at=time.time(), policy_version=1, counters={"x": 1.0}, detail=detail)  # fmt: skip


def test_a_message_over_its_topics_cap_is_refused_and_counted():
    bus = InProcBus()
    sub = bus.subscribe(STATUS, capacity=4)
    bus.publish(STATUS, pack({"padding": b"\0" * (STATUS.max_bytes + 1)}), service="svc", instance="big")
    assert sub.drain() == [] and bus.stats.bad[STATUS.name] == 1
    bus.publish(STATUS, beat(), service="test", instance="i-0")
    assert [d.message.instance_id for d in sub.drain()] == ["i-0"]
    bus.close()


def test_the_caps_hold_the_largest_legitimate_messages():
    assert {t.name: t.max_bytes for t in TOPICS if t.max_bytes < 1024 * 1024} == {}  # no cap under 1 MiB
    # an 80-step episode with 1,024 points per segment and 84x84 images: well under the episode cap
    ep = build_episode(T=80, P=1024, with_images=True, image_shape=(2, 84, 84))
    size = len(ep.encode())
    assert size < EPISODE_MAX_BYTES / 4, size
    bus = InProcBus()
    sub = bus.subscribe(EPISODES_RAW, capacity=2)
    bus.publish(EPISODES_RAW, ep, source="actor-0")
    assert len(sub.drain()) == 1
    bus.close()
    # a heartbeat with the longest detail it may carry stays far under the control cap
    assert len(beat("x" * 512).encode()) < STATUS.max_bytes / 100


def test_a_configured_cap_replaces_the_topics_and_bad_entries_are_refused():
    import pytest

    from services.common.config import ServiceConfig

    cfg = ServiceConfig(topic_caps=("status=300",))
    bus = InProcBus()
    bus.caps = cfg.caps()
    sub = bus.subscribe(STATUS, capacity=4)
    small, large = beat(), beat(detail="x" * 400)
    assert len(small.encode()) < 300 < len(large.encode()) < STATUS.max_bytes
    bus.publish(STATUS, large, service="test", instance="i-0")
    bus.publish(STATUS, small, service="test", instance="i-1")
    assert [d.parts["instance"] for d in sub.drain()] == [
        "i-1"
    ]  # the large one: under the default cap, over this one
    assert bus.stats.bad[STATUS.name] == 1
    bus.close()
    for bad in ("nope=10", "status", "status=-1", "status=ten"):
        with pytest.raises(ValueError, match="topic_caps"):
            ServiceConfig(topic_caps=(bad,))
