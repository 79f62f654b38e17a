"""Recurrent SAC learns the known optimal actions of a tiny memory task (CPU, well under 3 minutes).

The task: two steps. Observation 0 shows a cue c in {-1, +1} (one half of the image lit); observation
1 is blank. Rewards r_0 = -(dx_0 - c/2)^2 and r_1 = -(dy_1 - c/2)^2: the first optimal action reads
the current image, the second needs memory of the cue seen a step earlier. Trained from uniformly
random episodes through the real replay, batching, networks (plain and C4) and SAC update.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from services.algorithms.batch import to_batch
from services.algorithms.networks import NetConfig, build_actor, build_critic
from services.algorithms.policy import images_from_codes
from services.algorithms.replay import SequenceReplay
from services.algorithms.sac.agent import RecurrentSAC
from services.algorithms.sac.config import SacSettings
from services.algorithms.sac.losses import deterministic_action
from tests.helpers import build_episode

SIZE = 12
TARGET = 0.5


def cue_image(c: int) -> np.ndarray:
    img = np.zeros((2, SIZE, SIZE), np.uint8)
    if c > 0:
        img[0, :, : SIZE // 2] = 255
    else:
        img[0, :, SIZE // 2 :] = 255
    return img


def memory_episode(rng: np.random.Generator, k: int):
    c = int(rng.choice([-1, 1]))
    images = np.zeros((3, 2, SIZE, SIZE), np.uint8)
    images[0] = cue_image(c)
    actions = rng.uniform(-1, 1, (2, 5)).astype(np.float32)
    rewards = np.array(
        [-((actions[0, 1] - TARGET * c) ** 2), -((actions[1, 2] - TARGET * c) ** 2)], np.float32
    )
    ep = build_episode(T=2, seed=k)
    return dataclasses.replace(
        ep, episode_id=f"actor-0-{k}-0", images=images, actions=actions, rewards=rewards
    )


def policy_means(actor) -> dict[int, np.ndarray]:
    """Deterministic actions at steps 0 and 1 for each cue, the previous action fed back."""
    out = {}
    for c in (-1, 1):
        codes = torch.from_numpy(np.stack([cue_image(c), np.zeros((2, SIZE, SIZE), np.uint8)]))[None]
        with torch.no_grad():
            mean0, _, state = actor.step(images_from_codes(codes[:, 0]), torch.zeros(1, 5))
            a0 = deterministic_action(mean0)
            mean1, _, _ = actor.step(images_from_codes(codes[:, 1]), a0, state)
        out[c] = np.stack([a0[0].numpy(), deterministic_action(mean1)[0].numpy()])
    return out


@pytest.mark.parametrize("group", ["none", "c4"])
@pytest.mark.slow
def test_recurrent_sac_learns_an_action_that_needs_memory(group):
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    net = NetConfig(group=group, image_size=SIZE, encoder=((4, 3, 3),), final_kernel=4, image_embed=16,
                    action_embed=8, q_action_embed=8, lstm_hidden=32, mlp_hidden=(32, 32))  # fmt: skip
    replay = SequenceReplay(4_000, image_size=SIZE, seq_len=2, seed=0)
    for k in range(1_500):
        replay.insert(memory_episode(rng, k))
    sac = RecurrentSAC(build_actor(net), build_critic(net), SacSettings(lr=3e-3, gamma=0.9))
    before = policy_means(sac.actor)
    for _ in range(800):
        sac.update(to_batch(replay.sample(64, rng)))
    after = policy_means(sac.actor)
    for c in (-1, 1):
        dx0, dy1 = after[c][0, 1], after[c][1, 2]
        assert abs(dx0 - TARGET * c) < 0.2, (group, c, after[c])
        assert abs(dy1 - TARGET * c) < 0.2, (group, c, after[c])  # needs the cue from step 0
    # it was learned, not there from the start
    assert max(abs(before[c][1, 2] - TARGET * c) for c in (-1, 1)) > 0.2
