"""The action contract every service shares: layout, bounds and what one unit of action moves.

An action is ``(jaw, dx, dy, dz, dtheta)`` in [-1, 1]: jaw < 0 closes the gripper, > 0 opens it;
one unit of dx, dy or dz moves the gripper's pivot by ``DELTA_XYZ`` metres and one unit of dtheta
turns it by ``DELTA_THETA`` radians about the vertical axis (the Equi-RSAC tasks' scale).
"""

from __future__ import annotations

import math

ACTION_DIM = 5
"""Action layout: (jaw, dx, dy, dz, dtheta)."""
JAW, XYZ, THETA = 0, slice(1, 4), 4
"""Indices of the jaw, the translation and the rotation in an action."""
ACTION_LOW, ACTION_HIGH = -1.0, 1.0
"""Bounds of every action component."""
DELTA_XYZ = 0.05
"""Metres per unit translation action."""
DELTA_THETA = math.pi / 8
"""Radians per unit rotation action."""
