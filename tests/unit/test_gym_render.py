"""The gym envs render: ``render_mode="rgb_array"`` gives a third-person picture that follows the
scene, gymnasium's RecordVideo writes an MP4 of it, rendering changes no observation, and an unknown
render mode is refused."""

from __future__ import annotations

import gymnasium as gym
import imageio.v2 as imageio
import numpy as np
import pytest

import services.tasks.gym_env  # noqa: F401 - registers the ids

pytestmark = pytest.mark.unit


@pytest.mark.timeout(120)
def test_rgb_array_render_follows_the_scene_and_changes_no_observation():
    env = gym.make("mea/BlockPull-v0", points_per_segment=32, render_mode="rgb_array", render_size=128)
    plain = gym.make("mea/BlockPull-v0", points_per_segment=32)
    try:
        obs, _ = env.reset(seed=3)
        ref, _ = plain.reset(seed=3)
        assert env.metadata["render_modes"] == ["rgb_array"] and plain.render() is None
        first = env.render()
        assert first.shape == (128, 128, 3) and first.dtype == np.uint8 and first.std() > 10
        action = np.array([1.0, 1.0, 0.0, -1.0, 0.5], np.float32)  # the gripper moves: the picture too
        obs, *_ = env.step(action)
        ref, *_ = plain.step(action)
        assert np.abs(env.render().astype(int) - first).sum() > 0
        np.testing.assert_array_equal(obs["points"], ref["points"])  # rendered or not: the same
    finally:
        env.close()
        plain.close()


@pytest.mark.timeout(120)
def test_record_video_writes_the_rendered_steps(tmp_path):
    env = gym.make("mea/BlockPull-v0", points_per_segment=32, render_mode="rgb_array", render_size=128)
    folder = tmp_path / "videos"
    env = gym.wrappers.RecordVideo(env, str(folder), episode_trigger=lambda _: True, disable_logger=True)
    env.reset(seed=1)
    for _ in range(3):
        env.step(env.action_space.sample())
    env.close()  # RecordVideo writes the episode's frames so far
    (video,) = folder.glob("*.mp4")
    with imageio.get_reader(video) as reader:
        frames = [f for f in reader]
    assert len(frames) == 4 and frames[0].shape == (128, 128, 3)  # the reset and three steps


def test_an_unknown_render_mode_is_refused():
    from services.tasks.gym_env import MeaTaskEnv

    with pytest.raises(ValueError, match="render_mode must be one of"):
        MeaTaskEnv(points_per_segment=32, render_mode="ansi")
