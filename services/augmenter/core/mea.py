"""Multi-Group Equivariant Augmentation (MEA), paper Sec. V, generated backwards in time.

Design notes: docs/architecture-notes.md, services/augmenter/core/mea.py."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from proto.actions import DELTA_THETA, DELTA_XYZ, THETA, XYZ
from proto.episode import Augmentation, Episode
from services.geometry import rotate_z_per_step, turn_xy, wrap_angle

GROUP_PARAM_KEYS = ("delta_r", "delta_z", "delta_rot", "delta_theta", "eps")
"""``Augmentation.params`` keys of an MEA copy holding g_t, one entry per non-trivial step: the
columns of ``draw_group``'s (delta^r, delta^z, delta^rot, delta^theta, eps), in that order."""
START_PARAM = "start"
"""``Augmentation.params`` key of an MEA copy: (1,) int64, the first source step the copy keeps."""
MEA_PARAM_KEYS = (*GROUP_PARAM_KEYS, START_PARAM)
"""Every ``Augmentation.params`` key an MEA copy carries (proto/README.md documents each)."""


@dataclass(frozen=True)
class MeaSettings:
    """Phases, group ranges and feasibility limits of MEA (defaults: the general-manipulation tasks)."""

    # The pivot sits 0.19 m above the finger tips; objects are at most 0.065 m tall.
    lz: float = 0.27
    """L_z: pivot height (m) at or above which the gripper touches nothing."""
    margin_steps: int = 1
    """Steps H_p is moved earlier (a safety margin)."""
    height_from: str = "actions"
    """How h_t is known: actions (the paper) or recorded (privileged pose)."""
    radial_scale: tuple[float, float] = (0.75, 1.0)
    """Range of delta^r."""
    height_scale: tuple[float, float] = (0.75, 1.0)
    """Range of delta^z."""
    rotation: tuple[float, float] = (0.0, 2 * math.pi)
    """Range of delta^rot (rad)."""
    theta_noise: tuple[float, float] = (0.0, 0.3)
    """Range of delta^theta."""
    discrete: bool = False
    """Discrete actions: x/y rotated by a C4 element (surgical domain)."""
    discrete_rotate_prob: float = 0.3
    """Probability of rotating a discrete x/y action."""
    max_tries: int = 20
    """Draws per step before the augmentation is cut at that step."""
    # The workspace, z = finger tips + tip_drop (the live robot: tips in [0.01, 0.25], tip_drop
    # 0.1815, so pivot z in [0.1915, 0.4315]).
    pivot_low: tuple[float, float, float] = (0.3, -0.2, 0.2)
    """Lower bounds of the gripper pivot (x, y, z), m."""
    # Audit fix: z was 0.44 ("tips + 0.19"), above the live robot's 0.4315 (Robot.pivot_bounds()),
    # so a copy could claim a pose the controller clips. 0.43 stays inside, as 0.2 does below.
    pivot_high: tuple[float, float, float] = (0.7, 0.2, 0.43)
    """Upper bounds of the gripper pivot (x, y, z), m."""
    yaw_limit: float = 2.9
    """|yaw| limit (rad) of the wrist."""
    reach_origin: tuple[float, float, float] = (-0.1, 0.0, 0.2)
    """Centre of the arm's reach sphere for the pivot."""
    reach_radius: float = 0.77
    """Radius of the arm's reach sphere for the pivot (m)."""
    # Audit fix: was 0.002. Settled free motion is within 0.4 mm of a * Delta (the controller stops
    # within 0.2 mm of each pose; measured p99 0.19 mm), but a step the workspace/reach limits
    # clipped by less than 2 mm passed as free, and every augmented state before it was off by
    # the clipped amount (`mea audit`-style replays of random episodes: 1-1.9 mm pivot offsets).
    prior_tolerance: float = 0.0005
    """Tolerance (m) of recorded motion vs a * Delta."""
    yaw_tolerance: float = 0.02
    """Tolerance (rad) of recorded yaw vs the action."""

    def __post_init__(self) -> None:
        if self.height_from not in ("actions", "recorded"):
            raise ValueError(f"height_from must be actions or recorded, not {self.height_from!r}")
        if self.margin_steps < 0 or self.max_tries < 1:
            raise ValueError("margin_steps must be >= 0 and max_tries >= 1")


# --------------------------------------------------------------------------------------------
# phases
# --------------------------------------------------------------------------------------------


