"""The learner's inbox: a FIFO bounded by bytes between receiving and inserting (services/common/inbox.py),
and the learner's use of it: receiving goes on while the replay is held, and stopping inserts what was
received."""

from __future__ import annotations

import dataclasses
import threading

import pytest

from proto.topics import EPISODES_AUGMENTED
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig
from services.common.inbox import Inbox
from services.common.runtime import ServiceContext
from services.learner.main import Learner
from tests.helpers import poll_until
from tests.helpers.learner import learner_episode, tiny_learner_config


def test_items_come_out_in_the_order_they_went_in_and_bytes_are_counted():
    box: Inbox[str] = Inbox(100)
    for i, size in enumerate((10, 20, 30)):
        assert box.put(f"e{i}", size, timeout=0)
    assert (len(box), box.nbytes, box.peak_bytes) == (3, 60, 60)
    assert [box.get(timeout=0) for _ in range(3)] == ["e0", "e1", "e2"]
    assert (len(box), box.nbytes, box.peak_bytes) == (0, 0, 60)
    assert box.get(timeout=0.01) is None


def test_a_put_past_the_bound_waits_until_a_get_makes_room():
    box: Inbox[str] = Inbox(100)
    assert box.put("a", 60, timeout=0)
    assert not box.put("b", 50, timeout=0.05)  # 110 > 100: refused after the wait
    assert len(box) == 1
    done = threading.Event()
    waiter = threading.Thread(target=lambda: box.put("b", 50) and done.set(), daemon=True)
    waiter.start()
    assert not done.wait(0.1)  # still waiting
    assert box.get(timeout=0) == "a"
    assert done.wait(2.0)
    assert box.get(timeout=0) == "b"


def test_an_item_larger_than_the_bound_is_taken_when_the_inbox_is_empty():
    box: Inbox[str] = Inbox(10)
    assert box.put("big", 1_000, timeout=0)
    assert not box.put("small", 1, timeout=0)  # the big one fills it
    assert box.get(timeout=0) == "big"
    assert box.put("small", 1, timeout=0)


@pytest.mark.parametrize(("max_bytes", "size"), [(0, 1), (10, -1)])
def test_bad_bounds_and_sizes_are_refused(max_bytes, size):
    with pytest.raises(ValueError, match="must be >= "):
        Inbox(max_bytes).put("x", size)


def test_the_learner_keeps_receiving_while_its_replay_is_held_and_inserts_everything_on_stop(tmp_path):
    hub = Hub()
    service = ServiceConfig(instance_id="learner-0", metrics_port=0, heartbeat_seconds=0.5)
    cfg = tiny_learner_config(tmp_path, service, queue=2)
    holder: dict = {}

    def bus_factory(_c: ServiceConfig) -> InProcBus:
        bus = InProcBus(hub)
        holder["sub"] = bus.subscribe(EPISODES_AUGMENTED, capacity=cfg.queue)
        return bus

    producer = InProcBus(hub)
    episodes = [learner_episode(seed) for seed in range(12)]
    with ServiceContext("learner", service, bus_factory=bus_factory) as ctx:
        core = Learner(cfg, ctx, holder["sub"])
        core.start_ingest()
        try:
            with core.lock:  # a checkpoint being written
                for ep in episodes:  # 12 > the subscription's 2: the publisher would wait without the inbox
                    producer.publish(EPISODES_AUGMENTED, ep, source="augmenter-0")
                # one may be in the inserting thread, waiting on the lock; the rest wait in the inbox
                assert poll_until(lambda: len(core.inbox) >= len(episodes) - 1, 5.0)
                stopper = threading.Thread(target=core.stop_ingest, daemon=True)
                stopper.start()  # stops receiving at once; inserting waits for the lock
                stopper.join(0.3)
                assert stopper.is_alive() and core.counts["episodes_in"] == 0
            stopper.join(10.0)
            assert not stopper.is_alive()
        finally:
            core.stop_ingest()
        assert core.counts["episodes_in"] == len(episodes)
        assert len(core.inbox) == 0
        assert core.heartbeat_counters()["inbox_peak_bytes"] > 0


def test_a_learned_episode_carries_the_updates_owed_when_the_weights_that_acted_it_were_announced(tmp_path):
    service = ServiceConfig(instance_id="learner-0", metrics_port=0, heartbeat_seconds=0.5)
    cfg = tiny_learner_config(tmp_path, service)  # 1 update per env step
    with ServiceContext("learner", service, bus_factory=lambda _c: InProcBus(Hub())) as ctx:
        core = Learner(cfg, ctx, None)
        for seed in range(4):  # 4 demonstrations of 10 steps: 40 updates owed, none made
            core.ingest(learner_episode(seed, demo=True))
        core.publish_weights()  # version 0
        while core.trainer.updates < 7:  # announcing a version every 2 updates on the way
            assert core.try_update()
        core.ingest(dataclasses.replace(learner_episode(10), policy_version=0))
        assert core.lag == 40  # version 0 had learned from none of the 40 steps
        core.ingest(dataclasses.replace(learner_episode(11), policy_version=core.version))
        assert core.lag == 40 - core.published_at  # the newest had made published_at of them
        for unknown in (-1, core.version + 5):  # scripted, and a version this learner never announced
            core.ingest(dataclasses.replace(learner_episode(12 + unknown % 7), policy_version=unknown))
            assert core.lag == 40 - core.published_at  # unchanged
        assert ctx.metrics.registry.get_sample_value("mea_learner_episode_lag_updates_count") == 2
        assert ctx.metrics.registry.get_sample_value("mea_learner_episode_lag_updates_sum") == (
            40 + 40 - core.published_at
        )
