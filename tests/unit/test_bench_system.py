"""`mea bench system`'s own pieces: its refusals and the batched policy-step table."""

from __future__ import annotations

import pytest
import torch

from mea_tools.bench.system import POLICY_PRESETS, SystemBenchConfig, bench_policy_step


@pytest.mark.parametrize(
    "bad", [{"actors": 0}, {"envs_per_actor": 0}, {"envs_per_actor": 65}, {"seconds": 0.0}]
)
def test_a_system_benchmark_that_cannot_measure_is_refused(bad):
    with pytest.raises(ValueError, match="--"):
        SystemBenchConfig(**bad)


def test_the_policy_step_table_times_one_env_and_the_actors_batch_and_restores_threads():
    threads = torch.get_num_threads()
    rows = bench_policy_step(SystemBenchConfig(envs_per_actor=4), repeats=2)
    assert [r["actor network"] for r in rows] == list(POLICY_PRESETS)
    for r in rows:
        assert r["envs per actor"] == 4 and r["ms per step, 1 env"] > 0 and r["ms per batch of 4"] > 0
        assert r["ms per env"] == pytest.approx(r["ms per batch of 4"] / 4)
        assert r["per-env cost ratio"] == pytest.approx(r["ms per step, 1 env"] / r["ms per env"])
    assert torch.get_num_threads() == threads
