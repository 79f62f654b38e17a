"""Pull-if-newer weights: the learner serves and announces; consumers query only newer versions."""

from __future__ import annotations

import numpy as np
import pytest

from proto.weights import WeightsBlob
from services.common.bus import Hub, InProcBus
from services.common.weights import WeightsClient, WeightsServer

pytestmark = pytest.mark.unit


def _blob(version: int) -> WeightsBlob:
    return WeightsBlob.create(version, "equi_rsac", "run-1", {"w": np.full((4,), version, np.float32)})


class CountingBus(InProcBus):
    def __init__(self, hub):
        super().__init__(hub)
        self.queries = 0

    def query(self, *a, **kw):
        self.queries += 1
        return super().query(*a, **kw)


def test_consumer_pulls_only_when_a_newer_version_is_announced():
    hub = Hub()
    server = WeightsServer(InProcBus(hub), "learner-0")
    bus = CountingBus(hub)
    client = WeightsClient(bus)
    assert client.poll() is None  # nothing served yet: one start-up query
    assert bus.queries == 1
    assert client.poll() is None and bus.queries == 1  # no announcement, no query
    server.publish(_blob(1))
    got = client.poll()
    assert got is not None and got.version == 1 and client.version == 1
    assert float(got.tensors["w"][0]) == 1.0
    queries = bus.queries
    for _ in range(5):
        assert client.poll() is None
    assert bus.queries == queries  # steady state: no traffic
    server.publish(_blob(3))
    server.publish(_blob(4))
    assert client.poll().version == 4  # skips straight to the latest
    assert client.poll() is None


def test_late_joiner_gets_the_latest_without_an_announcement():
    hub = Hub()
    server = WeightsServer(InProcBus(hub), "learner-0")
    server.publish(_blob(7))
    late = WeightsClient(InProcBus(hub))
    assert late.poll().version == 7


def test_versions_must_increase():
    server = WeightsServer(InProcBus(Hub()), "learner-0")
    server.publish(_blob(2))
    with pytest.raises(ValueError, match="not newer"):
        server.publish(_blob(2))


def test_server_answers_nothing_to_a_stale_or_bad_request():
    hub = Hub()
    server = WeightsServer(InProcBus(hub), "learner-0")
    server.publish(_blob(2))
    bus = InProcBus(hub)
    from proto.topics import WEIGHTS_LATEST

    assert bus.query(WEIGHTS_LATEST, {"min_version": "3"}) is None
    assert bus.query(WEIGHTS_LATEST, {"min_version": "not-a-number"}) is None
    assert bus.query(WEIGHTS_LATEST, {"min_version": "2"}).message.version == 2


def test_absorbing_announcements_never_pulls_but_the_next_poll_gets_the_newest():
    hub = Hub()
    server = WeightsServer(InProcBus(hub), "learner-0")
    bus = CountingBus(hub)
    client = WeightsClient(bus)
    assert client.poll() is None and bus.queries == 1
    for v in (1, 2, 3):
        server.publish(_blob(v))
    client.absorb_announcements()
    assert bus.queries == 1 and client.version == -1  # drained, nothing pulled
    got = client.poll()
    assert got is not None and got.version == 3 and bus.queries == 2
    assert client.poll() is None and bus.queries == 2
