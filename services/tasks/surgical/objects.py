"""The three target objects of Surgical Grasp Any, built from pybullet primitives at a drawn scale.

A needle, a block and a rod, each lying flat on the tray with its base frame at its grasp point
(where the oracle centres the jaws).

Design notes: docs/architecture-notes.md, services/tasks/surgical/objects.py."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as pb

from services.tasks.surgical.settings import real

KINDS = ("needle", "block", "rod")
NEEDLE_RADIUS = real(0.007)
NEEDLE_WIRE = real(0.001)
NEEDLE_SPAN = math.radians(150.0)
NEEDLE_SEGMENTS = 8
BLOCK_HALF = (real(0.004), real(0.00175), real(0.0015))
ROD_RADIUS = real(0.0015)
ROD_LENGTH = real(0.016)
MASS = 0.01
RGBA = {"needle": (0.85, 0.85, 0.9, 1.0), "block": (0.2, 0.6, 0.9, 1.0), "rod": (0.9, 0.6, 0.2, 1.0)}


@dataclass(frozen=True)
class ObjectSpec:
    """An object drawn for an episode."""

    kind: str
    scale: float

    @property
    def height(self) -> float:
        """Top of the object above the tray when it lies flat."""
        if self.kind == "needle":
            return 2 * NEEDLE_WIRE * self.scale
        if self.kind == "block":
            return 2 * BLOCK_HALF[2] * self.scale
        return 2 * ROD_RADIUS * self.scale

    @property
    def width(self) -> float:
        """Extent across the grasp (along local y at the grasp point)."""
        if self.kind == "needle":
            return 2 * NEEDLE_WIRE * self.scale
        if self.kind == "block":
            return 2 * BLOCK_HALF[1] * self.scale
        return 2 * ROD_RADIUS * self.scale


def _horizontal(angle: float) -> tuple[float, ...]:
    """Orientation turning a shape's local z axis (capsules', cylinders') onto the horizontal
    direction ``angle``."""
    return pb.getQuaternionFromEuler((0.0, math.pi / 2, angle))


def _needle_parts(scale: float) -> tuple[list, list, list, list]:
    """(radii, lengths, positions, orientations) of the capsules along the arc, in the needle frame."""
    R, r = NEEDLE_RADIUS * scale, NEEDLE_WIRE * scale
    t = np.linspace(-NEEDLE_SPAN / 2, NEEDLE_SPAN / 2, NEEDLE_SEGMENTS + 1)
    pts = np.stack([R * np.sin(t), -R + R * np.cos(t)], axis=1)
    radii, lengths, positions, orientations = [], [], [], []
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        d = b - a
        radii.append(r)
        lengths.append(float(np.hypot(*d)))
        positions.append(((a[0] + b[0]) / 2, (a[1] + b[1]) / 2, 0.0))
        orientations.append(_horizontal(math.atan2(d[1], d[0])))
    return radii, lengths, positions, orientations


def build(client: int, spec: ObjectSpec, position, yaw: float) -> int:
    """Create the object's body lying on the tray at ``position`` (its grasp point, x, y; z is set
    from its height) turned by ``yaw``."""
    c, s = client, spec.scale
    rgba = RGBA[spec.kind]
    if spec.kind == "needle":
        radii, lengths, positions, orientations = _needle_parts(s)
        n = len(radii)
        col = pb.createCollisionShapeArray(
            [pb.GEOM_CAPSULE] * n, radii=radii, lengths=lengths, collisionFramePositions=positions,
            collisionFrameOrientations=orientations, physicsClientId=c,
        )  # fmt: skip
        vis = pb.createVisualShapeArray(
            [pb.GEOM_CAPSULE] * n, radii=radii, lengths=lengths, visualFramePositions=positions,
            visualFrameOrientations=orientations, rgbaColors=[rgba] * n, physicsClientId=c,
        )  # fmt: skip
    elif spec.kind == "block":
        half = [h * s for h in BLOCK_HALF]
        col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=c)
        vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=half, rgbaColor=rgba, physicsClientId=c)
    else:
        r, length, q = ROD_RADIUS * s, ROD_LENGTH * s, _horizontal(0.0)
        col = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=r, height=length, collisionFrameOrientation=q,
                                      physicsClientId=c)  # fmt: skip
        vis = pb.createVisualShape(pb.GEOM_CYLINDER, radius=r, length=length, visualFrameOrientation=q,
                                   rgbaColor=rgba, physicsClientId=c)  # fmt: skip
    z = spec.height / 2
    body = pb.createMultiBody(
        baseMass=MASS, baseCollisionShapeIndex=col, baseVisualShapeIndex=vis,
        basePosition=(float(position[0]), float(position[1]), z),
        baseOrientation=pb.getQuaternionFromEuler((0.0, 0.0, float(yaw))), physicsClientId=c,
    )  # fmt: skip
    pb.changeDynamics(body, -1, lateralFriction=1.0, physicsClientId=c)
    return body


def grasp_yaw(object_yaw: float) -> float:
    """Jaw yaw that closes across the object at its grasp point (one of two, pi apart)."""
    return object_yaw + math.pi / 2
