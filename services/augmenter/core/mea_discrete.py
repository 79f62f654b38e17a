"""MEA for the discrete-action surgical domain (Surgical Grasp Any): paper Sec. V and App. B, built
backwards in time from the termination like ``mea.py``.

Design notes: docs/architecture-notes.md, services/augmenter/core/mea_discrete.py."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from proto.actions import JAW
from proto.discrete_actions import TRIVIAL, index_of, rotate_c4, to_vector
from proto.episode import Augmentation, Episode
from proto.seeds import MEA_COPY_SEED_OFFSET
from services.augmenter.core.mea import START_PARAM

DISCRETE_MEA_TASKS = ("surgical_grasp_any",)
"""Tasks whose MEA copies this module makes (timestep phases, C4 actions, no isometric copies)."""
QUARTER_TURNS_PARAM = "quarter_turns"
"""``Augmentation.params`` key of a discrete MEA copy: (H_p,) int64, the quarter turns k in {0..3}
applied to each non-trivial-phase step's (dx, dy) (0: kept)."""
MEA_DISCRETE_PARAM_KEYS = (QUARTER_TURNS_PARAM, START_PARAM)
"""Every ``Augmentation.params`` key a discrete MEA copy carries (proto/README.md documents each)."""

Reproject = Callable[[Episode], Episode]
"""Re-renders a copy's images from its (moved) point clouds: gets the copy with the source's images
(rows ``start``..T) still attached, so that it can read what MEA leaves unchanged (the gripper,
FSM and controller state rows), and returns the copy with images it rendered itself."""


@dataclass(frozen=True)
class MeaDiscreteSettings:
    """Phases, group draws and feasibility limits of discrete MEA (defaults: Surgical Grasp Any)."""

    h_p: int = 5
    """Transitions kept at the end: H_p = H - h_p."""
    copies: int = 200
    """K: MEA copies per episode (the paper: 200)."""
    p_rotate: float = 0.3
    """Probability of turning a non-trivial action."""
    # Must equal the env's step (0.05 m world step x 0.3 discrete scale); the transition prior D_t rests
    # on it.
    delta_xyz: float = 0.015
    """Sim metres the pivot moves per unit of dx, dy or dz."""
    # The env's (``SurgicalGraspEnv.pivot_bounds``): its 0.5 x 0.5 x 0.35 workspace of the closed jaw
    # tips (centred at x = y = 0, above the tray at z = 0) raised by the pivot's height above the tips
    # (0.1430, calibrated by the env; a test keeps the two equal to 1e-4).
    pivot_low: tuple[float, float, float] = (-0.25, -0.25, 0.143)
    """Lower bounds of the gripper pivot (x, y, z), sim metres."""
    pivot_high: tuple[float, float, float] = (0.25, 0.25, 0.493)
    """Upper bounds of the gripper pivot (x, y, z), sim m."""
    # Recorded pivots are measured, and sit within about 2e-4 of the commanded ones the env clips
    # (the drive's settling and sag).
    bound_tolerance: float = 5e-4
    """How far (sim m) a moved pivot may lie outside the bounds."""
    max_redraws: int = 20
    """Redraws of a copy that left the workspace."""
    # A tenth of a step. The env's recorded steps follow the prior within 0.0002 (the drive's settling),
    # 0.0007 with domain randomisation's action noise (its bound: 0.0005 per axis); a workspace clip or
    # a blocked move misses by more.
    prior_tolerance: float | None = 0.0015
    """Tolerance (sim m) of recorded motion; None: off."""

    def __post_init__(self) -> None:
        if self.h_p < 0 or self.copies < 0 or self.max_redraws < 0:
            raise ValueError("h_p, copies and max_redraws must be >= 0")
        if not 0.0 <= self.p_rotate <= 1.0:
            raise ValueError(f"p_rotate must be in [0, 1], got {self.p_rotate}")
        if self.delta_xyz <= 0.0 or not np.all(np.less(self.pivot_low, self.pivot_high)):
            raise ValueError("delta_xyz must be > 0 and pivot_low < pivot_high")
        if not 0.0 <= self.bound_tolerance < self.delta_xyz:
            raise ValueError(f"bound_tolerance must be in [0, delta_xyz), got {self.bound_tolerance}")


