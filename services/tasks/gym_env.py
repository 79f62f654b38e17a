"""gymnasium API for the tasks, so other RL libraries can use them.

Ids ``mea/BlockPull-v0``, ``mea/BlockPick-v0``, ``mea/DrawerOpen-v0``, ``mea/SurgicalGraspAny-v0``
(registered on import); ``render_mode="rgb_array"`` lets gymnasium's wrappers record an env.

Design notes: docs/architecture-notes.md, services/tasks/gym_env.py."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from proto.discrete_actions import NAMES
from services.tasks import EnvSettings, make_env
from services.tasks.camera import CameraSettings, scene_image
from services.tasks.surgical.settings import (
    FSM_STATES,
    RandomisationSettings,
    SurgicalCameraSettings,
    SurgicalSettings,
)

IDS = {"block_pull": "mea/BlockPull-v0", "block_pick": "mea/BlockPick-v0", "drawer_open": "mea/DrawerOpen-v0",
       "surgical_grasp_any": "mea/SurgicalGraspAny-v0"}  # fmt: skip
ENTRY_POINTS = {"surgical_grasp_any": "services.tasks.gym_env:SurgicalGraspGymEnv"}
"""Tasks whose gymnasium class is not ``MeaTaskEnv``."""


RENDER_MODES = ("rgb_array",)
METADATA = {"render_modes": list(RENDER_MODES), "render_fps": 10}


def _check_render_mode(render_mode: str | None) -> str | None:
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES} or None, not {render_mode!r}")
    return render_mode


class _SimGymEnv(gym.Env):
    """The gymnasium side of a task's ``sim``: reset, step, render and close; a subclass says what it
    observes (``_obs``) and how its actions become the sim's (``_sim_action``)."""

    metadata = METADATA
    sim: Any
    render_mode: str | None
    render_size: int

    def _obs(self, o) -> dict[str, Any]:
        raise NotImplementedError

    def _sim_action(self, action) -> np.ndarray:
        raise NotImplementedError

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
        o, reward, terminated, truncated, info = self.sim.step(self._sim_action(action))
        return self._obs(o), reward, terminated, truncated, {**self._info(o), **info}

    def render(self) -> np.ndarray | None:
        """The scene now, (render_size, render_size, 3) uint8, with ``render_mode="rgb_array"``."""
        return scene_image(self.sim, self.render_size) if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        self.sim.close()


class MeaTaskEnv(_SimGymEnv):
    def __init__(
        self,
        task: str = "block_pull",
        points_per_segment: int = 256,
        depth_image: bool = False,
        render_mode: str | None = None,
        render_size: int = 256,
    ) -> None:
        self.render_mode, self.render_size = _check_render_mode(render_mode), render_size
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

    def _sim_action(self, action) -> np.ndarray:
        return np.asarray(action, dtype=np.float64)


class SurgicalGraspGymEnv(_SimGymEnv):
    """Surgical Grasp Any with its discrete action space (the paper's A_d)."""

    def __init__(
        self,
        points_per_segment: int = 256,
        domain_randomisation: bool = False,
        render_mode: str | None = None,
        render_size: int = 256,
    ) -> None:
        self.render_mode, self.render_size = _check_render_mode(render_mode), render_size
        settings = SurgicalSettings(
            camera=SurgicalCameraSettings(points_per_segment=points_per_segment),
            randomisation=RandomisationSettings(enabled=domain_randomisation),
        )
        self.sim = make_env("surgical_grasp_any", settings)
        S = len(self.sim.segment_names)
        n = settings.dsa.image
        self.observation_space = spaces.Dict({
            "image": spaces.Box(0, 255, (3, n, n), np.uint8),  # the DSA policy image (services.observation.dsa)
            "points": spaces.Box(-1.0, 1.0, (S, points_per_segment, 3), np.float32),  # sim units, gripper-centric
            "jaw": spaces.Box(0.0, 1.0, (1,), np.float32),
            "controller_state": spaces.Discrete(2),
            "fsm_state": spaces.Discrete(len(FSM_STATES)),
        })  # fmt: skip
        self.action_space = spaces.Discrete(len(NAMES))

    @staticmethod
    def _obs(o) -> dict[str, Any]:
        return {"image": o.image, "points": o.points, "jaw": np.array([o.jaw], np.float32),
                "controller_state": int(o.controller_state), "fsm_state": int(o.fsm_state)}  # fmt: skip

    def _sim_action(self, action) -> np.ndarray:
        return self.sim.discrete_action(int(action))


def register_envs() -> None:
    for task, env_id in IDS.items():
        if env_id not in gym.registry:
            entry = ENTRY_POINTS.get(task, "services.tasks.gym_env:MeaTaskEnv")
            kwargs = {} if task in ENTRY_POINTS else {"task": task}
            gym.register(id=env_id, entry_point=entry, kwargs=kwargs)


register_envs()
