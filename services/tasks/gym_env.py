"""gymnasium API for the tasks, so other RL libraries can use them.

Ids: ``mea/BlockPull-v0``, ``mea/BlockPick-v0``, ``mea/DrawerOpen-v0`` (registered on import of this
module, and through the ``gymnasium.envs`` entry point when the package is installed).
Observation: dict of ``points`` (S, P, 3) float32 in the gripper-centric frame and ``jaw`` (1,);
``depth`` (84, 84) is added with ``depth_image=True``. Privileged state goes in ``info``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from services.tasks import EnvSettings, make_env
from services.tasks.camera import CameraSettings

IDS = {"block_pull": "mea/BlockPull-v0", "block_pick": "mea/BlockPick-v0", "drawer_open": "mea/DrawerOpen-v0"}


class MeaTaskEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(
        self, task: str = "block_pull", points_per_segment: int = 256, depth_image: bool = False
    ) -> None:
        settings = EnvSettings(
            depth_image=depth_image, camera=CameraSettings(points_per_segment=points_per_segment)
        )
        self.sim = make_env(task, settings)
        S = len(self.sim.segment_names)
        obs = {
            "points": spaces.Box(-1.0, 1.0, (S, points_per_segment, 3), np.float32),  # m, gripper-centric
            "jaw": spaces.Box(0.0, 1.0, (1,), np.float32),
        }
        if depth_image:
            n = settings.depth_image_size
            obs["depth"] = spaces.Box(0.0, 0.5, (n, n), np.float32)
        self.observation_space = spaces.Dict(obs)
        self.action_space = spaces.Box(-1.0, 1.0, (5,), np.float32)

    def _obs(self, o) -> dict[str, np.ndarray]:
        out = {"points": o.points, "jaw": np.array([o.jaw], np.float32)}
        if o.depth_image is not None:
            out["depth"] = o.depth_image
        return out

    @staticmethod
    def _info(o) -> dict[str, Any]:
        return {"point_counts": o.point_counts, "gripper_pose": o.gripper_pose, "object_poses": o.object_poses,
                "contacts": o.contacts}  # fmt: skip

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        episode_seed = int(seed) if seed is not None else int(self.np_random.integers(0, 2**31 - 1))
        o = self.sim.reset(episode_seed)
        return self._obs(o), self._info(o)

    def step(self, action):
        o, reward, terminated, truncated, info = self.sim.step(np.asarray(action, dtype=np.float64))
        return self._obs(o), reward, terminated, truncated, {**self._info(o), **info}

    def close(self) -> None:
        self.sim.close()


def register_envs() -> None:
    for task, env_id in IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="services.tasks.gym_env:MeaTaskEnv", kwargs={"task": task})


register_envs()
