"""Latest-value topics (gates, weights announcements, heartbeats) keep only the newest message per
sender and never make the transport wait; episodes keep every message and push back."""

from __future__ import annotations

import threading
import time

import numpy as np

from proto.control import ReplayGate
from proto.topics import EPISODES_RAW, REPLAY_GATE, STATUS, TOPICS, WEIGHTS_ANNOUNCE
from proto.weights import WeightsBlob
from services.common.bus.inproc import InProcBus
from services.common.replay_gate import MAX_CLOCK_SKEW, GateTracker


def gate(k: int, learner: str = "learner-0", created_at: float | None = None) -> ReplayGate:
    return ReplayGate(learner_id=learner, run_id="run-a", inserted_steps=k, allowed_steps=k + 10, updates=k,
                      policy_version=k, replay_transitions=k,
                      created_at=time.time() if created_at is None else created_at)  # fmt: skip


def test_only_gates_announcements_acks_heartbeats_and_estops_are_latest_value_topics():
    latest = {t.name for t in TOPICS if t.qos.latest_only}
    assert latest == {REPLAY_GATE.name, WEIGHTS_ANNOUNCE.name, STATUS.name, "episode_acks", "estop"}
    assert not EPISODES_RAW.qos.latest_only


def test_a_gate_flood_never_blocks_and_leaves_the_newest_gate_per_sender():
    bus = InProcBus()
    sub = bus.subscribe(REPLAY_GATE, capacity=16)
    done = threading.Event()

    def flood() -> None:
        for k in range(3_000):
            bus.publish(REPLAY_GATE, gate(k), source="learner-0")
        bus.publish(REPLAY_GATE, gate(7, "learner-1"), source="learner-1")
        done.set()

    threading.Thread(target=flood, daemon=True).start()
    # nobody reads while 3,001 gates arrive on a 16-slot subscription: the publisher must not wait
    assert done.wait(30.0), "the publisher was blocked by an unread latest-value subscription"
    got = sub.drain()
    assert [(d.parts["source"], d.message.inserted_steps) for d in got] == [
        ("learner-0", 2_999),
        ("learner-1", 7),
    ]
    assert sub.replaced == 2_999 and sub.qsize() == 0
    bus.close()


def test_an_announcement_after_a_gate_flood_is_read_at_once():
    bus = InProcBus()
    gates = bus.subscribe(REPLAY_GATE, capacity=16)
    announces = bus.subscribe(WEIGHTS_ANNOUNCE, capacity=8)
    for k in range(3_000):
        bus.publish(REPLAY_GATE, gate(k), source="learner-0")
    blob = WeightsBlob.create(5, "equi_rsac", "run-a", {"w": np.zeros(3, np.float32)}, "{}")
    t0 = time.monotonic()
    bus.publish(WEIGHTS_ANNOUNCE, blob.announcement(byte_size=1024), source="learner-0")
    d = announces.recv(timeout=1.0)
    assert d is not None and d.message.version == 5 and time.monotonic() - t0 < 1.0
    assert len(gates.drain()) == 1
    bus.close()


def test_episodes_still_keep_every_message_in_order(make_episode):
    bus = InProcBus()
    sub = bus.subscribe(EPISODES_RAW, capacity=8)
    eps = [make_episode(T=3, seed=k, episode_id=f"ep-{k}") for k in range(5)]
    for ep in eps:
        bus.publish(EPISODES_RAW, ep, source="actor-0")
    assert [d.message.episode_id for d in sub.drain()] == [f"ep-{k}" for k in range(5)]
    bus.close()


def test_a_future_dated_gate_cannot_shadow_the_real_ones():
    bus = InProcBus()
    tracker = GateTracker(bus.subscribe(REPLAY_GATE, capacity=16))
    bus.publish(REPLAY_GATE, gate(99, created_at=time.time() + 3_600.0), source="learner-0")
    assert tracker.update() is None and tracker.future_dated == 1
    bus.publish(REPLAY_GATE, gate(5), source="learner-0")
    assert tracker.update().inserted_steps == 5
    # within the allowed skew a gate is taken as usual
    bus.publish(REPLAY_GATE, gate(6, created_at=time.time() + MAX_CLOCK_SKEW / 2), source="learner-0")
    assert tracker.update().inserted_steps == 6 and tracker.future_dated == 1
    bus.close()
