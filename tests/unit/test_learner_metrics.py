"""What an update's info puts in the learner's metrics, for SAC's and GASv2's update alike."""

from __future__ import annotations

import numpy as np
import torch

from mea_tools.bench.learner import random_dsa_episode
from services.algorithms.gasv2.agent import GasV2Agent
from services.algorithms.gasv2.chunk_replay import ChunkReplay, to_chunk_batch
from services.algorithms.gasv2.config import PRESETS
from services.common.metrics import ServiceMetrics
from services.learner.metrics import learner_metrics, record_update


def sample(m: ServiceMetrics, name: str, **labels) -> float | None:
    return m.registry.get_sample_value(name, labels or None)


def test_a_gasv2_update_fills_the_loss_and_entropy_gauges():
    torch.set_num_threads(1)
    replay = ChunkReplay(200, seed=0)
    replay.insert_episode(random_dsa_episode(np.random.default_rng(0), 0))
    info = GasV2Agent(PRESETS["smoke"], seed=0).update(to_chunk_batch(replay.sample_chunks(4, 6)))
    info.update(batch_demo_share=0.5, batch_reward_transitions=1.0)
    m = ServiceMetrics("learner", "learner-m")
    mx = learner_metrics(m)
    record_update(mx, info, 0.2, 3.0)
    for name, key in (("model", "model_loss"), ("image", "image_loss"), ("reward", "reward_loss"),
                      ("discount", "discount_loss"), ("kl", "kl"), ("actor", "actor_loss"), ("critic", "critic_loss")):  # fmt: skip
        assert sample(m, "mea_learner_loss", loss=name) == info[key], name
    assert sample(m, "mea_learner_policy_entropy") == info["actor_entropy"]
    assert sample(m, "mea_learner_batch_demo_share") == 0.5 and sample(m, "mea_learner_updates_total") == 1
    assert sample(m, "mea_learner_loss", loss="alpha") is None  # SAC's gauges stay unset


def test_a_sac_update_fills_alpha_and_q():
    m = ServiceMetrics("learner", "learner-s")
    mx = learner_metrics(m)
    info = {"critic_loss": 1.0, "actor_loss": 2.0, "alpha_loss": 0.1, "alpha": 0.05, "entropy": 3.0, "q1": 0.4,
            "q2": 0.5, "target_q": 0.45, "batch_demo_share": 0.0, "batch_reward_transitions": 2.0}  # fmt: skip
    record_update(mx, info, 0.1, None)
    assert sample(m, "mea_learner_alpha") == 0.05 and sample(m, "mea_learner_q", stat="q2") == 0.5
    assert (
        sample(m, "mea_learner_loss", loss="critic") == 1.0
        and sample(m, "mea_learner_loss", loss="kl") is None
    )