@dataclass
class DiscreteCounts:
    """What the guards did over some copies (for the augmenter's metrics)."""

    made: int = 0
    given_up: int = 0  # copies that left the workspace on every draw, or had no step to augment
    redraws: int = 0  # draws refused by the workspace guard
    cut: int = 0  # copies cut short by the prior guard (start > 0)


# --------------------------------------------------------------------------------------------
# phases and guards
# --------------------------------------------------------------------------------------------


def phase_split(ep: Episode, s: MeaDiscreteSettings) -> int:
    """H_p = max(0, H - h_p): the first transition kept as it is."""
    return max(0, ep.num_steps - s.h_p)


def free_motion_start(ep: Episode, hp: int, s: MeaDiscreteSettings) -> int:
    """First step from which every transition before H_p moved the pivot by ``delta_xyz * a``
    (within ``prior_tolerance``); 0 when the guard is off."""
    if s.prior_tolerance is None or hp == 0:
        return 0
    moved = np.diff(ep.gripper_pose[: hp + 1, :3].astype(np.float64), axis=0)
    commanded = ep.actions[:hp, 1:4].astype(np.float64) * s.delta_xyz
    bad = np.nonzero(np.linalg.norm(moved - commanded, axis=1) > s.prior_tolerance)[0]
    return int(bad[-1]) + 1 if len(bad) else 0


def inside(pos: np.ndarray, s: MeaDiscreteSettings) -> np.ndarray:
    """Per row of ``pos`` (..., 3): the pivot lies inside the workspace (bounds included, widened by
    ``bound_tolerance``)."""
    lo, hi = np.asarray(s.pivot_low) - s.bound_tolerance, np.asarray(s.pivot_high) + s.bound_tolerance
    return np.all((pos >= lo) & (pos <= hi), axis=-1)


# --------------------------------------------------------------------------------------------
# structured actions
# --------------------------------------------------------------------------------------------


def _turn_xy(xy: np.ndarray, k: int) -> np.ndarray:
    """(dx, dy) rows turned by k quarter turns counter-clockwise, exactly (+0.0, never -0.0)."""
    x, y = xy[:, 0], xy[:, 1]
    turned = ((x, y), (-y, x), (-x, -y), (y, -x))[k % 4]
    return np.stack(turned, axis=1) + np.float32(0.0)


def rotations(actions: np.ndarray, hp: int) -> tuple[np.ndarray, np.ndarray]:
    """Every step t < ``hp`` turned by k = 0..3 quarter turns, (hp, 4, 5) float32, and which steps
    are non-trivial, (hp,) bool. A discrete step is turned by ``rotate_c4`` (identity on A'_d); a
    continuous one (the P-controller) has its (dx, dy) turned; jaw, dz and dtheta never change."""
    a = np.asarray(actions[:hp], np.float32)
    table = np.repeat(a[:, None, :], 4, axis=1)
    for k in range(1, 4):
        table[:, k, 1:3] = _turn_xy(a[:, 1:3], k)
    nontrivial = np.any(a[:, 1:3] != 0.0, axis=1)
    for t in range(hp):
        jaw_open = bool(a[t, JAW] > 0)  # every discrete action but the toggle repeats the jaw command
        index = index_of(a[t], jaw_open)
        if index is None:  # continuous, or the toggle (no (dx, dy): trivial either way)
            continue
        nontrivial[t] = index not in TRIVIAL
        table[t] = [to_vector(rotate_c4(index, k), jaw_open) for k in range(4)]
    table[:, 0] = a  # k = 0 is the source's action, bit for bit
    return table, nontrivial


def _draw(nontrivial: np.ndarray, rng: np.random.Generator, p: float) -> np.ndarray:
    """Quarter turns per step: 0 for trivial steps, else 1..3 with probability ``p``."""
    n = len(nontrivial)
    turn = rng.random(n) < p
    k = rng.integers(1, 4, size=n)
    return np.where(nontrivial & turn, k, 0).astype(np.int64)


