"""Surgical observation (``services.observation.dsa``): voxel-shift equivariance of the projection,
a gripper-centred crop, exact state-row codes, mask ids, empty and non-finite input, a plain-loop
reference for the voxeliser, noise that leaves the mask channel bit-exact, and determinism.

Clouds used for exact statements put every point at least 0.1 voxel away from any voxel boundary, so
float rounding never decides which voxel a point lands in. The test spec has 32 crop voxels resized
to 64 px: every voxel is a 2 x 2 pixel block.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from services.observation import dsa
from services.observation.dsa import (
    FSM_STATES,
    STATE_ROW,
    DsaSpec,
    camera_pose_noise,
    decode_state_rows,
    dsa_image,
    dsa_image_from_voxels,
    image_noise,
    state_blocks,
    to_occupancy,
    voxel_centroid,
    voxelize,
)

pytestmark = pytest.mark.unit

SPEC = DsaSpec(grid=128, scale=2.0, origin=(0.3, -0.1, 0.5), image=64, zoom=0.25)
PX = SPEC.image // SPEC.crop_voxels
"""Pixels per voxel of SPEC (2)."""
STATE = {"gripper_state": 0, "fsm_state": 0, "controller_state": 0}


def box(lo: tuple[int, int, int], hi: tuple[int, int, int]) -> np.ndarray:
    """(K, 3) voxel indices of the box lo <= idx < hi."""
    axes = [np.arange(a, b) for a, b in zip(lo, hi, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def cloud(vox: np.ndarray, rng: np.random.Generator, spec: DsaSpec = SPEC, per: int = 3) -> np.ndarray:
    """World points, ``per`` in each voxel of ``vox``, each >= 0.1 voxel from the voxel's faces."""
    idx = np.repeat(np.asarray(vox, dtype=np.float64), per, axis=0)
    q = (idx + rng.uniform(0.1, 0.9, idx.shape)) / spec.grid - 0.5
    return q / spec.scale + np.asarray(spec.origin)


GRIPPER = np.concatenate([box((60, 62, 70), (66, 66, 80)), box((63, 63, 80), (64, 64, 90))])
"""A jaw block with a shaft column above it (voxel indices of SPEC)."""
OBJECT = np.concatenate([box((70, 55, 50), (76, 60, 53)), box((72, 57, 53), (73, 58, 55))])
"""A block on the tray with a bump on top."""


