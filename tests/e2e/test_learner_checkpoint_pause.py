"""A learner whose replay is held longer than Zenoh's lease (a checkpoint of a large replay) loses
nothing that was sent to it meanwhile.

Before the learner had an inbox (services/common/inbox.py) the thread reading its subscription waited
on the replay's lock; the subscription filled, Zenoh's reader waited with it, and past Zenoh's lease
(about 10 s) the transport was closed and the episodes it held were lost (docs/results.md)."""

from __future__ import annotations

import threading
import time

import pytest

from proto.topics import EPISODES_AUGMENTED
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from services.common.config import ServiceConfig
from services.common.runtime import ServiceContext
from services.learner.main import Learner
from tests.helpers import find_free_port, poll_until
from tests.helpers.learner import learner_episode, tiny_learner_config
from tests.helpers.zenoh_peer import peer_config

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(150)]

HOLD_S = 14.0  # past Zenoh's 10 s lease
SENT = 600  # episodes of 50 steps: ~10 MB, far more than the subscription and the socket buffers hold


class RecordingLearner(Learner):
    """The learner, noting the id of every episode its replay takes (in the order it does)."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        self.inserted: list[str] = []

    def ingest(self, ep) -> None:
        before = self.counts["episodes_in"]
        super().ingest(ep)  # refuses a repeat of an episode id it holds (the warm-up's)
        if self.counts["episodes_in"] > before:
            self.inserted.append(ep.episode_id)


def test_episodes_sent_while_a_checkpoint_holds_the_replay_past_the_lease_all_arrive(tmp_path):
    endpoint = f"tcp/127.0.0.1:{find_free_port()}"
    router = ZenohBus(ZenohConfig(mode="router", listen=(endpoint,), connect=()))
    producer = ZenohBus(peer_config(endpoint))
    service = ServiceConfig(instance_id="learner-0", zenoh=peer_config(endpoint), metrics_port=0,
                            heartbeat_seconds=0.5)  # fmt: skip
    cfg = tiny_learner_config(tmp_path, service, queue=4, seq_len=50, replay_capacity=100_000)
    holder: dict = {}

    def bus_factory(c: ServiceConfig) -> ZenohBus:
        bus = ZenohBus(c.zenoh)
        holder["sub"] = bus.subscribe(EPISODES_AUGMENTED, capacity=cfg.queue)
        return bus

    def send(eps) -> None:
        for ep in eps:
            producer.publish(EPISODES_AUGMENTED, ep, source="augmenter-0")

    episodes = [learner_episode(seed, T=50) for seed in range(SENT + 2)]
    held, sent_ids = episodes[:SENT], [ep.episode_id for ep in episodes[:SENT]]
    warm_up, after = episodes[SENT], episodes[SENT + 1]
    try:
        with ServiceContext("learner", service, bus_factory=bus_factory) as ctx:
            core = RecordingLearner(cfg, ctx, holder["sub"])
            core.start_ingest()
            try:
                # routes are up once an episode crosses (the same one, sent again until it does)
                assert poll_until(lambda: send([warm_up]) or warm_up.episode_id in core.inserted, 15.0)
                with core.lock:  # what save_checkpoint holds while it writes
                    sender = threading.Thread(target=send, args=(held,), daemon=True)
                    sender.start()
                    time.sleep(HOLD_S)  # the checkpoint being written (the behaviour under test)
                    waited = len(core.inbox)
                assert waited > 0, "nothing waited in the inbox: the test did not hold the replay"
                got = lambda: [i for i in core.inserted if i in set(sent_ids)]  # noqa: E731
                assert poll_until(lambda: len(got()) >= SENT, 30.0), (
                    f"{len(got())} of {SENT} reached the replay"
                )
                assert got() == sent_ids  # each once, in the order sent
                sender.join(5.0)
                send([after])
                assert poll_until(lambda: after.episode_id in core.inserted, 5.0)  # the path is still open
            finally:
                core.stop_ingest()
    finally:
        producer.close()
        router.close()