def _pick(actions: np.ndarray, table: np.ndarray, k: np.ndarray) -> np.ndarray:
    """abar (T, 5) float32: ``table[t, k_t]`` for t < len(k), the source's action after."""
    abar = np.array(actions, np.float32, copy=True)
    abar[: len(k)] = table[np.arange(len(k)), k]
    return abar


def draw_actions(
    actions: np.ndarray, hp: int, rng: np.random.Generator, s: MeaDiscreteSettings
) -> tuple[np.ndarray, np.ndarray]:
    """abar (T, 5) float32 (the source's from ``hp`` on) and the quarter turns k (hp,) int64."""
    table, nontrivial = rotations(actions, hp)
    k = _draw(nontrivial, rng, s.p_rotate)
    return _pick(actions, table, k), k


# --------------------------------------------------------------------------------------------
# the backward pass and the copy
# --------------------------------------------------------------------------------------------


def offsets(actions: np.ndarray, abar: np.ndarray, hp: int, delta_xyz: float) -> np.ndarray:
    """D_t (T+1, 3) float64: delta_xyz * sum_{j=t}^{hp-1} (a_j - abar_j) over xyz, 0 from ``hp`` on."""
    diff = np.zeros((len(actions) + 1, 3))
    diff[:hp] = np.asarray(actions[:hp, 1:4], np.float64) - np.asarray(abar[:hp, 1:4], np.float64)
    return delta_xyz * np.cumsum(diff[::-1], axis=0)[::-1]


def cut(ep: Episode, start: int) -> Episode:
    """``ep`` from step ``start`` on (observation rows start..T, transitions start..T-1)."""
    if start == 0:
        return ep
    obs = ("points", "point_counts", "jaw", "gripper_pose", "object_poses", "contacts")
    steps = ("actions", "rewards", "terminated", "truncated")
    arrays = {name: np.asarray(getattr(ep, name))[start:] for name in (*obs, *steps)}
    images = None if ep.images is None else ep.images[start:]
    return dataclasses.replace(ep, images=images, **arrays)


def moved_arrays(ep: Episode, abar: np.ndarray, hp: int, s: MeaDiscreteSettings) -> dict[str, np.ndarray]:
    """The copy's arrays for actions ``abar`` (``ep`` already cut at ``start``): objects translated
    by -D_t in the gripper frame, pivot moved by +D_t, contacts dropped where it moved."""
    D = offsets(ep.actions, abar, hp, s.delta_xyz)[:hp]
    points = np.array(ep.points, np.float32, copy=True)
    points[:hp, 1:] = (points[:hp, 1:].astype(np.float64) - D[:, None, None, :]).astype(np.float32)
    pose = np.array(ep.gripper_pose, np.float32, copy=True)
    pose[:hp, :3] = (pose[:hp, :3].astype(np.float64) + D).astype(np.float32)
    contacts = np.array(ep.contacts, bool, copy=True)
    contacts[:hp][np.any(D != 0.0, axis=1)] = False
    return {"points": points, "gripper_pose": pose, "contacts": contacts, "actions": abar.astype(np.float32)}


@dataclass
class DiscreteDraw:
    """One copy's draw: the steps kept, the actions and quarter turns drawn, the guards' work."""

    start: int  # first source step kept
    hp: int  # H_p in the copy's rows (the source's minus start)
    abar: np.ndarray | None  # (T - start, 5) float32; None when given up
    quarter_turns: np.ndarray | None  # (hp,) int64
    redraws: int  # draws refused by the workspace guard


def draw_copy(ep: Episode, s: MeaDiscreteSettings, rng: np.random.Generator) -> tuple[Episode, DiscreteDraw]:
    """``ep`` cut at the prior guard's start, and actions drawn until the moved pivot stays inside
    the workspace (``abar`` None when no step is left to augment or every draw left it)."""
    hp_source = phase_split(ep, s)
    start = free_motion_start(ep, hp_source, s)
    sub, hp = cut(ep, start), hp_source - start
    if hp < 1:
        return sub, DiscreteDraw(start, 0, None, None, 0)
    table, nontrivial = rotations(sub.actions, hp)
    pivot = sub.gripper_pose[:hp, :3].astype(np.float64)
    for attempt in range(s.max_redraws + 1):
        k = _draw(nontrivial, rng, s.p_rotate)
        abar = _pick(sub.actions, table, k)
        D = offsets(sub.actions, abar, hp, s.delta_xyz)[:hp]
        moved = np.any(D != 0.0, axis=1)
        if np.all(inside(pivot + D, s) | ~moved):
            return sub, DiscreteDraw(start, hp, abar, k, attempt)
    return sub, DiscreteDraw(start, hp, None, None, s.max_redraws + 1)


