"""A flood of 3,000 replay gates over real Zenoh (127.0.0.1) does not delay the next weights load by a
second: gates are latest-value per sender and announcements are read apart from them."""

from __future__ import annotations

import threading
import time

import pytest

from proto.control import ReplayGate
from proto.topics import REPLAY_GATE
from services.common.bus.base import Credentials
from services.common.bus.zenoh_bus import ZenohBus
from services.common.replay_gate import GateTracker
from services.common.weights import WeightsClient, WeightsServer
from tests.helpers import build_weights
from tests.helpers.zenoh_peer import peer_config

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(120)]
KEY = bytes(range(32))


def member(router: str, service: str, instance: str) -> ZenohBus:
    bus = ZenohBus(peer_config(router, "client"))
    bus.authenticate(Credentials(KEY, service, instance))
    return bus


def test_a_3000_gate_flood_delays_the_next_weights_load_by_under_a_second(zenoh_router):
    learner, flooder, actor = (member(zenoh_router, "learner", f"learner-{i}") for i in (0, 1, 2))
    try:
        server = WeightsServer(learner, "learner-0")
        client = WeightsClient(actor, timeout=5.0)
        gates = GateTracker(actor.subscribe(REPLAY_GATE, capacity=16))
        server.publish(build_weights(0))
        deadline = time.monotonic() + 10
        while client.poll() is None:  # the consumer holds v0; the flood starts from there
            assert time.monotonic() < deadline, "v0 never loaded"
        sent = threading.Event()

        def flood() -> None:
            for k in range(3000):
                flooder.publish(REPLAY_GATE, ReplayGate(learner_id="learner-1", run_id="run-0", inserted_steps=k,
                                                        allowed_steps=k, updates=k, policy_version=0,
                                                        replay_transitions=k, created_at=time.time()),
                                source="learner-1")  # fmt: skip
                if k == 1500:
                    sent.set()
            sent.set()

        t = threading.Thread(target=flood, daemon=True)
        t.start()
        assert sent.wait(30)
        t_announce = time.monotonic()
        server.publish(build_weights(1))  # mid-flood
        loaded = None
        while loaded is None and time.monotonic() - t_announce < 5:
            gates.update()  # the consumer keeps reading gates as an actor does
            loaded = client.poll()
            time.sleep(0.005)
        delay = time.monotonic() - t_announce
        t.join(30)
        assert loaded is not None and loaded.version == 1
        assert delay < 1.0, f"weights v1 loaded {delay:.2f} s after its announcement, during the flood"
        gates.update()
        assert gates.latest is not None and gates.latest.learner_id == "learner-1"
        assert actor.stats.bad["replay_gate"] == 0
    finally:
        for b in (learner, flooder, actor):
            b.close()
