"""From one raw episode to what the replay stores: the raw episode, its isometric copies and, for
the episodes MEA applies to, its MEA copies, every one re-projected through the same voxel
projection.

Design notes: docs/architecture-notes.md, services/augmenter/core/pipeline.py."""

from __future__ import annotations

import dataclasses
import functools
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from proto.episode import Episode
from proto.seeds import MEA_COPY_SEED_OFFSET, SHARED_ROTATION_STREAM
from services.augmenter.core.isometric import ROTATION_PARAM, compose_with_mea, draw_rotation, isometric_copy
from services.augmenter.core.mea import MEA_PARAM_KEYS, MeaDraw, MeaSettings, augment
from services.augmenter.core.mea_discrete import (
    DISCRETE_MEA_TASKS,
    MEA_DISCRETE_PARAM_KEYS,
    DiscreteCounts,
    MeaDiscreteSettings,
    mea_discrete_copies,
)
from services.observation.depth_image import (
    DEFAULT_DEPTH_SPEC,
    DepthImageSpec,
    policy_images,
    rotate_images,
)
from services.observation.dsa import SURGICAL_GRASP_ANY, DsaSpec, decode_state_rows, dsa_image, world_clouds
from services.observation.projection import ProjectionSpec, segment_policy_images

MEA_ON = ("demos", "successes", "all", "none")
OBSERVATIONS = ("voxel", "depth")
"""Policy images: voxel projection of the point clouds, or the rendered depth image (Equi-RSAC)."""
AUGMENTATION_PARAM_KEYS = tuple(dict.fromkeys((ROTATION_PARAM, *MEA_PARAM_KEYS, *MEA_DISCRETE_PARAM_KEYS)))
"""Every key the augmenter puts into ``Augmentation.params`` (isometric copies: ``rotation``; MEA
copies: ``MEA_PARAM_KEYS``; MEA + isometric copies: both; discrete MEA copies:
``MEA_DISCRETE_PARAM_KEYS``). proto/README.md documents each."""


@dataclass(frozen=True)
class AugmentSettings:
    """What the augmenter makes of each raw episode."""

    mea_copies: int = 6
    """MEA copies per episode (paper: 6)."""
    mea_on: str = "demos"
    """Episodes MEA applies to: demos, successes, all, none."""
    isometric_copies: int = 4
    """Rotated copies of every stored episode (Equi-RSAC: 4)."""
    success_isometric_copies: int = 0
    """Rotated copies of each success (0: as others)."""
    isometric_on_mea: bool = True
    """Rotate an episode's MEA copies by one angle."""
    reproject: bool = True
    """Attach voxel-projected images (voxel only)."""
    seed: int = 0
    """Base seed (mixed with each episode id's hash)."""
    mea: MeaSettings = field(default_factory=MeaSettings)
    """MEA phases, group ranges and feasibility limits."""
    mea_discrete: MeaDiscreteSettings = field(default_factory=MeaDiscreteSettings)
    """MEA of the discrete-action tasks (Surgical Grasp Any): h_p, copies, C4 rate, workspace."""
    projection: ProjectionSpec = field(default_factory=ProjectionSpec)
    """Voxel projection of the observations."""
    observation: str = "voxel"
    """Policy images: voxel (projected point clouds) or depth (rendered)."""

    def __post_init__(self) -> None:
        if self.mea_on not in MEA_ON:
            raise ValueError(f"mea_on must be one of {MEA_ON}, not {self.mea_on!r}")
        if self.observation not in OBSERVATIONS:
            raise ValueError(f"observation must be one of {OBSERVATIONS}, not {self.observation!r}")
        if self.observation == "depth" and self.mea_on != "none":
            raise ValueError(
                f"observation 'depth' (the Equi-RSAC baseline) has no MEA: set mea_on 'none', not {self.mea_on!r}"
            )
        if min(self.mea_copies, self.isometric_copies, self.success_isometric_copies) < 0:
            raise ValueError("copy counts must be >= 0")

    def isometric_count(self, ep: Episode) -> int:
        """How many rotated copies ``ep`` gets."""
        if self.success_isometric_copies and ep.succeeded:
            return self.success_isometric_copies
        return self.isometric_copies

    def mea_count(self, ep: Episode) -> int:
        """How many MEA copies ``ep`` gets when MEA applies to it."""
        return self.mea_discrete.copies if ep.task in DISCRETE_MEA_TASKS else self.mea_copies

    def applies_mea(self, ep: Episode) -> bool:
        if self.mea_count(ep) == 0 or self.mea_on == "none":
            return False
        success = ep.succeeded
        return {"demos": ep.is_demo and success, "successes": success, "all": True}[self.mea_on]


