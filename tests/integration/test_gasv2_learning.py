"""Learning sanity of GASv2 on the real task: the world model, trained on recorded Surgical Grasp Any
oracle episodes (the actor's rollout, the env's DSA images), predicts their images and rewards
better; measured on one fixed batch of windows before and after, with the losses the learner uses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from services.actor.config import ActorConfig
from services.actor.rollout import RolloutActor
from services.algorithms.gasv2.agent import GasV2Agent
from services.algorithms.gasv2.chunk_replay import ChunkReplay, to_chunk_batch
from services.algorithms.gasv2.config import PRESETS

pytestmark = pytest.mark.integration


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_world_model_losses_fall_on_recorded_surgical_episodes():
    torch.set_num_threads(1)
    actor = RolloutActor(ActorConfig(task="surgical_grasp_any"), "actor-0")
    try:
        episodes = [actor.expert_episode(k).finish(f"demo-{k}") for k in range(3)]
    finally:
        actor.env.close()
    assert all(ep.succeeded and ep.images.shape[1:] == (3, 64, 64) for ep in episodes)
    replay = ChunkReplay(1_000, seed=0)
    for ep in episodes:
        replay.insert_episode(ep)
    rng = np.random.default_rng(0)
    probe = to_chunk_batch(replay.sample_chunks(32, 6, np.random.default_rng(1)))
    assert probe.rewards.max() == 1.0  # the probe holds a success step: the reward loss sees it

    agent = GasV2Agent(PRESETS["smoke"], seed=0)

    def losses() -> tuple[float, float]:
        with torch.no_grad():
            _, _, m = agent.world_model.loss(probe, torch.Generator().manual_seed(0))
        return float(m["image_loss"]), float(m["reward_loss"])

    image0, reward0 = losses()
    for _ in range(120):
        agent.update(to_chunk_batch(replay.sample_chunks(16, 6, rng)))
    image1, reward1 = losses()
    assert image1 < 0.5 * image0, (image0, image1)
    assert reward1 < 0.3 * reward0, (reward0, reward1)
