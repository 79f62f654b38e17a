"""Behaviour pins of the learner's updates: 15 updates of the cpu-small SAC recipe (BC with the Q
filter, shared encoder, return bound), of cpu-small-state (the state critic, BC without a shared
encoder), of the smoke preset's plain twin (rsac: no BC, separate encoders) and of gasv2-smoke, from fixed seeds on a fixed synthetic replay, must leave exactly the
state (networks, optimisers, temperature) and the update statistics they left when the hashes were
recorded. A refactor of the learner that changes a bit of either fails here.

The hashes are of torch 2.13 on this project's CPU build with one torch thread (``RECORDED_ON``);
another torch or another CPU kernel set rounds differently (torch 2.11 on an H200 host's CPU gives
other hashes), so elsewhere only the statistics' names are compared: rerecord the hashes there, from
the commit that recorded these, with ``python -m tests.unit.test_update_hashes``."""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import torch

from mea_tools.bench.learner import random_dsa_episode
from proto.episode import Episode
from services.algorithms.gasv2.algorithm import GasV2Config
from services.learner.config import PRESETS, build_trainer
from tests.helpers.learner import learner_episode, policy_images

pytestmark = [pytest.mark.unit, pytest.mark.timeout(300)]

UPDATES = 15
RECORDED_ON = ("2.13.0+cpu", "AVX512")
"""torch version and CPU kernel set (``torch.backends.cpu.get_cpu_capability``) of the hashes."""
EXPECTED = {
    "cpu-small": (
        "31ebdcae3d04135edd354848b3701a5c02a872cd2d4eacb808ce6fe3542c9457",
        "3846f83ff49adb88d056e15ac13df5a32488eaa4205b65a9de819a62ae062f57",
    ),
    "cpu-small-state": (
        "c7cc3b7cda798c62e423f445ca28e6bf2330e1dc3c464e5a077e66a2de74827d",
        "ee29fc716f458be204e255825038b2882c0f47705cd30066e0210056069cd7d5",
    ),
    "smoke/rsac": (
        "4a02683277d3a221e444899d2560817f56ac561b80fff77babaa821ae5050644",
        "d4c1171032f1d6148eb59b4e5473671c02a3b8765ee912b142483ec3cc9f5bf3",
    ),
    "gasv2-smoke": (
        "e133b550f90c63d62a8f583f4f38ed6863ab3fca39abcf68ce439e53bc73719c",
        "144cbe3765b72287fb3e363ce26fd37f9cd38da32e07f151efb0db368c3ebc5d",
    ),
}
"""Preset -> (sha256 of the trainer's state after UPDATES updates, sha256 of their statistics)."""
SAC_METRICS = frozenset(
    {
        "actor_grad_norm",
        "actor_loss",
        "alpha",
        "alpha_loss",
        "batch_demo_share",
        "batch_reward_transitions",
        "bc_accept",
        "bc_grad_norm",
        "bc_loss",
        "bc_weight",
        "critic_loss",
        "entropy",
        "q1",
        "q2",
        "q_demo_minus_pi",
        "q_rank_gap",
        "target_q",
    }
)
METRICS = {
    "cpu-small": SAC_METRICS,
    "cpu-small-state": SAC_METRICS,
    "smoke/rsac": SAC_METRICS - {"bc_loss", "bc_weight", "bc_grad_norm"},
    "gasv2-smoke": frozenset(
        {
            "actor_entropy",
            "actor_grad_norm",
            "actor_loss",
            "advantage",
            "batch_demo_share",
            "batch_reward_transitions",
            "critic_grad_norm",
            "critic_loss",
            "discount_loss",
            "imag_discount",
            "imag_return",
            "imag_reward",
            "imag_starts",
            "imag_value",
            "image_loss",
            "kl",
            "model_grad_norm",
            "model_loss",
            "post_entropy",
            "prior_entropy",
            "reward_loss",
            "updates",
        }
    ),
}
"""Preset -> the statistics an update reports (the TensorBoard and Prometheus names come from these)."""


