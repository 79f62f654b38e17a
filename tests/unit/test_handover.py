"""The handover plays of `mea bench critic --handover`: a demo replayed, then the policy, on a toy env."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from mea_tools.bench.handover import (
    Handover,
    RecordedDemo,
    move_rows,
    move_table,
    play_handover,
    recorded_demos,
    summarize,
)
from services.common.mcap_io.recorder import McapRecorder
from tests.helpers.learner import learner_episode


@dataclass
class _Settings:
    max_steps: int = 10


class LineEnv:
    """x starts at 0 and moves by the action's first entry; success once x reaches 3."""

    settings = _Settings()

    def __init__(self) -> None:
        self.resets: list[int] = []

    def reset(self, seed: int) -> float:
        self.resets.append(seed)
        self.x = 0.0
        return self.x

    def step(self, action):
        self.x += float(action[0])
        return self.x, float(self.x >= 3), self.x >= 3, False, {}


class FixedPolicy:
    """Always proposes the same move; keeps what it saw and what it was told was executed."""

    def __init__(self, move: float) -> None:
        self.move = move
        self.seen: list[float] = []
        self.executed_actions: list[float] = []
        self.resets = 0

    def reset(self) -> None:
        self.resets += 1

    def act(self, obs) -> np.ndarray:
        self.seen.append(obs)
        return np.array([self.move, 0, 0, 0, 0], np.float32)

    def executed(self, action) -> None:
        self.executed_actions.append(float(action[0]))


DEMO = RecordedDemo("demo-0", 7, np.array([[1, 0, 0, 0, 0]] * 3, np.float32))


def play(move: float, back: int) -> tuple[Handover, FixedPolicy, LineEnv]:
    env, policy = LineEnv(), FixedPolicy(move)
    return play_handover(env, policy, lambda obs: obs, DEMO, back), policy, env


def test_a_whole_replay_reproduces_the_demo_and_tells_the_policy_every_action():
    h, policy, env = play(move=0.0, back=0)
    assert h == Handover(seed=7, replayed=3, success=True, policy_steps=0)
    assert env.resets == [7] and policy.resets == 1
    assert policy.executed_actions == [1.0, 1.0, 1.0]
    assert policy.seen == [0.0, 1.0, 2.0]  # it read every observation while the demo acted


@pytest.mark.parametrize(("move", "success", "policy_steps"), [(1.0, True, 1), (0.0, False, 8)])
def test_the_policy_finishes_from_the_demos_state_or_runs_out_of_steps(move, success, policy_steps):
    h, policy, _ = play(move, back=1)
    assert (h.replayed, h.success, h.policy_steps) == (2, success, policy_steps)
    assert policy.executed_actions == [1.0, 1.0]  # only the replayed steps are overridden
    assert policy.seen[:3] == [0.0, 1.0, 2.0]


def test_a_handover_past_the_demos_start_is_the_policy_from_the_first_step():
    h, policy, _ = play(move=1.5, back=10)
    assert (h.replayed, h.success, h.policy_steps) == (0, True, 2)
    assert policy.executed_actions == []


def test_the_summary_is_the_discounted_return_of_the_policys_part():
    plays = [Handover(0, 2, True, 1), Handover(1, 2, True, 3), Handover(2, 2, False, 8)]
    s = summarize(plays, gamma=0.9)
    assert (s["episodes"], s["successes"]) == (3, 2)
    assert s["mean_policy_steps"] == pytest.approx(2.0)
    assert s["mean_return"] == pytest.approx((1.0 + 0.81 + 0.0) / 3)
    empty = summarize([Handover(0, 2, False, 8)], gamma=0.9)
    assert math.isnan(empty["mean_policy_steps"]) and empty["mean_return"] == 0.0


def test_recorded_demos_are_the_runs_first_demonstrations_once_each(tmp_path):
    episodes = [learner_episode(3, demo=True), learner_episode(4), learner_episode(5, demo=True)]
    (tmp_path / "episodes").mkdir()
    with McapRecorder(tmp_path / "episodes" / "raw-0-0000.mcap") as rec:
        for ep in [*episodes, episodes[0]]:  # a repeated delivery is one demo
            rec.write(ep, topic="/mea/episodes/raw")
    demos = recorded_demos(tmp_path, limit=5)
    assert [(d.episode_id, d.seed) for d in demos] == [
        (episodes[0].episode_id, 3),
        (episodes[2].episode_id, 5),
    ]
    np.testing.assert_array_equal(demos[1].actions, np.asarray(episodes[2].actions, np.float32))
    assert [d.seed for d in recorded_demos(tmp_path, limit=1)] == [3]
    assert recorded_demos(tmp_path / "elsewhere", limit=5) == []


def test_a_first_action_replaces_the_policys_at_the_handover_and_counts_as_its_first_step():
    env, policy = LineEnv(), FixedPolicy(1.0)
    back = play_handover(
        env, policy, lambda obs: obs, DEMO, back=1, first=np.array([-1, 0, 0, 0, 0], np.float32)
    )
    # x: 0 -> 1 -> 2 by the demo, 1 by the reversed move, then 2, 3 by the policy
    assert (back.replayed, back.success, back.policy_steps) == (2, True, 3)
    assert policy.executed_actions == [1.0, 1.0, -1.0]  # the runtime is told the move it did not choose
    same = play_handover(LineEnv(), FixedPolicy(1.0), lambda obs: obs, DEMO, back=1, first=DEMO.actions[2])
    assert (same.success, same.policy_steps) == (True, 1)


def test_move_rows_set_the_returns_gap_beside_the_critics():
    plays = {
        "recorded": {2: [Handover(0, 1, True, 1), Handover(1, 1, True, 2)]},
        "reversed": {2: [Handover(0, 1, True, 3), Handover(1, 1, False, 9)]},
    }
    (row,) = move_rows([2], plays, {"recorded": {2: 0.8}, "reversed": {2: 0.7}}, gamma=0.9)
    assert row["episodes"] == 2 and (row["successes_recorded"], row["successes_reversed"]) == (2, 1)
    assert row["return_recorded"] == pytest.approx((1.0 + 0.9) / 2)
    assert row["return_reversed"] == pytest.approx(0.81 / 2)
    assert row["return_gap"] == pytest.approx(0.95 - 0.405)
    assert row["critic_gap"] == pytest.approx(0.1)
    (no_critic,) = move_rows([2], plays, {}, gamma=0.9)
    assert math.isnan(no_critic["critic_gap"])
    assert "| 2 | 2 | 2 / 1 | 0.950 | 0.405 | +0.545 |" in move_table([row])
