"""The actor service on the in-process bus: demos then random episodes, all valid on the wire."""

from __future__ import annotations

import numpy as np
import pytest

from proto.episode import Episode
from proto.topics import EPISODES_RAW
from services.actor.config import ActorConfig
from services.actor.main import run
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig

pytestmark = [pytest.mark.integration, pytest.mark.slow]


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
        # privileged: the immovable object is named, and it is the one that stayed put
        fixed, movable = ep.fixed_object, 1 - ep.fixed_object
        assert fixed in (0, 1)
        drift = np.abs(ep.object_poses[:, :, :3] - ep.object_poses[0, :, :3]).max(axis=(0, 2))
        assert drift[fixed] < 1e-3 < 0.01 < drift[movable], drift
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


@pytest.mark.timeout(180)
def test_learned_actor_acts_with_broadcast_weights_and_waits_for_the_replay_gate():
    import threading
    import time

    import torch

    from proto.control import ReplayGate
    from proto.topics import REPLAY_GATE
    from proto.weights import WeightsBlob
    from services.algorithms.networks import PRESETS, build_actor
    from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors
    from services.common.weights import WeightsServer
    from services.episodes.rollout import policy_image

    hub = Hub()
    observer = InProcBus(hub)
    episodes = observer.subscribe(EPISODES_RAW, capacity=64)
    torch.manual_seed(0)
    spec = PolicySpec(PRESETS["cpu-small"])
    blob = WeightsBlob.create(7, "equi_rsac", "run-1", actor_tensors(build_actor(spec.net)), spec.to_json())
    server = WeightsServer(observer, "learner-0")
    server.publish(blob)

    def gate(inserted: int, allowed: int) -> None:
        observer.publish(REPLAY_GATE, ReplayGate(learner_id="learner-0", run_id="run-1", inserted_steps=inserted,
                                                 allowed_steps=allowed, updates=0, policy_version=7,
                                                 replay_transitions=0, created_at=time.time()),
                         source="learner-0")  # fmt: skip

    closed = threading.Event()

    def keep_gate_closed() -> None:  # the learner's allowance is used up until `closed` is cleared
        while not closed.is_set():
            gate(100, 100)
            time.sleep(0.05)
        gate(100, 150)

    cfg = ActorConfig(task="block_pull", policy="learned", episodes=1, index=1, points_per_segment=64,
                      service=ServiceConfig(instance_id="actor-1", metrics_port=0, log_format="text"))  # fmt: skip
    gate(100, 100)
    keeper = threading.Thread(target=keep_gate_closed, daemon=True)
    keeper.start()
    result: dict = {}
    actor = threading.Thread(
        target=lambda: result.setdefault("rc", run(cfg, bus_factory=lambda _c: InProcBus(hub)))
    )
    actor.start()
    assert episodes.recv(timeout=3.0) is None, "published while the gate was closed"
    closed.set()
    actor.join(timeout=120)
    assert result.get("rc") == 0
    (d,) = episodes.drain()
    ep = d.message
    assert ep.policy_kind == "learned" and ep.policy_version == 7 and not ep.is_demo
    # the actions are the policy's: replaying the episode's observations through a runtime with the
    # same weights and seed reproduces them
    runtime = PolicyRuntime(deterministic=False, seed=cfg.seed_base + cfg.index * 1_000_000)
    runtime.load(blob)
    from services.tasks.env import Observation

    for t in range(3):
        obs = Observation(ep.points[t], ep.point_counts[t], float(ep.jaw[t]), ep.gripper_pose[t],
                          ep.object_poses[t], ep.contacts[t])  # fmt: skip
        np.testing.assert_allclose(runtime.act(policy_image(obs)), ep.actions[t], atol=1e-5)
    server.close()