def _floats(obj: Any, key: str = "") -> Iterator[tuple[str, torch.Tensor]]:
    """Every floating tensor in a (nested) state dict, by its key path, in sorted order."""
    if isinstance(obj, torch.Tensor):
        if obj.is_floating_point():
            yield key, obj
    elif isinstance(obj, dict):
        for k in sorted(obj, key=str):
            yield from _floats(obj[k], f"{key}/{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _floats(v, f"{key}/{i}")


def state_hash(state: dict) -> str:
    """sha256 of the concatenated float32 bytes of every floating tensor in ``state``."""
    h = hashlib.sha256()
    for _, t in _floats(state):
        h.update(t.detach().to(torch.float32).contiguous().numpy().tobytes())
    return h.hexdigest()


def metrics_hash(infos: list[dict[str, float]]) -> str:
    h = hashlib.sha256()
    for info in infos:
        for k in sorted(info):
            h.update(k.encode() + np.float64(info[k]).tobytes())
    return h.hexdigest()


def sac_episode(seed: int, T: int, **kw: Any) -> Episode:
    """``learner_episode`` with the cpu-small networks' 84 x 84 policy images."""
    ep = learner_episode(seed, T, **kw)
    images = policy_images(np.random.default_rng(seed), T, size=84)
    return dataclasses.replace(ep, images=images, fixed_object=1)  # fixed_object: for the state critic


def sac_episodes() -> list[Episode]:
    """Two demonstrations, one of them with an isometric copy, and three other episodes of 6-10 steps."""
    eps = [sac_episode(1, 8, demo=True), sac_episode(2, 10, demo=True)]
    eps.append(sac_episode(3, 8, copy_of=eps[0].episode_id))
    eps += [sac_episode(10 + k, 6 + 2 * k) for k in range(3)]
    return eps


def gasv2_episodes() -> list[Episode]:
    rng = np.random.default_rng(0)
    return [random_dsa_episode(rng, k, T=12, is_demo=k == 0) for k in range(4)]


def run_updates(case: str) -> tuple[str, str, frozenset[str]]:
    """(state hash, statistics hash, statistic names) after UPDATES updates of the trainer of ``case``:
    a preset, or ``preset/algorithm``."""
    preset, _, algorithm = case.partition("/")
    cfg = PRESETS[preset]
    if algorithm:
        cfg = dataclasses.replace(cfg, algorithm=dataclasses.replace(cfg.algorithm, name=algorithm))
    algo = cfg.algorithm
    if isinstance(algo, GasV2Config):
        cfg = dataclasses.replace(cfg, replay_capacity=2_000)
        episodes = gasv2_episodes()
    else:
        sac = dataclasses.replace(algo.sac, bc_filter=True) if algo.sac.share_encoder else algo.sac
        algo = dataclasses.replace(algo, sac=sac)
        cfg = dataclasses.replace(cfg, algorithm=algo, batch_size=4, seq_len=12, replay_capacity=1_000)
        episodes = sac_episodes()
    cfg = dataclasses.replace(cfg, samples_per_insert=10.0, min_steps=1, error_buffer=1_000.0, seed=3)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        trainer = build_trainer(cfg)
        for ep in episodes:
            trainer.insert(ep)
        infos = []
        for _ in range(UPDATES):
            info = trainer.step()
            assert info is not None
            infos.append(info)
        names = frozenset().union(*infos)
        return state_hash(trainer.agent.state_dict()), metrics_hash(infos), names
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("case", sorted(EXPECTED))
def test_updates_leave_the_recorded_state(case: str) -> None:
    state, stats, names = run_updates(case)
    assert names == METRICS[case]
    here = (torch.__version__, torch.backends.cpu.get_cpu_capability())
    if here != RECORDED_ON:
        pytest.skip(f"the hashes are torch {RECORDED_ON[0]} {RECORDED_ON[1]}'s, this is {here[0]} {here[1]}")
    assert (state, stats) == EXPECTED[case], f"{case}: {state}, {stats}"


if __name__ == "__main__":
    for name in sorted(EXPECTED):
        print(name, run_updates(name))
