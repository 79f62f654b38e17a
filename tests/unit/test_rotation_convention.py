"""Rotation convention, settled in the simulator: a world physically turned by +90 degrees about the
vertical through the gripper looks like ``rotate_episode(recorded, +pi/2)``, its (dx, dy) actions are
the recorded ones turned by +90 degrees, and its voxel images are ``np.rot90(image, k=1)``.

The public Equi-RSAC code and the MEA authors' fork disagree on the direction (transposed images,
transposed rotation matrix); these tests pin it, and show the opposite direction and the transpose
fail the same comparisons.

Set-up. After ``env.reset(seed)`` the gripper is teleported to PIVOT = the workspace centre (0.5, 0) at
its start height with a moderate yaw, and the settled objects are re-posed (pose arithmetic with
pybullet) by a rotation of phi about the vertical through PIVOT. phi = 0 is the recorded world,
phi = +90 degrees the rotated one. Rotating about PIVOT, which is also the centre used by
``rotate_episode`` for privileged poses, keeps block_pick's layout inside the (square) workspace and
makes the privileged poses comparable too. Seeds are not hand-picked: the first candidates whose
rotated layout passes the workspace check are used, and the check is asserted on them.

Noise floors (measured, seeds 0-7, start yaws -0.6 and 0.3, block_pick, 4 free-space steps):

* Observations hold every fused point (``points_per_segment`` above every segment's count), so the
  only noise is rendering/fusion. Per-segment Chamfer distance (mean of the two mean nearest-neighbour
  distances) between the rotated world and ``rotate_episode(recorded, +pi/2)``: 0.30-0.55 mm. It is
  this small because the camera rig (azimuths 45 + k 90 degrees) and the 4 mm fusion grid
  (0.5 / 0.004 = 125) are both mapped onto themselves by this rotation. The generic resampling floor,
  measured by translating the whole scene by ~2 mm (an exact symmetry in the gripper-centric frame),
  is 2.2-3.3 mm. Tolerance: 2 mm. Opposite direction: gripper 11.3 mm (the two-finger gripper is
  nearly C2-symmetric), cubes 80-470 mm.
* Voxel images (84 x 84, 4.8 mm pixels): pixels that differ (occupancy differs, or depths differ by
  more than one voxel level), as a fraction of the pixels occupied in either image: 0.11-0.15 for
  ``rot90(k=1)``; 0.25-0.27 for the ~2 mm translation above; >= 0.85 for ``k=-1`` and >= 0.74 for the
  transpose. Tolerance 0.30, wrong conventions must exceed 0.60.
* With the deployed 256 points per segment, random subsampling dominates (gripper ~6 mm, cubes
  1.4-2 mm); that case is checked against a floor measured in the test (a second draw of the same
  frame).
* Scripted expert (block_pick): rotated-world actions match the rotated original to <= 1.6e-3 over the
  approach. Tolerance 0.01; the opposite rotation differs by up to 2.

The baseline observation (public Equi-RSAC top-down depth image, ``depth_image=True``) is also
checked: it turns with ``k=+1`` too. pybullet's tiny renderer samples pixel corners, so the render
is shifted half a pixel to put the gripper on the documented pixel corner (last test).
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest

from proto.actions import DELTA_THETA
from proto.episode import Episode
from services.augmenter.core.isometric import WORKSPACE_CENTRE, rotate_actions, rotate_episode
from services.episodes.builder import EpisodeBuilder
from services.observation.projection import DEFAULT_SPEC, project_batch, segments_to_points
from services.tasks import EnvSettings, ManipulationEnv, make_env
from services.tasks.camera import CameraSettings, render_gripper_depth
from services.tasks.env import workspace_xy_margin
from services.tasks.robot import GRIPPER_LINKS, YAW_LIMIT, wrap

pytestmark = pytest.mark.unit

QUARTER = math.pi / 2
PIVOT_XY = np.array(WORKSPACE_CENTRE, dtype=float)
"""Where the gripper starts; the scene is rotated about the vertical through it."""
FULL_CLOUD = 3072
"""Points per segment covering every fused point (the gripper has ~2300): no subsampling noise."""
START_YAWS = (-0.6, 0.3)
"""Gripper start yaws (cycled over the cases); +90 degrees plus the turns below stay in YAW_LIMIT."""
CANDIDATE_SEEDS = range(10)
N_CASES = 3

# Free-space moves (jaw, dx, dy, dz, dtheta): the pivot stays within 5 cm of PIVOT and >= 13 cm
# above the 5 cm cubes, so nothing is touched, clipped or out of reach (all asserted).
ACTIONS = np.array(
    [
        [1.0, 0.6, 0.0, 0.0, 0.0],
        [1.0, 0.0, 0.8, -0.4, 0.5],
        [0.0, -0.5, 0.3, 0.2, -1.0],
        [1.0, 0.2, -0.9, 0.0, 0.0],
    ],
    np.float32,
)

CHAMFER_TOL = 2e-3  # m, see the module docstring
PIXEL_TOL = 0.30  # differing / occupied pixels, rotated world vs rot90(original, k=1)
PIXEL_WRONG = 0.60  # ... vs the wrong conventions (k=-1, transpose): at least this
POSE_TOL = 1e-3  # m, privileged positions (controller tolerance 0.2 mm)
YAW_TOL = 5e-3  # rad, privileged gripper yaw (controller tolerance 2 mrad)
JAW_TOL = 1e-2
EXPERT_TOL = 1e-2
YAW_MARGIN = 0.1
"""Expert test: the cube-yaw choice (nearest of 4) must be this far (in quarter turns) from a tie."""


# ------------------------------------------------------------------------------------------------
# Helpers
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def env():
    e = make_env(
        "block_pick", EnvSettings(depth_image=True, camera=CameraSettings(points_per_segment=FULL_CLOUD))
    )
    yield e
    e.close()


@pytest.fixture(scope="module")
def env_default():
    e = make_env("block_pick")
    yield e
    e.close()


def _turn_xy(xy: np.ndarray, phi: float) -> np.ndarray:
    """Rotate horizontal offsets by phi (counter-clockwise seen from above), written out by hand."""
    c, s = math.cos(phi), math.sin(phi)
    xy = np.asarray(xy, dtype=np.float64)
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], axis=-1)


def _turn_actions(actions: np.ndarray, phi: float) -> np.ndarray:
    out = np.array(actions, dtype=np.float64, copy=True)
    out[:, 1:3] = _turn_xy(actions[:, 1:3], phi)
    return out


def _rotated_layout(env: ManipulationEnv, seed: int, phi: float) -> np.ndarray:
    """(M, 7) object poses of ``seed``'s settled layout rotated by phi about the vertical through PIVOT."""
    env.reset(seed)
    turn = pb.getQuaternionFromEuler((0.0, 0.0, phi))
    out = []
    for pose in env.task.object_poses():
        offset = (pose[0] - PIVOT_XY[0], pose[1] - PIVOT_XY[1], pose[2])
        pos, quat = pb.multiplyTransforms((*PIVOT_XY, 0.0), turn, offset, pose[3:])
        out.append([*pos, *quat])
    return np.array(out)


