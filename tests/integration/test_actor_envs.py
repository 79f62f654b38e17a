"""An actor with K envs (``--envs-per-actor``) runs, seed for seed, what K single-env actors run: the
same episodes from the same seeds, the demos and the random prefill on env 0 as on actor 0 (bit for
bit), and in the learned episodes the actions a single-env actor's policy takes on the same
observations with the same noise stream, to float rounding (one batched policy step per tick instead
of K one-sample steps; the physics then amplifies rounding, so the learned trajectories themselves
are compared through the policy, not point by point)."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest
import torch

from proto.seeds import ACTOR_SEED_STRIDE
from proto.weights import WeightsBlob
from services.actor.config import ActorConfig
from services.algorithms.networks import PRESETS, build_actor
from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors
from services.common.config import ServiceConfig
from services.episodes.rollout import policy_image
from services.tasks.env import Observation
from tests.helpers.actor_run import published_episodes

pytestmark = [pytest.mark.integration, pytest.mark.slow]
K = 3


def _by_stream(episodes: list) -> dict[int, list]:
    """Episodes by the actor index whose seed stream they come from, in publishing order."""
    out: dict[int, list] = defaultdict(list)
    for ep in episodes:
        out[ep.seed // ACTOR_SEED_STRIDE].append(ep)
    return out


@pytest.mark.timeout(300)
def test_k_envs_in_one_actor_run_what_k_single_env_actors_run():
    torch.manual_seed(0)
    spec = PolicySpec(PRESETS["cpu-small"])
    blob = WeightsBlob.create(7, "equi_rsac", "run-1", actor_tensors(build_actor(spec.net)), spec.to_json())
    service = ServiceConfig(instance_id="actor-0", metrics_port=0, log_format="text")
    base = ActorConfig(
        task="block_pull", policy="learned", follow_gate=False, points_per_segment=32, service=service
    )
    vector = published_episodes(
        ActorConfig(**{**base.__dict__, "envs": K, "demos": 1, "random_steps": 20, "episodes": 2 * K}), blob
    )
    streams = _by_stream(vector)
    assert sorted(streams) == list(range(K)), sorted(streams)  # every env drew from its own stream
    assert sum(ep.is_demo for ep in vector) == 1 and vector[0].is_demo and vector[0].seed < ACTOR_SEED_STRIDE
    assert {ep.policy_kind for ep in streams[0]} >= {"random", "learned"}
    assert all(ep.policy_kind == "learned" for j in range(1, K) for ep in streams[j])
    assert len({ep.episode_id for ep in vector}) == len(vector)
    for j in range(K):
        alone_cfg = ActorConfig(**{**base.__dict__, "index": j, "demos": 1 if j == 0 else 0,
                                   "random_steps": 20 if j == 0 else 0,
                                   "episodes": sum(not ep.is_demo for ep in streams[j])})  # fmt: skip
        alone = published_episodes(alone_cfg, blob)
        assert [ep.seed for ep in alone] == [ep.seed for ep in streams[j]], j
        for a, v in zip(alone, streams[j], strict=True):
            assert (a.policy_kind, a.is_demo) == (v.policy_kind, v.is_demo)
            if a.policy_kind != "learned":
                np.testing.assert_array_equal(v.actions, a.actions)
                np.testing.assert_array_equal(v.points, a.points)
        replay = PolicyRuntime(deterministic=False, seed=alone_cfg.first_seed())  # env j's policy, alone
        replay.load(blob)
        learned = [ep for ep in streams[j] if ep.policy_kind == "learned"]
        assert learned and all(ep.policy_version == 7 for ep in learned)
        for ep in learned:
            replay.reset()
            for t in range(ep.num_steps):
                obs = Observation(ep.points[t], ep.point_counts[t], float(ep.jaw[t]), ep.gripper_pose[t],
                                  ep.object_poses[t], ep.contacts[t])  # fmt: skip
                np.testing.assert_allclose(replay.act(policy_image(obs)), ep.actions[t], atol=1e-5)
                replay.executed(ep.actions[t])
