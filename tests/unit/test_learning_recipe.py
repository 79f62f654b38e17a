"""The CPU recipes learn from a few demonstrations lost among many failures (CPU, about 10 s each).

Three-step episodes whose every observation shows a cue c in {-1, +1} (one half of the image lit).
Two demonstrations (one per cue) move dx = 0.8 c and succeed (reward 1 at the end); 300 online
episodes act at random and never succeed. Trained with each CPU preset's own settings (demo share,
BC, temperature, return bound, actor without a_{t-1}; ``cpu-small``: critic LayerNorm and shared
encoder; ``cpu-small-state``: a critic on privileged rows that hold the cue, as the simulator's
state shows the layout) through the real replay, batching and update, the policy's mean must follow
the cue and its spread must have narrowed.

The test fails if demo-aware sampling is broken (uniform sampling puts a demonstration in one batch
of about 19: the mean stays near 0), and for ``cpu-small`` if
the temperature fields are (alpha from 0.1 keeps the spread wide: mean log std about -0.35 against
about -0.7 here; ``cpu-small-state`` has the same fields, and its BC term alone reaches the goal
on this task whatever alpha or the critic does; the state critic is checked on its own in
``test_privileged_state`` and ``test_sac_options``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from services.algorithms.batch import to_batch
from services.algorithms.networks import build_actor, build_critic
from services.algorithms.policy import images_from_codes
from services.algorithms.privileged import STATE_DIM
from services.algorithms.replay import SequenceReplay
from services.algorithms.sac.agent import RecurrentSAC
from services.learner.config import PRESETS
from tests.helpers import build_episode

pytestmark = pytest.mark.unit

SIZE, T, GOAL = 8, 3, 0.8


def cue(c: int) -> np.ndarray:
    img = np.zeros((2, SIZE, SIZE), np.uint8)
    if c > 0:
        img[0, : SIZE // 2] = 255
    else:
        img[0, SIZE // 2 :] = 255
    return img


def episode(rng: np.random.Generator, k: int, demo: bool, c: int | None = None):
    c = int(rng.choice([-1, 1])) if c is None else c
    actions = rng.uniform(-1, 1, (T, 5)).astype(np.float32)
    if demo:
        actions[:] = 0.0
        actions[:, 1] = GOAL * c
    rewards = np.zeros(T, np.float32)
    rewards[-1] = float(demo)
    last = np.arange(T) == T - 1
    return dataclasses.replace(
        build_episode(T=T, seed=k), episode_id=f"e{k}", images=np.stack([cue(c)] * (T + 1)), actions=actions,
        rewards=rewards, terminated=last & demo, truncated=last & (not demo), is_demo=demo,
    )  # fmt: skip


def state_rows(c: int) -> np.ndarray:
    """Privileged rows of an episode with cue c (``critic_state``'s layout, frame angle 0): the cue
    where the movable object's x offset goes, as the simulator's state would show the layout."""
    rows = np.zeros((T + 1, STATE_DIM), np.float32)
    rows[:, 1] = c
    return rows


@pytest.mark.parametrize("preset_name", ["cpu-small", "cpu-small-state"])
@pytest.mark.slow
def test_cpu_recipe_learns_the_demonstrated_action_among_failures(preset_name: str):
    preset = PRESETS[preset_name]
    algo = preset.algorithm
    net = dataclasses.replace(
        algo.net, image_size=SIZE, encoder=((2, 3, 1),), final_kernel=6, image_embed=16, action_embed=8,
        lstm_hidden=16, mlp_hidden=(16, 16),
    )  # fmt: skip
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    with_state = net.critic_input == "state"
    replay = SequenceReplay(5_000, image_size=SIZE, seq_len=T, seed=0, state_dim=STATE_DIM * with_state)

    def insert(k: int, demo: bool, c: int | None = None) -> None:
        c = int(rng.choice([-1, 1])) if c is None else c
        replay.insert(episode(rng, k, demo, c=c), state_rows(c) if with_state else None)

    insert(100_001, True, c=1)
    insert(100_002, True, c=-1)
    for k in range(300):
        insert(k, False)
    sac = RecurrentSAC(build_actor(net), build_critic(net), algo.sac)
    for _ in range(300):
        sample = replay.sample(
            preset.batch_size, rng, demo_fraction=preset.demo_fraction,
            successes_as_demos=preset.successes_as_demos, trim=algo.trim_batches,
        )  # fmt: skip
        sac.update(to_batch(sample))
    for c in (-1, 1):
        images = images_from_codes(torch.from_numpy(np.stack([cue(c)] * T)))[None]
        with torch.no_grad():
            mean, log_std, _ = sac.actor(images, torch.zeros(1, T, 5))
        dx = torch.tanh(mean[0, :, 1])
        assert torch.all((dx - GOAL * c).abs() < 0.4), (c, dx)
        assert float(log_std.mean()) < -0.55, (c, float(log_std.mean()))