def _stage(env: ManipulationEnv, seed: int, yaw0: float, phi: float):
    """Reset with ``seed``, then turn the scene by phi about the vertical through PIVOT: the gripper at
    PIVOT (start height) with yaw ``yaw0 + phi``, each object's settled pose rotated. Same steps for
    every phi (phi = 0 is the recorded world). Returns the first observation."""
    layout = _rotated_layout(env, seed, phi)  # resets the env
    height = env.settings.initial_tip_height + env.robot.tip_drop
    env.robot.reset(np.array([*PIVOT_XY, height]), yaw0 + phi, jaw=1.0)
    for body, pose in zip(env.task.order, layout, strict=True):
        pb.resetBasePositionAndOrientation(body, pose[:3], pose[3:], physicsClientId=env.client)
        pb.resetBaseVelocity(body, (0, 0, 0), (0, 0, 0), physicsClientId=env.client)
    for _ in range(10):  # as env.reset: let everything rest
        env.step_physics()
    assert env.t == 0
    return env.observe()


def _record(env: ManipulationEnv, seed: int, yaw0: float, phi: float, actions: np.ndarray) -> Episode:
    builder = EpisodeBuilder(task="block_pick", seed=seed, actor_id="rot", policy_version=-1,
                             policy_kind="random", is_demo=False, segments=env.segment_names)  # fmt: skip
    builder.observe(_stage(env, seed, yaw0, phi))
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        assert not info["clipped"], f"seed {seed} phi {phi:.2f}: action {a} clipped (workspace/reach/yaw)"
        builder.observe(obs)
        builder.step(a, reward, terminated, truncated)
    ep = builder.finish(f"rot-{seed}-{round(math.degrees(phi))}")
    assert not ep.contacts.any(), f"seed {seed} phi {phi:.2f}: free-space moves touched an object"
    assert not ep.terminated.any()
    return ep