def build_copy(
    sub: Episode, draw: DiscreteDraw, s: MeaDiscreteSettings, *, source_id: str, seed: int, copy_index: int,
    episode_id: str,
) -> Episode:  # fmt: skip
    """The copy of a successful draw (images None: the re-projection attaches them)."""
    params = {
        QUARTER_TURNS_PARAM: np.asarray(draw.quarter_turns, np.int64).copy(),
        START_PARAM: np.array([draw.start], np.int64),
    }
    aug = Augmentation(source_episode_id=source_id, kind="mea", seed=seed, copy_index=copy_index,
                       phase_split=draw.hp, params=params)  # fmt: skip
    arrays = moved_arrays(sub, draw.abar, draw.hp, s)
    return dataclasses.replace(sub, episode_id=episode_id, images=None, augmentation=aug, **arrays)


def copy_rng(seed: int, copy_index: int) -> np.random.Generator:
    """The generator of MEA copy ``copy_index`` (the pipeline's ``mea_copy_rng`` convention)."""
    return np.random.default_rng([seed, MEA_COPY_SEED_OFFSET + copy_index])


def mea_discrete_copy(
    ep: Episode, s: MeaDiscreteSettings, rng: np.random.Generator, copy_index: int, *, seed: int,
    episode_id: str | None = None,
) -> Episode | None:  # fmt: skip
    """One discrete MEA copy of ``ep`` drawn from ``rng`` (None when given up); ``seed`` is recorded
    as its provenance, ``episode_id`` defaults to ``<ep id>.mea<copy_index>``."""
    sub, draw = draw_copy(ep, s, rng)
    if draw.abar is None:
        return None
    name = f"{ep.episode_id}.mea{copy_index}" if episode_id is None else episode_id
    return build_copy(
        sub, draw, s, source_id=ep.episode_id, seed=seed, copy_index=copy_index, episode_id=name
    )


def mea_discrete_copies(
    ep: Episode, s: MeaDiscreteSettings, seed: int, reproject: Reproject | None = None, *,
    counts: DiscreteCounts | None = None,
) -> list[Episode]:  # fmt: skip
    """The kept copies among ``s.copies`` draws, copy k from ``default_rng([seed, 1_000_001 + k])``;
    each re-rendered by ``reproject`` when given, else without images. ``counts`` gets the guards'
    work added."""
    counts = DiscreteCounts() if counts is None else counts
    out = []
    for k in range(s.copies):
        sub, draw = draw_copy(ep, s, copy_rng(seed, k))
        counts.redraws += draw.redraws
        if draw.abar is None:
            counts.given_up += 1
            continue
        counts.cut += int(draw.start > 0)
        copy = build_copy(sub, draw, s, source_id=ep.episode_id, seed=seed, copy_index=k,
                          episode_id=f"{ep.episode_id}.mea{k}")  # fmt: skip
        if reproject is not None:
            copy = _reprojected(reproject, dataclasses.replace(copy, images=sub.images))
        out.append(copy)
    counts.made += len(out)
    return out


def _reprojected(reproject: Reproject, copy: Episode) -> Episode:
    """``reproject(copy)``, checked to be the same copy with one image per observation row."""
    out = reproject(copy)
    if out.episode_id != copy.episode_id or out.num_steps != copy.num_steps or out.images is None:
        raise ValueError(f"reproject must return {copy.episode_id} with its images rendered")
    if len(out.images) != out.num_steps + 1:
        raise ValueError(f"reproject gave {len(out.images)} images for {out.num_steps + 1} rows")
    return out