def image(gripper: np.ndarray, obj: np.ndarray, seed: int = 0, **state: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return dsa_image(cloud(gripper, rng), cloud(obj, rng), SPEC, **{**STATE, **state})


# ------------------------------------------------------------------------------------------------
# Geometry: voxels, shifts, crop
# ------------------------------------------------------------------------------------------------


def test_voxelize_matches_plain_loop() -> None:
    rng = np.random.default_rng(1)
    spec = DsaSpec(grid=7)
    q = rng.uniform(-0.7, 0.7, (400, 3))
    q[:5] = [[-0.5, 0, 0], [0.5, 0, 0], [0, -0.5, 0.49999], [np.nan, 0, 0], [0, np.inf, 0]]
    expected = set()
    for x, y, z in q:
        cell = [(v + 0.5) * spec.grid for v in (x, y, z)]
        if all(0 <= c < spec.grid for c in cell):  # False for NaN, and inf is out of range
            expected.add(tuple(int(np.floor(c)) for c in cell))
    got = voxelize(q, spec)
    assert got.dtype == np.int64 and got.shape[1] == 3
    assert [tuple(r) for r in got.tolist()] == sorted(expected)


def test_voxel_centroid_is_mean_of_voxel_centres_and_moves_with_whole_voxels() -> None:
    rng = np.random.default_rng(2)
    c0 = voxel_centroid(cloud(OBJECT, rng), SPEC)
    assert c0 is not None
    np.testing.assert_allclose(c0, ((OBJECT + 0.5) / SPEC.grid - 0.5).mean(axis=0), atol=1e-12)
    d = np.array([3, -2, 5])
    c1 = voxel_centroid(cloud(OBJECT + d, rng), SPEC)
    np.testing.assert_allclose(c1 - c0, d / SPEC.grid, atol=1e-12)
    assert voxel_centroid(np.empty((0, 3)), SPEC) is None


def test_object_shift_by_whole_voxels_shifts_its_projection_by_pixels() -> None:
    base = image(GRIPPER, OBJECT)
    assert base[1].any()
    for dx, dy, dz in [(1, 0, 0), (0, 1, 0), (-3, 2, 0), (2, -3, 1)]:
        moved = image(GRIPPER, OBJECT + [dx, dy, dz], seed=5)
        np.testing.assert_array_equal(moved[0], base[0])  # gripper and crop unchanged
        shifted = np.roll(base[1], (PX * dx, PX * dy), axis=(0, 1))
        if dz == 0:
            np.testing.assert_array_equal(moved[1], shifted)
        else:  # one voxel higher: same footprint, every code larger
            np.testing.assert_array_equal(moved[1] > 0, shifted > 0)
            assert np.all(moved[1][shifted > 0] > shifted[shifted > 0])


def test_gripper_shift_moves_crop_so_gripper_stays_put() -> None:
    base = image(GRIPPER, OBJECT)
    for dx, dy in [(1, 0), (0, -1), (3, -2)]:
        moved = image(GRIPPER + [dx, dy, 0], OBJECT, seed=7)
        np.testing.assert_array_equal(moved[0], base[0])
        np.testing.assert_array_equal(moved[1], np.roll(base[1], (-PX * dx, -PX * dy), axis=(0, 1)))


def test_moving_both_clouds_by_whole_voxels_leaves_the_image_unchanged() -> None:
    base = image(GRIPPER, OBJECT, fsm_state=2)
    for d in [(1, 0, 0), (-2, 3, 0), (0, 0, 4), (3, -1, -7)]:
        np.testing.assert_array_equal(image(GRIPPER + d, OBJECT + d, seed=9, fsm_state=2), base)


def test_crop_is_centred_on_the_gripper_centroid() -> None:
    rng = np.random.default_rng(3)
    for _ in range(10):
        i, j = rng.integers(20, 108, 2)
        layer = box((i, j, 40), (i + rng.integers(1, 6), j + rng.integers(1, 6), 41))  # one voxel per column
        img = dsa_image(cloud(layer, rng), np.empty((0, 3)), SPEC, **STATE)
        rows, cols = np.nonzero(img[0])
        centre = (SPEC.image - 1) / 2  # pixel-centre coordinates
        assert abs(rows.mean() - centre) <= PX / 2 and abs(cols.mean() - centre) <= PX / 2


def test_orientation_rows_follow_x_columns_follow_y() -> None:
    rng = np.random.default_rng(4)
    gripper = box((64, 64, 60), (65, 65, 61))
    for (dx, dy), sign in [((5, 0), (1, 0)), ((-5, 0), (-1, 0)), ((0, 5), (0, 1)), ((0, -5), (0, -1))]:
        img = dsa_image(cloud(gripper, rng), cloud(gripper + [dx, dy, -3], rng), SPEC, **STATE)
        g = np.argwhere(img[0]).mean(axis=0)
        o = np.argwhere(img[1]).mean(axis=0)
        np.testing.assert_allclose(o - g, PX * np.array([dx, dy]))
        assert tuple(np.sign(o - g)) == sign


def test_camera_rotation_is_applied_about_the_cube_centre() -> None:
    rng = np.random.default_rng(5)
    R = camera_pose_noise(rng)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    assert (
        np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) <= 3 + 3 + 1
    )  # composed angle <= the sum
    pts = cloud(OBJECT, rng)
    np.testing.assert_allclose(to_occupancy(pts, SPEC, R), to_occupancy(pts, SPEC) @ R.T, atol=1e-15)
    g = cloud(GRIPPER, rng)
    np.testing.assert_array_equal(
        dsa_image(g, pts, SPEC, cam_rotation=np.eye(3), **STATE), dsa_image(g, pts, SPEC, **STATE)
    )
    assert not np.array_equal(
        dsa_image(g, pts, SPEC, cam_rotation=R, **STATE), dsa_image(g, pts, SPEC, **STATE)
    )
    np.testing.assert_array_equal(
        camera_pose_noise(np.random.default_rng(9)), camera_pose_noise(np.random.default_rng(9))
    )
    np.testing.assert_allclose(camera_pose_noise(rng, angles_deg=(0.0, 0.0, 0.0)), np.eye(3))


# ------------------------------------------------------------------------------------------------
# Depth codes and mask ids
# ------------------------------------------------------------------------------------------------