def _nn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point of ``a`` to its nearest neighbour in ``b`` (chunked, float64)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    bb = (b * b).sum(axis=1)
    out = np.empty(len(a))
    for i in range(0, len(a), 512):
        x = a[i : i + 512]
        d2 = (x * x).sum(axis=1)[:, None] + bb[None, :] - 2.0 * x @ b.T
        out[i : i + 512] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
    return out


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance (m) between the distinct points of two clouds."""
    a, b = np.unique(a, axis=0), np.unique(b, axis=0)
    return 0.5 * float(_nn(a, b).mean() + _nn(b, a).mean())


def _chamfers(points_a: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """(T, S) per-frame, per-segment Chamfer distances of two (T, S, P, 3) episodes' clouds."""
    T, S = points_a.shape[:2]
    return np.array([[_chamfer(points_a[t, s], points_b[t, s]) for s in range(S)] for t in range(T)])


def _images(points: np.ndarray, counts: np.ndarray) -> np.ndarray:
    pts, valid = segments_to_points(points, counts)
    return project_batch(pts, DEFAULT_SPEC, valid)


def _differing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per frame: pixels whose occupancy differs or whose depths differ by more than one voxel level,
    as a fraction of the pixels occupied in either image."""
    occ_a, occ_b = a > 0, b > 0
    bad = (occ_a != occ_b) | (occ_a & occ_b & (np.abs(a - b) > 1.01 * DEFAULT_SPEC.voxel))
    return bad.sum(axis=(1, 2)) / np.maximum(1, (occ_a | occ_b).sum(axis=(1, 2)))


def _rot(images: np.ndarray, k: int) -> np.ndarray:
    return np.rot90(images, k=k, axes=(-2, -1))


def _inside_after_turn(env: ManipulationEnv, seed: int) -> bool:
    """Every cube of ``seed``'s layout, rotated by +90 degrees about PIVOT, in the placement area."""
    lo, hi = workspace_xy_margin(0.05)
    xy = _rotated_layout(env, seed, QUARTER)[:, :2]
    return bool(np.all((xy >= lo) & (xy <= hi)))


def _cases(env: ManipulationEnv) -> list[tuple[int, float]]:
    """(seed, start yaw): the first N_CASES candidate seeds whose layout, rotated by +90 degrees about
    PIVOT, keeps every cube inside the placement area (workspace less 5 cm); skipped seeds are
    reported in the assertion message if too few pass."""
    chosen, skipped = [], []
    for seed in CANDIDATE_SEEDS:
        (chosen if _inside_after_turn(env, seed) else skipped).append(seed)
        if len(chosen) == N_CASES:
            break
    assert len(chosen) == N_CASES, f"only seeds {chosen} pass the workspace check; skipped {skipped}"
    return [(seed, START_YAWS[i % len(START_YAWS)]) for i, seed in enumerate(chosen)]


def _check_yaw_budget(yaw0: float, actions: np.ndarray) -> None:
    turns = yaw0 + QUARTER + np.concatenate([[0.0], np.cumsum(actions[:, 4])]) * DELTA_THETA
    assert np.all(np.abs(turns) < YAW_LIMIT) and np.all(np.abs(turns - QUARTER) < YAW_LIMIT)


# ------------------------------------------------------------------------------------------------
# 1. Physically rotated world vs rotated recording
# ------------------------------------------------------------------------------------------------


