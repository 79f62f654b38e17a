"""The safety envelope between a policy and a robot: what may be commanded, per robot.

Design notes: docs/architecture-notes.md, services/inference/core/envelope.py."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from proto.actions import ACTION_DIM, DELTA_THETA, DELTA_XYZ, JAW, THETA, XYZ

HOLD_REASONS = (
    "non_finite_action",
    "non_finite_observation",
    "out_of_workspace",
    "rate",
    "watchdog",
    "estop",
)
CLAMP_REASONS = ("range", "max_translation", "max_rotation", "workspace")


@dataclass(frozen=True)
class Limits:
    """One robot's envelope (SI units, the robot's base frame; defaults: the Equi-RSAC tasks' scale
    and a 40 cm x 40 cm x 30 cm box)."""

    metres_per_unit: float = DELTA_XYZ
    """What one unit of dx, dy or dz moves the gripper pivot."""
    radians_per_unit: float = DELTA_THETA
    """What one unit of dtheta turns the gripper about the vertical axis."""
    max_translation: float = 0.03
    """Longest move of one command (m)."""
    max_rotation: float = math.pi / 16
    """Largest turn of one command (rad)."""
    workspace_low: tuple[float, float, float] = (-0.2, -0.2, 0.0)
    workspace_high: tuple[float, float, float] = (0.2, 0.2, 0.3)
    """The box the pivot must stay in (m)."""
    observation_margin: float = 0.05
    """An observed pivot farther than this outside the box is refused as bad perception (m)."""
    min_interval: float = 0.0
    """Shortest time between two commands (s); 0: no rate limit."""

    def __post_init__(self) -> None:
        low, high = np.asarray(self.workspace_low, float), np.asarray(self.workspace_high, float)
        if low.shape != (3,) or high.shape != (3,) or not (low < high).all():
            raise ValueError(
                "workspace_low and workspace_high must be 3 numbers each, low < high on every axis"
            )
        values = (self.metres_per_unit, self.radians_per_unit, self.max_translation, self.max_rotation)
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(
                "metres_per_unit, radians_per_unit, max_translation and max_rotation must be > 0"
            )
        if self.observation_margin < 0 or self.min_interval < 0:
            raise ValueError("observation_margin and min_interval must be >= 0")


@dataclass(frozen=True)
class Decision:
    """The command to send and why it differs from what the policy asked for."""

    action: np.ndarray
    """float32 (5,): the normalised command actually sent."""
    hold: bool
    """True when the command is a hold (no motion)."""
    reasons: tuple[str, ...] = field(default_factory=tuple)
    """HOLD_REASONS (a hold) or CLAMP_REASONS (a clamped command); empty: sent as asked."""


class Envelope:
    """One robot session's envelope: keeps the last jaw command and the time of the last command."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self._low = np.asarray(limits.workspace_low, np.float64)
        self._high = np.asarray(limits.workspace_high, np.float64)
        self.jaw = 1.0  # open until a command closes it
        self.last_command_at: float | None = None

    def hold(self, reason: str) -> Decision:
        a = np.zeros(ACTION_DIM, np.float32)
        a[JAW] = self.jaw
        return Decision(a, True, (reason,))

    def check_observation(self, pivot: np.ndarray) -> str | None:
        """Why an observed pivot (3,) must be refused, or None."""
        p = np.asarray(pivot, np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            return "non_finite_observation"
        margin = self.limits.observation_margin
        if (p < self._low - margin).any() or (p > self._high + margin).any():
            return "out_of_workspace"
        return None

    def command(self, action: np.ndarray, pivot: np.ndarray, now: float) -> Decision:
        """The command for ``action`` from the observed ``pivot`` (m) at time ``now`` (s)."""
        a = np.asarray(action, np.float64)
        if a.shape != (ACTION_DIM,) or not np.isfinite(a).all():
            return self.hold("non_finite_action")
        bad = self.check_observation(pivot)
        if bad is not None:
            return self.hold(bad)
        lim = self.limits
        if self.last_command_at is not None and now - self.last_command_at < lim.min_interval:
            return self.hold("rate")
        reasons = []
        clipped = np.clip(a, -1.0, 1.0)
        if (clipped != a).any():
            reasons.append("range")
        move = clipped[XYZ] * lim.metres_per_unit
        length = float(np.linalg.norm(move))
        if length > lim.max_translation:
            move *= lim.max_translation / length
            reasons.append("max_translation")
        turn = float(clipped[THETA]) * lim.radians_per_unit
        if abs(turn) > lim.max_rotation:
            turn = math.copysign(lim.max_rotation, turn)
            reasons.append("max_rotation")
        p = np.asarray(pivot, np.float64)
        # an axis outside the box may only move back towards it; inside, it may not leave it
        target = np.clip(p + move, np.minimum(self._low, p), np.maximum(self._high, p))
        if not np.allclose(target - p, move, rtol=0.0, atol=1e-12):
            move = target - p
            reasons.append("workspace")
        out = np.empty(ACTION_DIM, np.float32)
        out[JAW] = clipped[JAW]
        out[XYZ] = move / lim.metres_per_unit
        out[THETA] = turn / lim.radians_per_unit
        self.jaw, self.last_command_at = float(out[JAW]), now
        return Decision(out, False, tuple(reasons))
