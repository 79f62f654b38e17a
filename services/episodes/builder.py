"""Assemble env observations and actions into a wire Episode (T actions, T+1 observations)."""

from __future__ import annotations

import time

import numpy as np

from proto.episode import Episode, succeeded
from services.tasks.env import Observation


class EpisodeBuilder:
    """Collects one episode step by step; ``finish`` returns the validated wire message."""

    def __init__(self, *, task: str, seed: int, actor_id: str, policy_version: int, policy_kind: str,
                 is_demo: bool, segments: tuple[str, ...]) -> None:  # fmt: skip
        self.meta = dict(task=task, seed=seed, actor_id=actor_id, policy_version=policy_version,
                         policy_kind=policy_kind, is_demo=is_demo, segments=list(segments))  # fmt: skip
        self.obs: list[Observation] = []
        self.actions: list[np.ndarray] = []
        self.rewards: list[float] = []
        self.terminated: list[bool] = []
        self.truncated: list[bool] = []
        self.jump_left: int | None = None
        """A jump start's demonstration steps left at the handover (the actor's charts; not sent)."""

    def observe(self, obs: Observation) -> None:
        self.obs.append(obs)

    def step(self, action: np.ndarray, reward: float, terminated: bool, truncated: bool) -> None:
        self.actions.append(np.clip(np.asarray(action, np.float32), -1.0, 1.0))
        self.rewards.append(float(reward))
        self.terminated.append(bool(terminated))
        self.truncated.append(bool(truncated))

    @property
    def num_steps(self) -> int:
        return len(self.actions)

    @property
    def success(self) -> bool:
        return succeeded(self.terminated, self.rewards)

    def finish(self, episode_id: str) -> Episode:
        if len(self.obs) != len(self.actions) + 1 or not self.actions:
            raise ValueError(f"{len(self.obs)} observations for {len(self.actions)} actions")
        images = None
        if self.obs[0].depth_image is not None:
            images = np.stack([o.depth_image for o in self.obs])[:, None].astype(np.float16)
        elif self.obs[0].image is not None:  # a policy image the env renders itself (surgical DSA)
            images = np.stack([o.image for o in self.obs]).astype(np.uint8)
        return Episode(
            episode_id=episode_id,
            created_at=time.time(),
            points=np.stack([o.points for o in self.obs]).astype(np.float32),
            point_counts=np.stack([o.point_counts for o in self.obs]).astype(np.int32),
            jaw=np.array([o.jaw for o in self.obs], np.float32),
            actions=np.stack(self.actions).astype(np.float32),
            rewards=np.array(self.rewards, np.float32),
            terminated=np.array(self.terminated, bool),
            truncated=np.array(self.truncated, bool),
            gripper_pose=np.stack([o.gripper_pose for o in self.obs]).astype(np.float32),
            object_poses=np.stack([o.object_poses for o in self.obs]).astype(np.float32),
            contacts=np.stack([o.contacts for o in self.obs]),
            images=images,
            **self.meta,
        )