def test_rotate_actions_turns_dx_dy_counter_clockwise():
    """The convention in its smallest form: +90 degrees sends (dx, dy) to (-dy, dx)."""
    a = np.array([[0.3, 0.5, -0.2, 0.7, -0.4]], np.float32)
    np.testing.assert_allclose(rotate_actions(a, QUARTER), [[0.3, 0.2, 0.5, 0.7, -0.4]], atol=1e-7)


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_physically_rotated_world_matches_rotated_episode(env):
    for seed, yaw0 in _cases(env):
        _check_yaw_budget(yaw0, ACTIONS)
        recorded = _record(env, seed, yaw0, 0.0, ACTIONS)
        replay_actions = _turn_actions(ACTIONS, QUARTER)
        rotated = _record(env, seed, yaw0, QUARTER, replay_actions)
        assert recorded.point_counts.max() < FULL_CLOUD, "observations must hold every fused point"
        assert recorded.point_counts.min() > 0 and rotated.point_counts.min() > 0, "a segment went unseen"
        aug = rotate_episode(recorded, QUARTER)
        wrong = rotate_episode(recorded, -QUARTER)
        label = f"seed {seed}, start yaw {yaw0}"

        # Actions: the replayed (physically rotated) actions are the recorded ones rotated by +90.
        np.testing.assert_allclose(rotated.actions, aug["actions"], atol=1e-6, err_msg=label)
        assert np.abs(rotated.actions - wrong["actions"]).max() > 0.5, label

        # Observations: per-segment Chamfer within the floor for +90, far outside it for -90.
        good = _chamfers(aug["points"], rotated.points)
        bad = _chamfers(wrong["points"], rotated.points)
        assert good.max() < CHAMFER_TOL, f"{label}: Chamfer (mm) per frame/segment\n{good * 1e3}"
        assert np.all(bad.max(axis=1) > 3 * CHAMFER_TOL), f"{label}: -90 Chamfer (mm)\n{bad * 1e3}"

        # Rotation leaves the jaw alone.
        np.testing.assert_allclose(rotated.jaw, recorded.jaw, atol=JAW_TOL, err_msg=label)

        # Privileged state: PIVOT is rotate_episode's centre, so its poses are the rotated world's.
        np.testing.assert_allclose(rotated.gripper_pose[:, :3], aug["gripper_pose"][:, :3], atol=POSE_TOL)
        yaw_err = [wrap(float(d)) for d in rotated.gripper_pose[:, 3] - aug["gripper_pose"][:, 3]]
        assert np.abs(yaw_err).max() < YAW_TOL, f"{label}: gripper yaw errors {yaw_err}"
        np.testing.assert_allclose(rotated.object_poses[..., :3], aug["object_poses"][..., :3], atol=POSE_TOL)
        dots = np.abs(np.sum(rotated.object_poses[..., 3:] * aug["object_poses"][..., 3:], axis=-1))
        assert dots.min() > 1 - 1e-5, f"{label}: object orientations differ: |q.q'| = {dots}"

        # Image convention: rotating the cloud by +90 is np.rot90(k=1), exactly ...
        im_rec = _images(recorded.points, recorded.point_counts)
        im_rot = _images(rotated.points, rotated.point_counts)
        assert np.array_equal(_images(aug["points"], recorded.point_counts), _rot(im_rec, 1)), label
        # ... and the physically rotated world's images are rot90(k=1) of the recorded ones up to
        # sampling noise, while k=-1 and the transpose (the other conventions) are far off.
        diff = _differing(_rot(im_rec, 1), im_rot)
        assert diff.max() < PIXEL_TOL, f"{label}: differing pixel fractions, k=1: {diff}"
        for name, other in (("k=-1", _rot(im_rec, -1)), ("transpose", np.swapaxes(im_rec, -2, -1))):
            d = _differing(other, im_rot)
            assert d.min() > PIXEL_WRONG, f"{label}: {name} matches too well: {d}"


