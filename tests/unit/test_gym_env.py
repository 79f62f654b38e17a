"""The gymnasium API: registered ids, spaces, seeding and the step contract."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import services.tasks.gym_env  # noqa: F401 - registers the ids

pytestmark = pytest.mark.unit


@pytest.mark.timeout(120)
def test_registered_env_follows_the_gymnasium_contract():
    env = gym.make("mea/BlockPick-v0", points_per_segment=32)
    try:
        obs, info = env.reset(seed=4)
        assert env.observation_space.contains(obs)
        again, _ = env.reset(seed=4)
        assert np.array_equal(obs["points"], again["points"])
        other, _ = env.reset(seed=5)
        assert not np.array_equal(obs["points"], other["points"])
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        assert reward in (0.0, 1.0) and isinstance(terminated, bool) and isinstance(truncated, bool)
        assert {"gripper_pose", "object_poses", "contacts", "success"} <= set(info)
        from gymnasium.utils.env_checker import check_env

        check_env(env.unwrapped, skip_render_check=True)
    finally:
        env.close()


def test_all_task_ids_are_registered():
    for env_id in ("mea/BlockPull-v0", "mea/BlockPick-v0", "mea/DrawerOpen-v0", "mea/SurgicalGraspAny-v0"):
        assert env_id in gym.registry
