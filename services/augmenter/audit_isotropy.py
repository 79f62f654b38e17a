"""How far the simulator's contact physics is from invariant under turning about the vertical.

pybullet's friction depends on a body's yaw, so a rotated copy cannot be reproduced once objects
slide; ``drag_isotropy(env)`` measures that floor, which ``mea audit`` reports beside rotated copies.

Design notes: docs/architecture-notes.md, services/augmenter/audit_isotropy.py."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pybullet is imported only where an env exists
    from services.tasks.env import ManipulationEnv

ANGLES_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
CLEAR_SPOT = (1.5, 0.0)  # m: on the floor, far from the arm and the workspace's other objects
PUSH_OVER_FRICTION = 1.5  # push force / the sliding friction force (mu_object mu_floor m g)
PUSH_SECONDS, REST_SECONDS = 0.25, 0.5


def drag_isotropy(
    env: ManipulationEnv, seed: int = 0, angles_deg: Sequence[float] = ANGLES_DEG
) -> list[dict[str, Any]]:
    """One row per angle: the movable object's slide along and across its push (mm) and its own
    turn (deg); [] for tasks without a free movable object (a drawer slides on its joint)."""
    import pybullet as pb  # deferred: pybullet, only where an env exists

    body = getattr(env.task, "movable", None)
    if body is None or pb.getNumJoints(body, physicsClientId=env.client) > 0:
        return []
    cid, hz = env.client, int(env.settings.control.sim_hz)
    mass, mu = pb.getDynamicsInfo(body, -1, physicsClientId=cid)[:2]
    mu_floor = pb.getDynamicsInfo(env.floor, -1, physicsClientId=cid)[1]
    force = PUSH_OVER_FRICTION * mu * mu_floor * mass * 9.8
    rows = []
    for deg in angles_deg:
        env.reset(seed)
        th = math.radians(deg)
        z = pb.getBasePositionAndOrientation(body, physicsClientId=cid)[0][2]
        start = np.array([*CLEAR_SPOT, z])
        pb.resetBasePositionAndOrientation(
            body, start.tolist(), pb.getQuaternionFromEuler((0, 0, th)), physicsClientId=cid
        )
        pb.resetBaseVelocity(body, (0, 0, 0), (0, 0, 0), physicsClientId=cid)
        direction = (force * math.cos(th), force * math.sin(th), 0.0)
        for _ in range(round(PUSH_SECONDS * hz)):
            pos = pb.getBasePositionAndOrientation(body, physicsClientId=cid)[0]
            bottom = pb.getAABB(body, physicsClientId=cid)[0][2] + 1e-3
            pb.applyExternalForce(
                body, -1, direction, (pos[0], pos[1], bottom), pb.WORLD_FRAME, physicsClientId=cid
            )
            pb.stepSimulation(physicsClientId=cid)
        for _ in range(round(REST_SECONDS * hz)):
            pb.stepSimulation(physicsClientId=cid)
        pos, quat = pb.getBasePositionAndOrientation(body, physicsClientId=cid)
        d = np.asarray(pos[:2]) - start[:2]
        c, s = math.cos(th), math.sin(th)
        yaw = pb.getEulerFromQuaternion(quat)[2]
        rows.append({
            "yaw (deg)": deg,
            "along (mm)": 1e3 * float(c * d[0] + s * d[1]),
            "across (mm)": 1e3 * float(-s * d[0] + c * d[1]),
            "own turn (deg)": math.degrees((yaw - th + math.pi) % (2 * math.pi) - math.pi),
        })  # fmt: skip
    env.reset(seed)
    return rows


def spread(rows: list[dict[str, Any]]) -> dict[str, float]:
    """The largest differences between angles: slide along the push and sideways drift (mm)."""
    if not rows:
        return {}
    along = [r["along (mm)"] for r in rows]
    return {
        "along spread (mm)": max(along) - min(along),
        "max sideways (mm)": max(abs(r["across (mm)"]) for r in rows),
    }


__all__ = ["ANGLES_DEG", "drag_isotropy", "spread"]