@dataclass
class AugmentStats:
    """Counters of one call, for metrics."""

    outputs: int = 0
    mea_made: int = 0
    mea_empty: int = 0  # copies with no non-trivial step left after the guards
    rejections: int = 0  # group draws refused by the feasibility guards
    cuts: int = 0  # copies cut short by the guards
    transitions: int = 0


def episode_seed(base: int, episode_id: str) -> int:
    return (zlib.crc32(episode_id.encode()) ^ (base * 0x9E3779B1)) & 0x7FFF_FFFF_FFFF_FFFF


def mea_copy_rng(seed: int, copy_index: int) -> np.random.Generator:
    """The generator of MEA copy ``copy_index`` of an episode augmented with ``seed`` (its provenance
    ``Augmentation.seed``): enough to regenerate the un-rotated copy."""
    return np.random.default_rng([seed, MEA_COPY_SEED_OFFSET + copy_index])


def isometric_angle(seed: int, copy_index: int, actions: np.ndarray) -> float:
    """The angle of isometric copy ``copy_index``: no rotated (dx, dy) of ``actions`` is clipped."""
    return draw_rotation(np.random.default_rng([seed, copy_index]), [actions])


def shared_rotation(seed: int, copies: list[Episode]) -> float:
    """The one angle all MEA copies of an episode share (G_t x G), exact for every copy's actions."""
    return draw_rotation(np.random.default_rng([seed, SHARED_ROTATION_STREAM]), [c.actions for c in copies])


def isometric_copies(raw: Episode, count: int, seed: int) -> list[Episode]:
    """The ``count`` isometric copies of ``raw``, each with its own angle."""
    return [
        isometric_copy(
            raw,
            isometric_angle(seed, k, raw.actions),
            seed=seed,
            copy_index=k,
            episode_id=f"{raw.episode_id}.iso{k}",
        )
        for k in range(count)
    ]


def mea_copy(
    raw: Episode, settings: MeaSettings, seed: int, copy_index: int, episode_id: str | None = None
) -> tuple[Episode | None, MeaDraw]:
    """MEA copy ``copy_index`` of ``raw`` before any rotation, drawn from ``mea_copy_rng`` (None where
    the guards left nothing); ``episode_id`` defaults to the pipeline's ``<raw id>.mea<k>``."""
    return augment(
        raw,
        settings,
        mea_copy_rng(seed, copy_index),
        seed=seed,
        copy_index=copy_index,
        episode_id=f"{raw.episode_id}.mea{copy_index}" if episode_id is None else episode_id,
    )


def mea_copies(
    raw: Episode, settings: MeaSettings, count: int, seed: int
) -> list[tuple[Episode | None, MeaDraw]]:
    """The ``count`` MEA copies of ``raw`` before any rotation (None where the guards left nothing)."""
    return [mea_copy(raw, settings, seed, k) for k in range(count)]


def kept_mea_copies(
    raw: Episode, settings: MeaSettings, count: int, seed: int, stats: AugmentStats
) -> list[Episode]:
    """The MEA copies of ``raw`` the guards left something of, before any rotation; the guards' work
    (rejections, cut and empty copies) and the copies made are added to ``stats``."""
    made = []
    for copy, draw in mea_copies(raw, settings, count, seed):
        stats.rejections += draw.rejections
        stats.cuts += int(draw.cut)
        if copy is None:
            stats.mea_empty += 1
        else:
            made.append(copy)
    stats.mea_made += len(made)
    return made


def with_images(ep: Episode, spec: ProjectionSpec) -> Episode:
    """Attach the policy images: voxel projection of all segments + the jaw channel, uint8."""
    # == quantize(observation_channels(project_batch(points, spec, valid), ep.jaw, spec), spec)
    return dataclasses.replace(ep, images=segment_policy_images(ep.points, ep.point_counts, ep.jaw, spec))


def depth_policy_images(ep: Episode, spec: DepthImageSpec = DEFAULT_DEPTH_SPEC) -> np.ndarray:
    """The uint8 policy stack (T+1, 2, N, N) of an episode carrying rendered depth images
    (``images`` (T+1, 1, N, N) float, as recorded by the actor); ValueError naming ``images`` otherwise."""
    images = ep.images
    n = spec.size
    if images is None:
        raise ValueError(
            f"images: episode {ep.episode_id} carries no rendered depth images (observation 'depth' needs "
            "actors started with --depth-image)"
        )
    if images.ndim != 4 or images.shape[1:] != (1, n, n) or images.dtype.kind != "f":
        raise ValueError(
            f"images: episode {ep.episode_id} must carry float depth images (T+1, 1, {n}, {n}), "
            f"got {images.dtype} {images.shape}"
        )
    return policy_images(images[:, 0].astype(np.float32), ep.jaw, spec)