def test_depth_codes_follow_the_window_around_the_gripper_median() -> None:
    rng = np.random.default_rng(6)
    G, w, off = SPEC.grid, SPEC.window, SPEC.depth_offset
    kg = 80
    jaw = box((60, 60, kg), (64, 64, kg + 1))  # 16 flat columns ...
    gripper = np.concatenate([jaw, box((64, 60, kg), (65, 65, kg + 15))])  # ... and 5 taller ones
    for n in [-60, -20, -5, 0, 3, 10, 40]:  # -60 and 40 saturate at 1 and 255
        obj = box((70, 64, kg + n), (71, 65, kg + n + 1))
        img = dsa_image(
            cloud(gripper, rng), cloud(np.concatenate([obj, obj - [0, 0, 2]]), rng), SPEC, **STATE
        )
        t = (n / G + off + w / 2) / w
        expected = int(np.clip(np.floor(254 * t + 0.5) + 1, 1, 255))
        assert set(np.unique(img[1])) == {0, expected}  # the top-most voxel of the column wins
        # The median (not the mean) of the gripper's column depths is the jaw's own depth.
        jaw_px = img[0, PX * 12 : PX * 16, PX * 14 : PX * 18]  # crop starts at voxel (48, 46)
        assert set(np.unique(jaw_px)) == {int(np.floor(254 * (off + w / 2) / w + 0.5) + 1)}


def test_mask_channel_holds_only_ids_and_the_gripper_wins() -> None:
    rng = np.random.default_rng(7)
    for _ in range(5):
        g = rng.normal([0.01, 0.0, 0.05], [0.02, 0.02, 0.02], (500, 3)) / SPEC.scale + SPEC.origin
        o = rng.normal([0.0, 0.01, 0.0], [0.03, 0.03, 0.01], (500, 3)) / SPEC.scale + SPEC.origin
        img = dsa_image(g, o, SPEC, gripper_state=1, fsm_state=5, controller_state=1)
        body = slice(0, SPEC.image - 1)  # every row but the state row
        mask, gd, od = img[2, body], img[0, body], img[1, body]
        assert set(np.unique(mask)) <= {0, SPEC.object_code, SPEC.gripper_code}
        assert gd.any() and od.any() and (gd.astype(bool) & od.astype(bool)).any()  # overlap exercised
        np.testing.assert_array_equal(mask == SPEC.gripper_code, gd > 0)
        np.testing.assert_array_equal(mask == SPEC.object_code, (od > 0) & (gd == 0))


# ------------------------------------------------------------------------------------------------
# State row
# ------------------------------------------------------------------------------------------------


def test_state_rows_decode_back_for_every_combination() -> None:
    rng = np.random.default_rng(8)
    g, o = cloud(GRIPPER, rng), cloud(OBJECT, rng)
    seen = set()
    for gs, fs, cs in itertools.product(range(2), range(len(FSM_STATES)), range(2)):
        for gw, ow in [(g, o), (np.empty((0, 3)), o), (g, np.empty((0, 3)))]:
            img = dsa_image(gw, ow, SPEC, gripper_state=gs, fsm_state=fs, controller_state=cs)
            assert decode_state_rows(img) == (gs, fs, cs)
        seen.add(img[2, STATE_ROW].tobytes())
        for (a, b), code in zip(state_blocks(SPEC.image), (255 * gs, 51 * fs, 255 * cs), strict=True):
            assert np.all(img[2, STATE_ROW, a:b] == code)
    assert len(seen) == 2 * len(FSM_STATES) * 2


def test_invalid_states_and_corrupted_rows_are_rejected() -> None:
    for bad in [{"gripper_state": 2}, {"fsm_state": 6}, {"controller_state": -1}, {"fsm_state": 1.0}]:
        with pytest.raises(ValueError):
            dsa_image(np.empty((0, 3)), np.empty((0, 3)), SPEC, **{**STATE, **bad})
    img = image(GRIPPER, OBJECT, fsm_state=3)
    img[2, STATE_ROW, state_blocks(SPEC.image)[1][0]] += 1
    with pytest.raises(ValueError, match="fsm_state"):
        decode_state_rows(img)


# ------------------------------------------------------------------------------------------------
# Edge cases and determinism
# ------------------------------------------------------------------------------------------------


def test_empty_clouds_give_zero_channels() -> None:
    rng = np.random.default_rng(10)
    empty, outside = np.empty((0, 3)), np.full((5, 3), 10.0)
    for g, o in [(empty, empty), (outside, outside), (empty, cloud(OBJECT, rng))]:
        img = dsa_image(g, o, SPEC, **STATE)
        assert img.shape == (3, SPEC.image, SPEC.image) and img.dtype == np.uint8
        assert not img[:2].any() and not img[2, :STATE_ROW].any()
    img = dsa_image(cloud(GRIPPER, rng), empty, SPEC, **STATE)
    assert img[0].any() and not img[1].any()
    assert voxelize(np.empty((0, 3)), SPEC).shape == (0, 3)


