"""The actor service on the in-process bus: demos then random episodes, all valid on the wire."""

from __future__ import annotations

import numpy as np
import pytest

from proto.episode import Episode
from proto.topics import EPISODES_RAW
from services.actor.main import ActorConfig, run
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig

pytestmark = pytest.mark.integration


@pytest.mark.timeout(180)
def test_actor_publishes_demos_then_random_episodes_that_validate():
    hub = Hub()
    observer = InProcBus(hub)
    episodes = observer.subscribe(EPISODES_RAW, capacity=64)
    cfg = ActorConfig(task="block_pick", policy="random", demos=2, episodes=2, index=3, points_per_segment=64,
                      service=ServiceConfig(instance_id="actor-3", metrics_port=0, log_format="text"))  # fmt: skip
    assert run(cfg, bus_factory=lambda _c: InProcBus(hub)) == 0
    got = [d for d in episodes.drain()]
    assert len(got) == 4
    assert all(d.parts == {"source": "actor-3"} for d in got)
    demos, rand = [d.message for d in got[:2]], [d.message for d in got[2:]]
    for ep in demos:
        assert isinstance(ep, Episode) and ep.is_demo and ep.policy_kind.startswith("expert_")
        assert ep.terminated[-1] and ep.rewards[-1] == 1.0  # only successful demos are published
    assert {ep.policy_kind for ep in demos} == {"expert_probe", "expert_direct"}
    for ep in rand:
        assert ep.policy_kind == "random" and not ep.is_demo and ep.policy_version == -1
    seeds = [ep.seed for ep in demos + rand]
    assert len(set(seeds)) == 4 and all(3_000_000 <= s < 4_000_000 for s in seeds)  # actor 3's seed stream
    for ep in demos + rand:
        # round trip through the codec again: what was published validates
        again = Episode.decode(ep.encode())
        assert np.array_equal(again.points, ep.points) and again.points.shape[2] == 64
        assert ep.points.shape[0] == ep.num_steps + 1 and ep.segments == ["gripper", "object_0", "object_1"]
