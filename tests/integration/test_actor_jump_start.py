"""An actor with jump starts (``--jump-start``) publishes learned episodes that begin with the run's
own demonstration, made again on an actor that never recorded it: the demonstration's seed, its
first actions as executed, a new id each, and the policy's own actions after the handover."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from proto.weights import WeightsBlob
from services.actor import jump_start
from services.actor.config import ActorConfig
from services.algorithms.networks import PRESETS, build_actor
from services.algorithms.policy import PolicySpec, actor_tensors
from services.common.config import ServiceConfig
from services.tasks import make_env
from tests.helpers.actor_run import published_episodes

pytestmark = [pytest.mark.integration, pytest.mark.slow]


@pytest.mark.timeout(300)
def test_an_actor_jump_starts_from_the_runs_demonstration():
    torch.manual_seed(0)
    spec = PolicySpec(PRESETS["cpu-small"])
    blob = WeightsBlob.create(3, "equi_rsac", "run-1", actor_tensors(build_actor(spec.net)), spec.to_json())
    service = ServiceConfig(instance_id="actor-1", metrics_port=0, log_format="text")
    cfg = ActorConfig(task="block_pull", policy="learned", follow_gate=False, points_per_segment=32, index=1,
                      envs=2, episodes=6, seed_base=500, jump_start=1.0, jump_start_demos=1,
                      jump_start_seed_base=100, service=service)  # fmt: skip
    env = make_env("block_pull", cfg.env_settings())
    try:
        (demo,) = jump_start.regenerate(cfg, env, "check")  # what actor 0 recorded in the first sitting
    finally:
        env.close()
    episodes = published_episodes(cfg, blob)
    assert len(episodes) == 6 and len({ep.episode_id for ep in episodes}) == 6
    assert all(
        ep.policy_kind == "jump_start" and not ep.is_demo and ep.policy_version == 3 for ep in episodes
    )
    assert {ep.seed for ep in episodes} == {demo.seed} and demo.seed < 10**6  # actor 0's stream, not its own
    for ep in episodes:
        n = min(len(ep.actions), len(demo.actions))
        same = np.all(ep.actions[:n] == demo.actions[:n], axis=1)
        replayed = int(np.argmin(same)) if not same.all() else n
        assert replayed >= 1  # the demonstration acted first, then the policy (a random net's action)
        assert not same[replayed:].any() or replayed == n