def _augment_depth(raw: Episode, s: AugmentSettings, seed: int) -> list[Episode]:
    """``observation == "depth"``: the raw episode and its isometric copies, each with the raw
    episode's policy images rotated by the copy's angle (drawn exactly as for voxel)."""
    codes = depth_policy_images(raw)
    out = [dataclasses.replace(raw, images=codes)]
    for copy in isometric_copies(raw, s.isometric_count(raw), seed):
        phi = float(copy.augmentation.params[ROTATION_PARAM][0])
        out.append(dataclasses.replace(copy, images=rotate_images(codes, phi)))
    return out


# --------------------------------------------------------------------------------------------
# discrete-action tasks (Surgical Grasp Any)
# --------------------------------------------------------------------------------------------


def discrete_reprojector(task: str) -> Callable[[Episode], Episode] | None:
    """The observation pipeline that re-renders MEA copies of ``task`` (``mea_discrete.Reproject``):
    ``surgical_grasp_any``'s DSA image (``reproject_dsa`` with ``dsa.SURGICAL_GRASP_ANY``, the spec the
    env renders with); None for a task without one (its copies then carry no images)."""
    if task == "surgical_grasp_any":
        return functools.partial(reproject_dsa, spec=SURGICAL_GRASP_ANY)
    return None


def reproject_dsa(copy: Episode, spec: DsaSpec) -> Episode:
    """``copy`` with every row's DSA image rendered from its own (moved) points, as the surgical env
    renders a raw row: ``dsa_image`` of ``dsa.world_clouds(points, point_counts, gripper_pose[:3])``
    (the observed rows of each segment plus the pivot, so the gripper's cloud moves with the copy's
    pivot and the object's stays where it was in the world). The state row (gripper, FSM and
    controller state), which MEA leaves unchanged, is read from the source images ``copy`` still
    carries (``dsa.decode_state_rows``); ValueError when it carries none. A row MEA did not move is
    the source's row, so it re-renders to the source's image bit for bit."""
    if copy.images is None or len(copy.images) != copy.num_steps + 1:
        raise ValueError(f"images: {copy.episode_id} must carry its source's images to read their state rows")
    n = spec.image
    images = np.empty((copy.num_steps + 1, 3, n, n), np.uint8)
    for t in range(copy.num_steps + 1):
        gripper, obj = world_clouds(copy.points[t], copy.point_counts[t], copy.gripper_pose[t, :3])
        g, f, c = decode_state_rows(copy.images[t])
        images[t] = dsa_image(gripper, obj, spec, gripper_state=g, fsm_state=f, controller_state=c)
    return dataclasses.replace(copy, images=images)


def _augment_discrete(raw: Episode, s: AugmentSettings, seed: int, stats: AugmentStats) -> list[Episode]:
    """The raw episode and, where MEA applies, its discrete MEA copies (no isometric copies)."""
    out = [raw]
    if s.applies_mea(raw):
        counts = DiscreteCounts()
        reproject = discrete_reprojector(raw.task) if s.reproject else None
        out += mea_discrete_copies(raw, s.mea_discrete, seed, reproject, counts=counts)
        stats.mea_made += counts.made
        stats.mea_empty += counts.given_up
        stats.rejections += counts.redraws
        stats.cuts += counts.cut
    return out


def augment_episode(raw: Episode, s: AugmentSettings) -> tuple[list[Episode], AugmentStats]:
    """The raw episode followed by its isometric copies and MEA copies (discrete-action tasks: the
    raw episode and its discrete MEA copies)."""
    stats = AugmentStats()
    seed = episode_seed(s.seed, raw.episode_id)
    if raw.task in DISCRETE_MEA_TASKS:
        out = _augment_discrete(raw, s, seed, stats)
        stats.outputs = len(out)
        stats.transitions = sum(e.num_steps for e in out)
        return out, stats
    if s.observation == "depth":
        out = _augment_depth(raw, s, seed)
        stats.outputs = len(out)
        stats.transitions = sum(e.num_steps for e in out)
        return out, stats
    out = [raw, *isometric_copies(raw, s.isometric_count(raw), seed)]
    if s.applies_mea(raw):
        made = kept_mea_copies(raw, s.mea, s.mea_copies, seed, stats)
        if s.isometric_on_mea and made:
            phi = shared_rotation(seed, made)
            made = [compose_with_mea(copy, phi) for copy in made]
        out += made
    if s.reproject:
        out = [with_images(e, s.projection) for e in out]
    stats.outputs = len(out)
    stats.transitions = sum(e.num_steps for e in out)
    return out, stats
