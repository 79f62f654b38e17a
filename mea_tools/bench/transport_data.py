"""Synthetic data of the transport benchmark: seeded plausible episodes and weight tensors."""

from __future__ import annotations

import time
from typing import Protocol

import numpy as np

from proto.episode import Episode
from proto.weights import WeightsBlob

MB = 1e6
SOURCE = "bench-transport"
"""The benchmark's actor, learner and source name on every message and topic."""
SEGMENTS = ("gripper", "block", "goal")


class EpisodeShape(Protocol):
    """What ``make_episode`` reads of the benchmark's config (``transport.TransportBenchConfig``)."""

    seed: int
    steps: int
    points_per_segment: int
    image_size: int


def make_episode(cfg: EpisodeShape, image_dtype: str | None, index: int = 0) -> Episode:
    """A seeded, plausible episode: smooth gripper path, objects, point clouds, optional heightmaps."""
    rng = np.random.default_rng((cfg.seed, index))
    T, S, P, H = cfg.steps, len(SEGMENTS), cfg.points_per_segment, cfg.image_size
    t = np.linspace(0.0, 1.0, T + 1)
    gripper = np.stack([0.45 + 0.1 * t, 0.08 * np.sin(2 * np.pi * t), 0.30 - 0.26 * t, 0.6 * t], axis=1)
    obj_xyz = np.empty((T + 1, S - 1, 3))
    obj_xyz[:, 0] = [0.55, 0.0, 0.02]  # block, pulled along x in the second half
    obj_xyz[:, 0, 0] -= 0.1 * np.clip(2 * t - 1, 0, 1)
    obj_xyz[:, 1] = [0.40, 0.05, 0.0]  # goal marker
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (T + 1, S - 1, 1))
    object_poses = np.concatenate([obj_xyz, quat], axis=2)

    # gripper-centric clouds: a fixed template per segment, moved by the relative position
    scale = np.array([0.02, 0.025, 0.03])[:, None, None]
    template = rng.standard_normal((S, P, 3)) * scale
    centres = np.zeros((T + 1, S, 3))
    centres[:, 1:] = obj_xyz - gripper[:, None, :3]
    points = centres[:, :, None, :] + template[None] + rng.standard_normal((T + 1, S, P, 3)) * 1e-3

    images = None
    if image_dtype is not None:
        lin = np.linspace(-0.3, 0.3, H)
        yy, xx = np.meshgrid(lin, lin, indexing="ij")
        rel = obj_xyz[:, 0, :2] - gripper[:, :2]  # block in the gripper-centred image
        d2 = (xx[None] - rel[:, 0, None, None]) ** 2 + (yy[None] - rel[:, 1, None, None]) ** 2
        height = 0.2 * np.exp(-d2 / (2 * 0.03**2)) + 0.02 * (xx[None] + 0.3)
        gripper_mask = np.exp(-(xx**2 + yy**2) / (2 * 0.02**2))[None] * (1 - 0.5 * t[:, None, None])
        imgs = np.stack([height / 0.25, np.broadcast_to(gripper_mask, height.shape)], axis=1)
        imgs = np.clip(imgs, 0.0, 1.0)
        images = np.round(imgs * 255).astype(np.uint8) if image_dtype == "uint8" else imgs.astype(np.float32)

    terminated = np.zeros(T, dtype=bool)
    terminated[-1] = True
    rewards = np.zeros(T, dtype=np.float32)
    rewards[-1] = 1.0
    actions = np.clip(np.cumsum(rng.normal(0, 0.2, (T, 5)), axis=0) / 3, -1, 1)
    contacts = np.zeros((T + 1, S - 1), dtype=bool)
    contacts[T // 2 :, 0] = True
    return Episode(
        episode_id=f"{SOURCE}-{cfg.seed}-{index}",
        task="block_pull",
        seed=cfg.seed,
        actor_id=SOURCE,
        policy_version=-1,
        policy_kind="expert_direct",
        is_demo=True,
        created_at=time.time(),
        segments=list(SEGMENTS),
        points=points.astype(np.float32),
        point_counts=rng.integers(200, 2000, (T + 1, S)).astype(np.int32),
        jaw=np.clip(1.0 - 1.5 * t, 0.0, 1.0).astype(np.float32),
        actions=actions.astype(np.float32),
        rewards=rewards,
        terminated=terminated,
        truncated=np.zeros(T, dtype=bool),
        gripper_pose=gripper.astype(np.float32),
        object_poses=object_poses.astype(np.float32),
        contacts=contacts,
        images=images,
    )


def make_tensors(size_mb: float, seed: int, parts: int = 8) -> dict[str, np.ndarray]:
    """float32 tensors totalling ``size_mb`` MB, split over a few named layers."""
    count = max(parts, int(size_mb * MB) // 4)
    rng = np.random.default_rng(seed)
    sizes = [count // parts] * parts
    sizes[-1] += count - sum(sizes)
    return {
        f"actor.layers.{i}.weight": (rng.standard_normal(n, dtype=np.float32) * 0.05)
        for i, n in enumerate(sizes)
    }


def make_blob(size_mb: float, seed: int, version: int) -> WeightsBlob:
    return WeightsBlob.create(version, "equi_rsac", SOURCE, make_tensors(size_mb, seed))