@pytest.mark.timeout(60)
def test_baseline_depth_image_turns_with_rot90_k1_within_one_pixel(env):
    """The Equi-RSAC baseline image (rows +x, columns +y): the rotated world's image is rot90(k=1) of the
    recorded one (checked with one pixel of slack for the renderer's rasterisation of edges), while
    k=-1 and the transpose are far off even with that slack."""
    seed, yaw0 = _cases(env)[0]
    recorded = _record(env, seed, yaw0, 0.0, ACTIONS)
    rotated = _record(env, seed, yaw0, QUARTER, _turn_actions(ACTIONS, QUARTER))
    a = recorded.images[:, 0].astype(np.float32)
    b = rotated.images[:, 0].astype(np.float32)
    # the floor, each frame's farthest depth (the gripper's height above it changes from frame to frame)
    far_a = 0.99 * a.max(axis=(1, 2), keepdims=True)
    far_b = 0.99 * b.max(axis=(1, 2), keepdims=True)

    def off(ref: np.ndarray) -> np.ndarray:
        """Pixels of b no 3x3 neighbour of ref matches within 5 mm, over the pixels seen in either."""
        padded = np.pad(ref, ((0, 0), (1, 1), (1, 1)), mode="edge")
        n = b.shape[-1]
        best = np.min(
            [np.abs(padded[:, i : i + n, j : j + n] - b) for i in range(3) for j in range(3)], axis=0
        )
        seen = (ref < far_a) | (b < far_b)
        return ((best > 5e-3) & seen).sum(axis=(1, 2)) / np.maximum(1, seen.sum(axis=(1, 2)))

    # Measured: k=1 <= 0.017; k=-1 >= 0.71, transpose >= 0.67 (seeds 0-2).
    assert off(_rot(a, 1)).max() < 0.05
    assert off(_rot(a, -1)).min() > 0.4
    assert off(np.swapaxes(a, -2, -1)).min() > 0.4


@pytest.mark.timeout(60)
def test_rotation_holds_with_the_deployed_point_sampling(env_default):
    """With 256 points per segment the comparison is as good as a second random draw of the same frame
    (the floor), and -90 degrees is worse than that floor."""
    env = env_default
    seed, yaw0 = 0, START_YAWS[0]
    recorded = _record(env, seed, yaw0, 0.0, ACTIONS[:1])
    _stage(env, seed, yaw0, QUARTER)
    first = env.observe().points
    env.t = 10**6  # observe() draws its points from rng([seed, t, 1]): a different t is a fresh draw
    redraw = env.observe().points
    env.t = 0
    floor = _chamfers(first[None], redraw[None])[0]
    good = _chamfers(rotate_episode(recorded, QUARTER)["points"][:1], first[None])[0]
    bad = _chamfers(rotate_episode(recorded, -QUARTER)["points"][:1], first[None])[0]
    assert np.all(good < 1.5 * floor + 5e-4), f"floor {floor * 1e3} mm, +90 {good * 1e3} mm"
    assert np.all(bad[1:] > 3 * floor[1:]) and bad[0] > 1.5 * floor[0], f"floor {floor}, -90 {bad}"


# ------------------------------------------------------------------------------------------------
# 2. The scripted expert is equivariant
# ------------------------------------------------------------------------------------------------


def _expert_run(env: ManipulationEnv, seed: int, yaw0: float, phi: float, style: str):
    """Actions of the block_pick expert while it approaches its first cube (phase "above"), the
    distance, in quarter turns, of its cube-yaw choice from a tie, and its travel height."""
    _stage(env, seed, yaw0, phi)
    expert = env.task.expert(env, style, np.random.default_rng(0))
    body, phase = expert.plan[0]
    assert phase == "above"
    _, quat = pb.getBasePositionAndOrientation(body, physicsClientId=env.client)
    m = (env.robot.target_yaw - pb.getEulerFromQuaternion(quat)[2]) / QUARTER
    margin = 0.5 - abs(m - round(m))
    actions = []
    while expert.i == 0 and len(actions) < 6:
        actions.append(expert.act())
        env.step(actions[-1])
    return np.array(actions), margin, expert.approach.height


