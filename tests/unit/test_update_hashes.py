"""Behaviour pins of the learner's updates: 15 updates of the cpu-small SAC recipe (BC with the Q
filter, shared encoder, return bound), of cpu-small-state (the state critic, BC without a shared
encoder), of the smoke preset's plain twin (rsac: no BC, separate encoders) and of gasv2-smoke, from
fixed seeds on a fixed synthetic replay, must leave exactly the state (networks, optimisers,
temperature) and the update statistics they left when the hashes were recorded. A refactor of the
learner that changes a bit of either fails here.

torch picks its CPU kernels by what the CPU offers (MKL's GEMM, oneDNN's and NNPACK's convolutions,
ATen's vector width), and two x86 machines that both report AVX512 still round differently. So the
updates run in a child process on kernels that give the same bits on any x86 CPU: MKL in its
conditional-reproducibility mode (``MKL_CBWR=COMPATIBLE``), ATen's scalar kernels, oneDNN and NNPACK
off, one thread. Intel's MKL keeps that mode on Intel CPUs only, and an AMD CPU (a Zen 4 with
AVX512) gives other bits, the same for the same code: the hashes are recorded per CPU vendor, and
a vendor with none recorded fails, naming itself. Only another torch rounds differently (torch 2.11
on a GPU host); there only the statistics' names are compared. Rerecord with ``python -m
tests.unit.test_update_hashes`` on each vendor's CPU."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
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
RECORDED_ON = "2.13.0+cpu"
"""The torch version of the hashes."""
REPRODUCIBLE_KERNELS = {
    "MKL_CBWR": "COMPATIBLE",
    "ATEN_CPU_CAPABILITY": "default",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}
"""The child's environment: read when torch loads, so they cannot be set in this process."""
EXPECTED_BY_VENDOR = {
    "GenuineIntel": {
        "cpu-small": (
            "8831471e14cd280a9d2339ffd72b98d7f0d09a776f2e4984c62848c8906f3e26",
            "c82fe6b1f58a0bff3533fe6a9dad749a0dda4dfe35dfcccedd7154991ac943c9",
        ),
        "cpu-small-state": (
            "becc02952ff0dc8f6cb8810d57d08f62ea3dce5cadafe474e577d2f791f9d35f",
            "46c2b4f2e83340896afe86904a989a2bf867447be687f37bdadb1927acf134ef",
        ),
        "smoke/rsac": (
            "92deac40d041336e3dff6353cc6e89e08d64ef1f0e0c5fda9ee08066d290c2ed",
            "306d5d0f5f6290cf4eed829a2d8bb58a712c53ce68ea029dccf8cba21fbda2dc",
        ),
        "gasv2-smoke": (
            "85d2569078fed660313962f69a7f76fe49144cd6c982c7e339815e35da5d1898",
            "766578005e512623fa8b40fc9f0f90a947d93f27f211832ab1f464ba4e316288",
        ),
    },
    # the same code as the Intel hashes (the learner unchanged in between), on an AMD EPYC (Zen 4)
    "AuthenticAMD": {
        "cpu-small": (
            "383c82abfb92571a60e0f2bc279f0a94669e7e970da02375e3178d5e52a1e965",
            "257288fdf8d1486444afc5dd773743d1014562110558ee08e9f85554e1aeea63",
        ),
        "cpu-small-state": (
            "2a239489a95cf7628d21c13bf218d59084be672e5880e510f052f4613796f8de",
            "2d3afc7d1b002e50d1f17ab0fb525f35f97fd3ad8f7bb9b5c3151927b9b230f9",
        ),
        "smoke/rsac": (
            "463600bc7f525f2e6c6ab5b164610f5454799e9affabd507f175dc4ad4fdd569",
            "3922f93aa73cbd8f12d4f8a180c4aeb9d9897364dcf1718d88d2dfffc8e878f8",
        ),
        "gasv2-smoke": (
            "21cce02595b5b8e54110e6eaa3d38fe36540143fd3d943893fdc8acc1880792d",
            "dfc2cd28a7b46b858c4f830c7da761702635df0266f857c35801d8185189041f",
        ),
    },
}
"""CPU vendor -> preset -> (sha256 of the trainer's state after UPDATES updates, sha256 of their statistics)."""
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
        "q_reverse_gap",
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
    a preset, or ``preset/algorithm``. Changes this process's torch settings: run it in a child."""
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
    torch.set_num_threads(1)
    torch.backends.mkldnn.enabled = False  # its convolutions pick code paths by CPU
    torch.backends.nnpack.set_flags(False)
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


def child_env() -> dict[str, str]:
    return {**os.environ, **REPRODUCIBLE_KERNELS}


def run_in_child() -> dict[str, tuple[str, str, frozenset[str]]]:
    """``run_updates`` of every case, in a child process on the reproducible kernels."""
    out = subprocess.run(
        [sys.executable, "-m", "tests.unit.test_update_hashes", "--json"],
        env=child_env(),
        cwd=Path(__file__).resolve().parents[2],  # the repository root, where ``tests`` imports
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert out.returncode == 0, out.stderr[-4000:]
    return {
        case: (state, stats, frozenset(names))
        for case, (state, stats, names) in json.loads(out.stdout.splitlines()[-1]).items()
    }


@pytest.fixture(scope="module")
def child_results() -> dict[str, tuple[str, str, frozenset[str]]]:
    return run_in_child()


def test_the_child_runs_on_the_reproducible_kernels() -> None:
    """What makes the hashes portable: without these settings two AVX512 machines disagree."""
    code = "import torch; print(torch.backends.cpu.get_cpu_capability())"
    out = subprocess.run(
        [sys.executable, "-c", code], env=child_env(), capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "DEFAULT"


def cpu_vendor() -> str:
    """/proc/cpuinfo's vendor_id (GenuineIntel, AuthenticAMD), else what ``platform`` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("vendor_id"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


CASES = sorted(EXPECTED_BY_VENDOR["GenuineIntel"])


def test_every_vendor_pins_every_case() -> None:
    assert all(sorted(pins) == CASES for pins in EXPECTED_BY_VENDOR.values())


@pytest.mark.parametrize("case", CASES)
def test_updates_leave_the_recorded_state(case: str, child_results) -> None:
    state, stats, names = child_results[case]
    assert names == METRICS[case]
    if torch.__version__ != RECORDED_ON:
        pytest.skip(f"the hashes are torch {RECORDED_ON}'s, this is {torch.__version__}")
    vendor = cpu_vendor()
    assert vendor in EXPECTED_BY_VENDOR, (
        f"no hashes recorded on a {vendor} CPU: rerecord there ({case}: {state}, {stats})"
    )
    assert (state, stats) == EXPECTED_BY_VENDOR[vendor][case], f"{case} on {vendor}: {state}, {stats}"


if __name__ == "__main__":
    if sys.argv[1:] == ["--json"]:  # the child's side of run_in_child
        results = {name: run_updates(name) for name in CASES}
        print(
            json.dumps(
                {name: [state, stats, sorted(names)] for name, (state, stats, names) in results.items()}
            )
        )
    else:  # rerecording: through the child too, so the hashes are the portable ones
        for name, (state, stats, _) in run_in_child().items():
            print(name, (state, stats))
