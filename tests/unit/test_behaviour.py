"""`mea bench critic --behaviour`: what a policy did, read from Block Pull's privileged state, and its
summary on fixed inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mea_tools.bench.behaviour import (
    Behaviour,
    behaviour_table,
    object_labels,
    play_behaviour,
    summarize_behaviour,
)
from mea_tools.bench.critic import CriticBenchConfig
from services.tasks import EnvSettings, make_env


class ExpertRuntime:
    """The task's privileged expert behind the runtime interface (made afresh at each reset)."""

    def __init__(self, env, style: str) -> None:
        self.env, self.style = env, style

    def reset(self) -> None:
        self.expert = self.env.task.expert(self.env, self.style, np.random.default_rng(0))

    def act(self, obs) -> np.ndarray:
        return np.asarray(self.expert.act(), np.float32)


class PressDown:
    """Jaw closed, straight down, nothing else: the policy that comes down at once and stays put."""

    def reset(self) -> None:
        pass

    def act(self, obs) -> np.ndarray:
        return np.array([-1.0, 0.0, 0.0, -1.0, 0.0], np.float32)


@pytest.fixture(scope="module")
def env():
    e = make_env("block_pull", EnvSettings(max_steps=30))
    yield e
    e.close()


def test_the_immovable_block_is_listed_first_whichever_slot_it_holds(env):
    assert object_labels(env) == ("immovable", "movable")
    slots = set()
    for seed in range(4):
        b = play_behaviour(env, ExpertRuntime(env, "direct"), lambda obs: obs, seed)
        slots.add(env.task.fixed_index())
        # the block the expert pulls is listed second, whichever slot it holds
        assert b.success and b.moved[0] < 1e-3 and b.moved[1] > 0.02
        assert b.first_near == 1 and b.near[1] > 0 and b.near[0] == 0
    assert slots == {0, 1}


def test_the_direct_expert_closes_the_gap_after_travelling(env):
    for seed in (0, 1):
        b = play_behaviour(env, ExpertRuntime(env, "direct"), lambda obs: obs, seed)
        assert b.seed == seed and b.success and b.steps < 30
        assert b.gap[1] < b.gap[0] - 0.02  # pulled towards the other block
        assert b.low_at is not None and b.low_at > 1  # it travels before it comes down


def test_the_probing_expert_goes_to_the_immovable_block_first(env):
    for seed in (0, 1):
        b = play_behaviour(env, ExpertRuntime(env, "probe"), lambda obs: obs, seed)
        assert b.success and b.first_near == 0 and min(b.near) > 0
        assert b.moved[1] > 0.02 and b.moved[0] < 1e-3


def test_pressing_down_comes_down_at_once_and_moves_nothing(env):
    b = play_behaviour(env, PressDown(), lambda obs: obs, 5)
    assert not b.success and b.steps == 30
    assert b.low_at is not None and b.low_at <= 5
    assert max(b.moved) < 1e-3 and b.gap[0] == pytest.approx(b.gap[1], abs=1e-3)


def test_the_summary_of_fixed_plays():
    plays = [
        Behaviour(0, True, 12, 4, 1, (0, 6), (0.0, 0.05), (0.20, 0.10)),
        Behaviour(1, False, 50, 2, 0, (3, 2), (0.0, 0.04), (0.18, 0.22)),
        Behaviour(2, False, 50, None, None, (0, 0), (0.0, 0.0), (0.16, 0.16)),
    ]
    s = summarize_behaviour(plays, ("immovable", "movable"))
    assert s["episodes"] == 3 and s["success"] == pytest.approx(1 / 3)
    assert s["low"] == pytest.approx(2 / 3) and s["low_by_5"] == pytest.approx(2 / 3)
    assert s["mean_low_at"] == pytest.approx(3.0)
    assert s["gap_closed"] == pytest.approx(1 / 3) and s["gap_opened"] == pytest.approx(1 / 3)
    assert s["gap_start"] == pytest.approx(0.18) and s["gap_end"] == pytest.approx((0.10 + 0.22 + 0.16) / 3)
    assert s["near_immovable"] == pytest.approx(1 / 3) and s["near_movable"] == pytest.approx(2 / 3)
    assert s["first_movable"] == pytest.approx(1 / 3) and s["first_immovable"] == pytest.approx(1 / 3)
    assert s["moved_movable"] == pytest.approx(0.03) and s["moved_immovable"] == 0.0
    table = behaviour_table(s, ("immovable", "movable"))
    assert "| 0.33 | 0.67 | 0.67 | 3.0 | 18.0 -> 16.0 | 0.33 | 0.33 |" in table
    assert "| movable | 0.67 | 0.33 | 3.0 |" in table
    never = summarize_behaviour(plays[2:], ("immovable", "movable"))
    assert never["low"] == 0.0 and math.isnan(never["mean_low_at"])
    assert summarize_behaviour([], ("a", "b")) == {"episodes": 0}


def test_a_negative_count_is_refused(tmp_path):
    with pytest.raises(ValueError, match="--behaviour"):
        CriticBenchConfig(run=tmp_path, behaviour=-1)
