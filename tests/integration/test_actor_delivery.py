"""The actor keeps what it published until the learner acknowledges it: an augmenter (re)start makes
it publish again what is unacknowledged, an ack lets it go, and with a learner alive it does not
exit before its episodes are acknowledged. On an authenticated in-process bus, like `mea run`."""

from __future__ import annotations

import threading
import time

import pytest

from proto.control import EpisodeAck
from proto.topics import EPISODE_ACKS, EPISODES_RAW
from services.actor.config import ActorConfig
from services.actor.main import run
from services.common.bus import Hub, InProcBus
from services.common.bus.base import Credentials
from services.common.config import ServiceConfig

pytestmark = pytest.mark.integration
KEY = bytes(range(32))


def member(hub: Hub, service: str, instance: str) -> InProcBus:
    bus = InProcBus(hub)
    bus.authenticate(Credentials(KEY, service, instance))
    return bus


def ids_within(sub, n: int, timeout: float) -> list[str]:
    out: list[str] = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        d = sub.recv(timeout=0.2)
        if d is not None:
            out.append(d.message.episode_id)
    return out


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_unacknowledged_episodes_are_published_again_when_an_augmenter_restarts():
    hub = Hub()
    learner = member(hub, "learner", "learner-0")
    raw = learner.subscribe(EPISODES_RAW, capacity=64)
    alive = learner.declare_alive("learner", "learner-0")
    augmenter = member(hub, "augmenter", "augmenter-0")
    cfg = ActorConfig(task="block_pull", policy="random", episodes=3, points_per_segment=32, follow_gate=False,
                      service=ServiceConfig(instance_id="actor-0", metrics_port=0, log_format="text"))  # fmt: skip
    result: dict[str, int] = {}

    def actor() -> None:
        bus = InProcBus(hub)
        result["code"] = run(cfg, bus_factory=lambda _c: _authenticated(bus))

    def _authenticated(bus: InProcBus) -> InProcBus:
        bus.authenticate(Credentials(KEY, "actor", "actor-0"))
        return bus

    t = threading.Thread(target=actor, daemon=True)
    t.start()
    first = ids_within(raw, 3, 120.0)
    assert len(first) == 3 and len(set(first)) == 3
    time.sleep(0.5)
    assert t.is_alive(), "the actor exited with its episodes unacknowledged while a learner was alive"
    assert raw.recv(timeout=0.5) is None  # nothing is resent without a reason

    token = augmenter.declare_alive("augmenter", "augmenter-0")  # an augmenter (re)starts
    again = ids_within(raw, 3, 10.0)
    assert again == first  # every unacknowledged episode, oldest first, once

    ack = EpisodeAck(learner_id="learner-0", run_id="run-0", episode_ids=first[:2], created_at=time.time())
    learner.publish(EPISODE_ACKS, ack, source="learner-0")
    time.sleep(0.5)
    assert t.is_alive()  # one is still unacknowledged
    forged = member(hub, "actor", "actor-9")  # a service that may not acknowledge: refused
    forged.publish(EPISODE_ACKS, b"x", source="actor-9")
    ack = EpisodeAck(learner_id="learner-0", run_id="run-0", episode_ids=first, created_at=time.time())
    learner.publish(EPISODE_ACKS, ack, source="learner-0")
    t.join(30.0)
    assert not t.is_alive() and result["code"] == 0
    assert raw.recv(timeout=0.2) is None  # acknowledged episodes are never resent
    token.close()
    alive.close()