def heights(ep: Episode, s: MeaSettings) -> np.ndarray:
    """h_t for t = 0..T: known initial height plus the clipped cumulative dz (or the recorded pose)."""
    if s.height_from == "recorded":
        return ep.gripper_pose[:, 2].astype(np.float64)
    h = np.empty(ep.num_steps + 1)
    h[0] = float(ep.gripper_pose[0, 2])
    for t in range(ep.num_steps):
        h[t + 1] = min(max(h[t] + float(ep.actions[t, 3]) * DELTA_XYZ, s.pivot_low[2]), s.pivot_high[2])
    return h


def phase_split(ep: Episode, s: MeaSettings) -> int:
    """H_p: first step whose gripper height is below L_z, minus the margin (T if it never is)."""
    below = np.nonzero(heights(ep, s) < s.lz)[0]
    first = int(below[0]) if len(below) else ep.num_steps
    return max(0, min(first, ep.num_steps) - s.margin_steps)


def free_motion_start(ep: Episode, hp: int, s: MeaSettings) -> int:
    """First step from which every transition before H_p moved the gripper as commanded.

    Transitions whose recorded pivot motion differs from a * Delta (workspace clipping, a blocked
    arm) break the transition prior, so no augmented step may precede them."""
    pose = ep.gripper_pose[: hp + 1].astype(np.float64)
    moved = np.diff(pose[:, :3], axis=0)
    commanded = ep.actions[:hp, XYZ].astype(np.float64) * DELTA_XYZ
    turned = np.diff(pose[:, 3]) - ep.actions[:hp, THETA].astype(np.float64) * DELTA_THETA
    turned = wrap_angle(turned)
    off = (np.linalg.norm(moved - commanded, axis=1) > s.prior_tolerance) | (np.abs(turned) > s.yaw_tolerance)
    bad = np.nonzero(off)[0]
    return int(bad[-1]) + 1 if len(bad) else 0


# --------------------------------------------------------------------------------------------
# structured actions
# --------------------------------------------------------------------------------------------


def rotate_xy(v: np.ndarray, angle: float) -> np.ndarray:
    """Rotate the first two components of ``v`` (..., >=2) by ``angle`` about z."""
    # computed in v's dtype, stored as float64
    return turn_xy(v, math.cos(angle), math.sin(angle), out=np.array(v, dtype=np.float64, copy=True))


def draw_group(rng: np.random.Generator, s: MeaSettings) -> np.ndarray:
    """g_t = (delta^r, delta^z, delta^rot, delta^theta, eps) for one step."""
    if s.discrete:
        rotate = rng.random() < s.discrete_rotate_prob
        quarter = float(rng.integers(4)) * math.pi / 2 if rotate else 0.0
        return np.array([1.0, 1.0, quarter, 0.0, 0.0])
    return np.array([
        rng.uniform(*s.radial_scale),
        rng.uniform(*s.height_scale),
        rng.uniform(*s.rotation),
        rng.uniform(*s.theta_noise),
        rng.uniform(-1.0, 1.0),
    ])  # fmt: skip


def structured_action(a: np.ndarray, g: np.ndarray, discrete: bool = False) -> np.ndarray:
    """abar_t from a_t and g_t (Sec. V-B); clipped to [-1, 1]."""
    a = np.asarray(a, dtype=np.float64)
    out = a.copy()
    if discrete:
        if np.any(a[1:3] != 0.0):  # only x/y translations take the C4 rotation
            out[1:3] = np.rint(rotate_xy(a[1:3], g[2]))
        return np.clip(out, -1.0, 1.0)
    dr, dz, rot, dtheta, eps = g
    scaled = np.array([dr * a[1], dr * a[2], dz * a[3]])
    out[XYZ] = rotate_xy(scaled, rot)
    out[THETA] = a[THETA] + dtheta * eps
    return np.clip(out, -1.0, 1.0)


# --------------------------------------------------------------------------------------------
# feasibility and the backward pass
# --------------------------------------------------------------------------------------------


def feasible(pos: np.ndarray, yaw: float, s: MeaSettings) -> bool:
    """An augmented gripper pose the robot can take without clipping or touching objects."""
    return bool(
        np.all(pos >= np.asarray(s.pivot_low) - 1e-9)
        and np.all(pos <= np.asarray(s.pivot_high) + 1e-9)
        and pos[2] >= s.lz
        and abs(yaw) <= s.yaw_limit
        and np.linalg.norm(pos - np.asarray(s.reach_origin)) <= s.reach_radius
    )


