"""Seeded synthetic episodes that obey MEA's transition prior exactly (no simulator needed).

The world has fixed object clouds and a rigid gripper cloud; the gripper moves by a*Delta and turns
by a^theta*Delta_theta per step. Used by the MEA property tests and the augment benchmark's tests.
"""

from __future__ import annotations

import math

import numpy as np

from proto.actions import DELTA_THETA, DELTA_XYZ
from proto.episode import Episode


class SyntheticWorld:
    """Objects fixed in the world, a rigid gripper cloud, the prior's transitions."""

    def __init__(self, rng: np.random.Generator, P: int = 32) -> None:
        self.objects = [
            rng.normal([0.45, -0.08, 0.025], 0.01, (P, 3)),
            rng.normal([0.55, 0.1, 0.025], 0.01, (P, 3)),
        ]
        self.gripper_local = rng.normal(0.0, 0.03, (P, 3))
        self.gripper_local -= self.gripper_local.mean(0)

    def observe(self, pos: np.ndarray, yaw: float) -> np.ndarray:
        c, s = math.cos(yaw), math.sin(yaw)
        g = self.gripper_local.copy()
        g[:, 0], g[:, 1] = (
            c * self.gripper_local[:, 0] - s * self.gripper_local[:, 1],
            (s * self.gripper_local[:, 0] + c * self.gripper_local[:, 1]),
        )
        return np.stack([g] + [o - pos for o in self.objects]).astype(np.float32)

    def rollout(self, pos0: np.ndarray, yaw0: float, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        poses = [np.array([*pos0, yaw0])]
        for a in actions:
            p = poses[-1]
            poses.append(np.array([*(p[:3] + a[1:4] * DELTA_XYZ), p[3] + a[4] * DELTA_THETA]))
        poses = np.array(poses)
        points = np.stack([self.observe(p[:3], p[3]) for p in poses])
        return points, poses


def synthetic_episode(seed: int, T: int = 20, xy: np.ndarray | None = None) -> tuple[Episode, SyntheticWorld]:
    """An approach from above (height 0.38) that goes below L_z around the middle, then contact-like
    steps; ``xy`` (T, 2) replaces the drawn (dx, dy) actions."""
    rng = np.random.default_rng(seed)
    world = SyntheticWorld(rng)
    actions = rng.uniform(-0.5, 0.5, (T, 5)).astype(np.float32)
    actions[:, 0] = np.sign(rng.uniform(-1, 1, T))
    down_at = int(rng.integers(4, T - 4))
    actions[:down_at, 3] = rng.uniform(-0.4, 0.2, down_at)  # drift while high
    actions[down_at : down_at + 3, 3] = -1.0  # descend below L_z
    actions[down_at + 3 :, 3] = 0.0
    if xy is not None:
        actions[:, 1:3] = xy
    pos0 = np.array([rng.uniform(0.4, 0.6), rng.uniform(-0.1, 0.1), 0.38])
    points, poses = world.rollout(pos0, float(rng.uniform(-1, 1)), actions)
    terminated = np.zeros(T, bool)
    terminated[-1] = True
    ep = Episode(
        episode_id=f"syn-{seed}", task="block_pick", seed=seed, actor_id="syn", policy_version=-1,
        policy_kind="expert_direct", is_demo=True, created_at=1.0, segments=["gripper", "object_0", "object_1"],
        points=points, point_counts=np.full((T + 1, 3), points.shape[2], np.int32),
        jaw=np.linspace(1, 0, T + 1).astype(np.float32), actions=actions,
        rewards=np.r_[np.zeros(T - 1), 1.0].astype(np.float32), terminated=terminated, truncated=np.zeros(T, bool),
        gripper_pose=poses.astype(np.float32), object_poses=np.zeros((T + 1, 2, 7), np.float32),
        contacts=np.zeros((T + 1, 2), bool),
    )  # fmt: skip
    return ep, world


SURGICAL_STEP = 0.015
"""Sim metres per unit action of the synthetic surgical episodes (``MeaDiscreteSettings.delta_xyz``)."""
SURGICAL_PIVOT_HEIGHT = 0.143
"""The pivot's height above the closed jaw tips (the env calibrates 0.1430)."""


def synthetic_surgical_episode(seed: int, P: int = 24, *, images: bool = True) -> Episode:
    """Surgical Grasp Any as its env records it, obeying the transition prior exactly: the hybrid
    P-controller's continuous approach (dx, dy, dz in [-1, 1], jaw open), a few discrete policy
    steps (``proto.discrete_actions``: +-x, +-y, +-z, +-yaw toward the object), then the jaw toggle
    that ends it successfully. One object fixed in the world; the pivot (``SURGICAL_PIVOT_HEIGHT``
    above the tips, as in the env) starts at x = -0.225 (the reference's x ratio -0.9) inside the
    env's pivot workspace [-0.25, 0.25]^2 x [0.143, 0.493]."""
    from proto.discrete_actions import NAMES, TOGGLE, index_of, to_vector
    from services.observation.dsa import SURGICAL_GRASP_ANY, dsa_image, world_clouds

    rng = np.random.default_rng(seed)
    obj = np.array([rng.uniform(-0.1, 0.2), rng.uniform(-0.2, 0.2), 0.03])
    obj_cloud = obj + rng.normal(0.0, 0.01, (P, 3))
    grip_local = rng.normal(0.0, 0.01, (P, 3))
    grip_local -= grip_local.mean(0)
    pos0 = np.array([-0.225, rng.uniform(-0.2, 0.2), rng.uniform(0.2, 0.3) + SURGICAL_PIVOT_HEIGHT])
    target, pos, actions = obj + np.array([0.0, 0.0, 0.08 + SURGICAL_PIVOT_HEIGHT]), pos0.copy(), []
    while np.any(np.abs(target - pos) > 0.03) and len(actions) < 60:  # the P-controller (Kp 10)
        a = np.zeros(5)
        a[0], a[1:4] = 1.0, np.clip(10.0 * (target - pos), -1.0, 1.0)
        actions.append(a)
        pos = pos + SURGICAL_STEP * a[1:4]
    for _ in range(int(rng.integers(3, 8))):  # policy steps inside the threshold
        name = str(rng.choice(["+x", "-x", "+y", "-y", "+z", "-z", "+yaw", "-yaw"]))
        actions.append(to_vector(NAMES.index(name), True).astype(np.float64))
    actions.append(to_vector(TOGGLE, True).astype(np.float64))  # close: the grasp
    actions = np.array(actions, np.float32)
    T = len(actions)
    poses = np.empty((T + 1, 4))
    poses[0] = [*pos0, rng.uniform(-0.5, 0.5)]
    for t, a in enumerate(actions.astype(np.float64)):
        poses[t + 1, :3] = poses[t, :3] + SURGICAL_STEP * a[1:4]
        poses[t + 1, 3] = poses[t, 3] + a[4] * math.pi / 4
    points = np.empty((T + 1, 2, P, 3))
    for t, (x, y, z, psi) in enumerate(poses):
        c, s = math.cos(psi), math.sin(psi)
        points[t, 0] = grip_local @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        points[t, 1] = obj_cloud - np.array([x, y, z])
    jaw = np.ones(T + 1, np.float32)
    jaw[-1] = 0.0
    terminated = np.zeros(T, bool)
    terminated[-1] = True
    contacts = np.zeros((T + 1, 1), bool)
    contacts[-1] = True
    object_poses = np.zeros((T + 1, 1, 7), np.float32)
    object_poses[:, 0, :3], object_poses[:, 0, 6] = obj, 1.0
    points, poses = points.astype(np.float32), poses.astype(np.float32)
    controller = np.r_[[index_of(a, True) is None and a[0] > 0 for a in actions], False]
    pictures = None
    if images:  # the env's DSA images of these points: jaw closed and done_success after the last step
        pictures = np.stack([
            dsa_image(*world_clouds(points[t], np.full(2, P), poses[t, :3]), SURGICAL_GRASP_ANY,
                      gripper_state=int(t == T), fsm_state=5 if t == T else 0, controller_state=int(controller[t]))
            for t in range(T + 1)
        ])  # fmt: skip
    return Episode(
        episode_id=f"sga-{seed}", task="surgical_grasp_any", seed=seed, actor_id="sga", policy_version=-1,
        policy_kind="expert_direct", is_demo=True, created_at=1.0, segments=["gripper", "object_0"],
        points=points, point_counts=np.full((T + 1, 2), P, np.int32), jaw=jaw, actions=actions,
        rewards=np.r_[np.full(T - 1, -0.001), 1.0].astype(np.float32), terminated=terminated,
        truncated=np.zeros(T, bool), gripper_pose=poses, object_poses=object_poses,
        contacts=contacts, images=pictures,
    )  # fmt: skip