def test_non_finite_points_are_ignored() -> None:
    rng = np.random.default_rng(11)
    g, o = cloud(GRIPPER, rng), cloud(OBJECT, rng)
    bad = np.array([[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf], [np.nan] * 3])
    clean = dsa_image(g, o, SPEC, **STATE)
    np.testing.assert_array_equal(
        dsa_image(np.concatenate([bad, g]), np.concatenate([o, bad]), SPEC, **STATE), clean
    )
    np.testing.assert_array_equal(voxel_centroid(np.concatenate([g, bad]), SPEC), voxel_centroid(g, SPEC))
    assert voxel_centroid(bad, SPEC) is None


def test_deterministic_and_input_untouched() -> None:
    rng = np.random.default_rng(12)
    g, o = cloud(GRIPPER, rng), cloud(OBJECT, rng)
    R = camera_pose_noise(rng)
    g0, o0 = g.copy(), o.copy()
    a = dsa_image(g, o, SPEC, cam_rotation=R, gripper_state=1, fsm_state=4, controller_state=1)
    b = dsa_image(g, o, SPEC, cam_rotation=R, gripper_state=1, fsm_state=4, controller_state=1)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(g, g0)
    np.testing.assert_array_equal(o, o0)


def test_voxel_path_equals_point_path_and_drops_shifted_out_voxels() -> None:
    rng = np.random.default_rng(13)
    g, o = cloud(GRIPPER, rng), cloud(OBJECT, rng)
    gv, ov = voxelize(to_occupancy(g, SPEC), SPEC), voxelize(to_occupancy(o, SPEC), SPEC)
    np.testing.assert_array_equal(
        dsa_image_from_voxels(gv, ov, SPEC, **STATE), dsa_image(g, o, SPEC, **STATE)
    )
    far = ov + [SPEC.grid, 0, 0]  # every voxel leaves the cube
    assert not dsa_image_from_voxels(gv, far, SPEC, **STATE)[1].any()


# ------------------------------------------------------------------------------------------------
# Image noise
# ------------------------------------------------------------------------------------------------


def test_image_noise_keeps_mask_and_state_rows_exact() -> None:
    img = image(GRIPPER, OBJECT, gripper_state=1, fsm_state=2, controller_state=1)
    before = img.copy()
    a = image_noise(img, np.random.default_rng(0))
    b = image_noise(img, np.random.default_rng(0))
    c = image_noise(img, np.random.default_rng(1))
    np.testing.assert_array_equal(img, before)  # input untouched
    np.testing.assert_array_equal(a, b)  # fixed seed, same noise
    assert not np.array_equal(a[:2], img[:2]) and not np.array_equal(a[:2], c[:2])
    for noisy in (a, c):
        np.testing.assert_array_equal(noisy[2], img[2])
        assert decode_state_rows(noisy) == (1, 2, 1)
        assert not np.any((noisy[:2] > 0) & (img[:2] == 0))  # noise never fills an empty column


def test_image_noise_parts() -> None:
    img = image(GRIPPER, OBJECT)
    off = {"cutout": (1.0, 1.0), "uniform": 0.0, "blur_sigma": 0.0}
    np.testing.assert_array_equal(image_noise(img, np.random.default_rng(0), **off), img)
    # Uniform noise: +-0.0025 * 255 = +-0.64 codes, so at most one code either way; occupancy kept.
    noisy = image_noise(img, np.random.default_rng(0), **{**off, "uniform": 0.005})
    assert np.abs(noisy[:2].astype(int) - img[:2]).max() == 1
    np.testing.assert_array_equal(noisy[:2] > 0, img[:2] > 0)
    # Cutout only empties pixels, and keeps 80 .. 100 % of each channel's occupied pixels.
    for seed in range(10):
        cut = image_noise(img, np.random.default_rng(seed), **{**off, "cutout": (0.8, 1.0)})
        kept = (cut[:2] > 0).sum(axis=(1, 2)) / (img[:2] > 0).sum(axis=(1, 2))
        assert np.all((kept >= 0.8) & (kept <= 1.0))
        np.testing.assert_array_equal(cut[:2][cut[:2] > 0], img[:2][cut[:2] > 0])
    # Blur averages over occupied pixels only: a constant patch stays constant, empty stays empty.
    flat = np.zeros_like(img)
    flat[:2, 10:20, 10:20] = 100
    np.testing.assert_array_equal(
        image_noise(flat, np.random.default_rng(0), **{**off, "blur_sigma": 5.0}), flat
    )


def test_spec_validation() -> None:
    assert DsaSpec().crop_voxels == 60 and SPEC.crop_voxels == 32
    for bad in [
        {"grid": 1},
        {"image": 2},
        {"zoom": 0.0},
        {"window": 0.0},
        {"object_code": 140},
        {"scale": np.inf},
    ]:
        with pytest.raises(ValueError):
            DsaSpec(**bad)
    assert dsa.image_noise is image_noise