@pytest.mark.timeout(60)
@pytest.mark.parametrize("style", ["direct", "probe"])
def test_block_pick_expert_is_equivariant(env, style):
    """Cubes are C4-symmetric, so turning the world by +90 turns the expert's (dx, dy) by +90 and leaves
    jaw, dz and (away from a tie in the cube-yaw choice) dtheta unchanged. Seeds whose yaw choice is
    within YAW_MARGIN of a tie are skipped (deterministically, in order), and so are seeds where the
    arm's reach (not rotation-symmetric) sets a different travel height in the two worlds."""
    used, skipped, reach_limited = [], [], []
    for seed in CANDIDATE_SEEDS:
        yaw0 = START_YAWS[seed % len(START_YAWS)]
        assert _inside_after_turn(env, seed), f"seed {seed}: rotated layout leaves the workspace"
        original, margin, height = _expert_run(env, seed, yaw0, 0.0, style)
        if margin < YAW_MARGIN:
            skipped.append(seed)
            continue
        rotated, margin_rot, height_rot = _expert_run(env, seed, yaw0, QUARTER, style)
        assert abs(margin_rot - margin) < 0.01
        if abs(height_rot - height) > 1e-9:
            reach_limited.append(seed)
            continue
        n = min(len(original), len(rotated))
        assert n >= 1
        expected = _turn_actions(original[:n], QUARTER)
        label = f"{style}, seed {seed}: original {original[0]}, rotated {rotated[0]}"
        # the first action: dx, dy, dz and jaw (and dtheta, the choice being unambiguous)
        np.testing.assert_allclose(rotated[0], expected[0], atol=EXPERT_TOL, err_msg=label)
        # ... and the rest of the free-space approach
        np.testing.assert_allclose(rotated[:n], expected, atol=EXPERT_TOL, err_msg=label)
        # the opposite rotation does not fit (the first move is never along the vertical only)
        assert np.abs(original[0, 1:3]).max() > 0.1, label
        assert np.abs(rotated[0, 1:3] - _turn_actions(original[:1], -QUARTER)[0, 1:3]).max() > 0.1, label
        used.append(seed)
        if len(used) == N_CASES:
            break
    assert len(used) == N_CASES, f"used {used}, skipped (yaw tie) {skipped}, reach-limited {reach_limited}"


# ------------------------------------------------------------------------------------------------
# 3. The baseline depth image is centred on the pixel corner, like the voxel projection
# ------------------------------------------------------------------------------------------------


@pytest.mark.timeout(30)
def test_baseline_depth_image_is_centred_on_the_pixel_corner(env):
    """A cube edge a quarter pixel either side of the pivot must start at index N/2 = 42 (rows along x,
    columns along y), as pixel i covers [(i - N/2) v, (i - N/2 + 1) v). Before the half-pixel shift
    in render_gripper_depth the first covered row was 41 for an edge at -1/4 px and the first
    covered column 43 for an edge at +1/4 px."""
    c, n, span = env.client, 84, 0.4
    env.reset(0)
    env.robot.reset(np.array([*PIVOT_XY, env.settings.initial_tip_height + env.robot.tip_drop]), 0.0)
    pivot, _ = env.robot.pivot()
    cube, other = env.task.fixed, env.task.movable
    pb.resetBasePositionAndOrientation(other, (2.0, 2.0, 0.025), (0, 0, 0, 1), physicsClientId=c)
    # image scale at the cube top (z = 0.05): the camera sits 5 m above the plane 6 cm over the pivot
    scale = 5.0 / (5.0 + pivot[2] + 0.06 - 0.05)
    for link in GRIPPER_LINKS:  # as the env does: the camera sits inside the gripper
        pb.changeVisualShape(env.robot.body, link, rgbaColor=(1, 1, 1, 0), physicsClientId=c)
    found = {}
    try:
        for axis, name in ((0, "row"), (1, "column")):
            for e_px in (-0.25, 0.25):
                centre = [pivot[0] + 0.1, pivot[1] + 0.1, 0.025]  # 10 cm off the other axis
                centre[axis] = pivot[axis] + e_px * span / n / scale + 0.025  # -edge at e_px
                pb.resetBasePositionAndOrientation(cube, centre, (0, 0, 0, 1), physicsClientId=c)
                image = render_gripper_depth(c, pivot, size=n, span=span)
                found[(name, e_px)] = int(np.flatnonzero((image < 0.45).any(axis=1 - axis)).min())
    finally:
        for link in GRIPPER_LINKS:
            pb.changeVisualShape(env.robot.body, link, rgbaColor=(0.6, 0.6, 0.6, 1), physicsClientId=c)
    assert found == {key: n // 2 for key in found}, found
