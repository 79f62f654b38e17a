"""The drawer model of Drawer Open (authored here: pybullet_data has no drawer), as a URDF string.

A small cabinet of box primitives, open at the front, holding a sliding drawer whose front carries
a T-shaped handle seen from above: a vertical fin (stem) standing out of the drawer front along the
drawer axis, capped by a crossbar at its end. A top-down gripper closing across the drawer axis
pinches the stem; the cap keeps the fingers from slipping off when pulling.

Frame (cabinet base): origin on the floor at the cabinet's centre, +x = the drawer's pulling
direction (out of the front), +z up. The drawer link's frame coincides with it when closed, so the
joint position is the opening. The unlocked drawer slides on a prismatic joint in [0, OPEN_LIMIT];
the locked one is the same model with a fixed joint: same links, shapes and colours, immovable.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass

# Cabinet (outer box) and walls, m
CAB_DEPTH = 0.10  # along x (the drawer axis)
CAB_WIDTH = 0.09  # along y
CAB_HEIGHT = 0.065
WALL = 0.006
# Drawer
FRONT_X = CAB_DEPTH / 2  # drawer front face (flush with the cabinet front when closed)
FRONT_THICKNESS = 0.008
CLEARANCE = 0.001  # gap between drawer and shell on each side
TRAY_WALL = 0.004
TRAY_HEIGHT = 0.045  # top of the tray's sides and back
OPEN_LIMIT = 0.08  # prismatic joint range [0, OPEN_LIMIT]
# Handle: stem along x out of the front face, cap across its end
STEM_LENGTH = 0.05
STEM_HALF_WIDTH = 0.006
CAP_THICKNESS = 0.01
CAP_HALF_WIDTH = 0.02
HANDLE_Z = (0.015, 0.06)  # bottom and top of stem and cap
GRASP_X = FRONT_X + 0.026  # where the expert centres the fingers on the stem (cabinet frame)
HANDLE_TOP = HANDLE_Z[1]

DRAWER_MASS = 0.2  # kg
CABINET_RGBA = (0.55, 0.42, 0.3, 1.0)
DRAWER_RGBA = (0.8, 0.7, 0.5, 1.0)
HANDLE_RGBA = (0.25, 0.25, 0.28, 1.0)


@dataclass(frozen=True)
class Box:
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    rgba: tuple[float, float, float, float]

    @property
    def centre(self) -> tuple[float, ...]:
        return tuple((a + b) / 2 for a, b in zip(self.lo, self.hi, strict=True))

    @property
    def size(self) -> tuple[float, ...]:
        return tuple(b - a for a, b in zip(self.lo, self.hi, strict=True))


def cabinet_boxes() -> list[Box]:
    """The static shell: bottom, top, two sides and back; open at the front (+x)."""
    dx, dy, h, w, c = CAB_DEPTH / 2, CAB_WIDTH / 2, CAB_HEIGHT, WALL, CABINET_RGBA
    return [
        Box((-dx, -dy, 0.0), (dx, dy, w), c),  # bottom
        Box((-dx, -dy, h - w), (dx, dy, h), c),  # top
        Box((-dx, -dy, w), (dx, -dy + w, h - w), c),  # side -y
        Box((-dx, dy - w, w), (dx, dy, h - w), c),  # side +y
        Box((-dx, -dy + w, w), (-dx + w, dy - w, h - w), c),  # back
    ]


def drawer_boxes() -> list[Box]:
    """The sliding part, closed position: front plate, tray (bottom, sides, back) and handle."""
    y = CAB_WIDTH / 2 - WALL - CLEARANCE  # half width of the drawer
    z0, z1 = WALL + CLEARANCE, CAB_HEIGHT - WALL - CLEARANCE
    back = -CAB_DEPTH / 2 + WALL + CLEARANCE
    fx = FRONT_X - FRONT_THICKNESS
    t, d, hz = TRAY_WALL, DRAWER_RGBA, HANDLE_Z
    sx, cx = FRONT_X + STEM_LENGTH, FRONT_X + STEM_LENGTH + CAP_THICKNESS
    return [
        Box((fx, -y, z0), (FRONT_X, y, z1), d),  # front plate
        Box((back, -y, z0), (fx, y, z0 + t), d),  # tray bottom
        Box((back, -y, z0 + t), (fx, -y + t, TRAY_HEIGHT), d),  # tray side -y
        Box((back, y - t, z0 + t), (fx, y, TRAY_HEIGHT), d),  # tray side +y
        Box((back, -y + t, z0 + t), (back + t, y - t, TRAY_HEIGHT), d),  # tray back
        Box((FRONT_X, -STEM_HALF_WIDTH, hz[0]), (sx, STEM_HALF_WIDTH, hz[1]), HANDLE_RGBA),  # stem
        Box((sx, -CAP_HALF_WIDTH, hz[0]), (cx, CAP_HALF_WIDTH, hz[1]), HANDLE_RGBA),  # cap
    ]


def _shapes(boxes: list[Box]) -> str:
    out = []
    for b in boxes:
        xyz = " ".join(f"{v:.6f}" for v in b.centre)
        size = " ".join(f"{v:.6f}" for v in b.size)
        rgba = " ".join(f"{v:.3f}" for v in b.rgba)
        name = "rgba_" + rgba.replace(" ", "_")
        geom = f'<origin xyz="{xyz}" rpy="0 0 0"/><geometry><box size="{size}"/></geometry>'
        out.append(f'    <visual>{geom}<material name="{name}"><color rgba="{rgba}"/></material></visual>')
        out.append(f"    <collision>{geom}</collision>")
    return "\n".join(out)


def drawer_urdf(locked: bool) -> str:
    """URDF of one cabinet + drawer. ``locked`` gives the drawer a fixed joint (same looks)."""
    if locked:
        joint = '<joint name="slide" type="fixed">'
    else:
        joint = (
            '<joint name="slide" type="prismatic"><axis xyz="1 0 0"/>'
            f'<limit lower="0" upper="{OPEN_LIMIT}" effort="100" velocity="1"/>'
        )
    # inertia of a 0.08 x 0.08 x 0.05 m box of DRAWER_MASS (only needs to be plausible)
    i = DRAWER_MASS / 12 * (0.08**2 + 0.05**2)
    return f"""<?xml version="1.0"?>
<robot name="{"locked_" if locked else ""}drawer">
  <link name="cabinet">
    <inertial><mass value="0"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial>
{_shapes(cabinet_boxes())}
  </link>
  <link name="drawer">
    <inertial><origin xyz="0 0 0.03"/><mass value="{DRAWER_MASS}"/>
      <inertia ixx="{i:.6f}" ixy="0" ixz="0" iyy="{i:.6f}" iyz="0" izz="{i:.6f}"/></inertial>
{_shapes(drawer_boxes())}
  </link>
  {joint}
    <parent link="cabinet"/><child link="drawer"/><origin xyz="0 0 0" rpy="0 0 0"/>
  </joint>
</robot>
"""


def write_drawer_urdf(locked: bool, directory: str | None = None) -> str:
    """Write the URDF to a temporary file and return its path (the caller deletes it)."""
    fd, path = tempfile.mkstemp(prefix="drawer_", suffix=".urdf", dir=directory)
    with os.fdopen(fd, "w") as f:
        f.write(drawer_urdf(locked))
    return path