@dataclass
class MeaDraw:
    """The backward pass of one copy: augmented actions, offsets and what was rejected."""

    start: int  # first step kept (the episode is cut before it)
    hp: int  # H_p in the original step indices
    actions: np.ndarray  # (T, 5) abar (trivial phase equal to a)
    offset_xyz: np.ndarray  # (T+1, 3) D_t (0 from H_p on)
    offset_yaw: np.ndarray  # (T+1,) Theta_t
    groups: np.ndarray  # (T, 5) g_t used (NaN outside the non-trivial phase)
    rejections: int  # draws refused by the feasibility guards
    cut: bool  # the guards cut the episode short


def backward_pass(ep: Episode, s: MeaSettings, rng: np.random.Generator) -> MeaDraw:
    """Generate abar_t for t = H_p-1 down to the first step, with feasibility guards."""
    T = ep.num_steps
    hp = phase_split(ep, s)
    start = free_motion_start(ep, hp, s)
    a = ep.actions.astype(np.float64)
    abar = a.copy()
    D = np.zeros((T + 1, 3))
    theta = np.zeros(T + 1)
    groups = np.full((T, 5), np.nan)
    pose = ep.gripper_pose.astype(np.float64)
    rejections, cut = 0, False
    for t in range(hp - 1, start - 1, -1):
        for _ in range(s.max_tries):
            g = draw_group(rng, s)
            cand = structured_action(a[t], g, s.discrete)
            d = D[t + 1] + (a[t, XYZ] - cand[XYZ]) * DELTA_XYZ
            th = theta[t + 1] + (a[t, THETA] - cand[THETA]) * DELTA_THETA
            if feasible(pose[t, :3] + d, pose[t, 3] + th, s):
                abar[t], D[t], theta[t], groups[t] = cand, d, th, g
                break
            rejections += 1
        else:
            start, cut = t + 1, True
            break
    return MeaDraw(start, hp, abar, D, theta, groups, rejections, cut)


# --------------------------------------------------------------------------------------------
# the augmented episode
# --------------------------------------------------------------------------------------------


def apply_draw(ep: Episode, draw: MeaDraw) -> dict[str, np.ndarray]:
    """Augmented arrays for steps draw.start..T (observations) and draw.start..T-1 (transitions)."""
    s0 = draw.start
    points = ep.points[s0:].astype(np.float64, copy=True)
    D, theta = draw.offset_xyz[s0:], draw.offset_yaw[s0:]
    points[:, 1:] -= D[:, None, None, :]  # objects translated by -D_t
    points[:, 0] = rotate_z_per_step(points[:, 0], theta)  # gripper turned by Theta_t about its centroid
    pose = ep.gripper_pose[s0:].astype(np.float64, copy=True)
    pose[:, :3] += D
    pose[:, 3] += theta
    return {
        "points": points.astype(np.float32),
        "point_counts": np.asarray(ep.point_counts[s0:]),
        "jaw": np.asarray(ep.jaw[s0:]),
        "actions": draw.actions[s0:].astype(np.float32),
        "rewards": np.asarray(ep.rewards[s0:]),
        "terminated": np.asarray(ep.terminated[s0:]),
        "truncated": np.asarray(ep.truncated[s0:]),
        "gripper_pose": pose.astype(np.float32),
        "object_poses": np.asarray(ep.object_poses[s0:]),
        "contacts": np.asarray(ep.contacts[s0:]),
    }


def augment(
    ep: Episode, s: MeaSettings, rng: np.random.Generator, *, seed: int, copy_index: int, episode_id: str
) -> tuple[Episode | None, MeaDraw]:
    """One MEA copy of ``ep`` (None when no non-trivial step survives the guards)."""
    draw = backward_pass(ep, s, rng)
    if draw.hp - draw.start < 1:
        return None, draw
    arrays = apply_draw(ep, draw)
    n = draw.hp - draw.start
    g = draw.groups[draw.start : draw.hp]
    params = {key: g[:, c].copy() for c, key in enumerate(GROUP_PARAM_KEYS)}
    params[START_PARAM] = np.array([draw.start], np.int64)
    aug = Augmentation(source_episode_id=ep.episode_id, kind="mea", seed=seed, copy_index=copy_index,
                       phase_split=n, params=params)  # fmt: skip
    out = dataclasses.replace(ep, episode_id=episode_id, images=None, augmentation=aug, **arrays)
    return out, draw
