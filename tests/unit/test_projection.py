"""Voxel-based orthogonal projection: equivariance under voxel shifts and 90-degree rotations, exact
agreement with a plain-loop reference, batch == per-frame, orientation, and uint8 quantisation.

Clouds used for exact (pixel-for-pixel) statements put every point at least 0.1 voxel away from any
voxel boundary, so float rounding never decides which voxel a point lands in.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.observation import projection as proj
from services.observation.projection import (
    ProjectionSpec,
    dequantize,
    dequantize_depth,
    observation_channels,
    project,
    project_batch,
    quantize,
    quantize_depth,
    segments_to_points,
)

pytestmark = pytest.mark.unit

SPEC = ProjectionSpec()
SMALL = ProjectionSpec(size=12, voxel=0.01, z_top=0.03, depth=0.09)
"""A small grid for the slow plain-loop reference (12 x 12 px, 9 depth levels)."""
F32_SLACK = 1e-7
"""Float32 representation error (m) allowed on top of the exact half-step quantisation bound: both
the image and its dequantised copy are float32 (ulp of 0.4 is 3e-8). It matters with the default
spec, where every depth level (k + 0.5) v = (3 k + 1.5) s sits exactly on a rounding tie."""


# ------------------------------------------------------------------------------------------------
# Helpers
# ------------------------------------------------------------------------------------------------


def n_levels(spec: ProjectionSpec) -> int:
    """Number of depth levels K = ceil(depth / v)."""
    return math.ceil(spec.depth / spec.voxel - 1e-9)


def grid_cloud(
    rng: np.random.Generator, spec: ProjectionSpec, m: int, margin: int = 0, dtype=np.float64
) -> np.ndarray:
    """m points inside the grid, each >= 0.1 voxel from every voxel boundary and >= `margin` voxels
    from the grid's faces: voxel indices (a, b, c) plus offsets in [0.1, 0.9] per axis."""
    N, K, v, h = spec.size, n_levels(spec), spec.voxel, spec.half_extent
    a = rng.integers(margin, N - margin, m)
    b = rng.integers(margin, N - margin, m)
    c = rng.integers(margin, K - margin, m)
    u = rng.uniform(0.1, 0.9, (m, 3))
    x = (a + u[:, 0]) * v - h
    y = (b + u[:, 1]) * v - h
    z = spec.z_top - (c + u[:, 2]) * v  # depth below the top plane: (c + u) v
    return np.stack([x, y, z], axis=1).astype(dtype)


def messy_cloud(rng: np.random.Generator, spec: ProjectionSpec, m: int) -> np.ndarray:
    """Uniform points over a box 20 % larger than the grid (some outside), plus a few NaN / inf."""
    h = spec.half_extent
    lo = np.array([-1.2 * h, -1.2 * h, spec.z_top - 1.2 * spec.depth])
    hi = np.array([1.2 * h, 1.2 * h, spec.z_top + 0.2 * spec.depth])
    pts = rng.uniform(lo, hi, (m, 3))
    bad = rng.choice(m, size=min(m, 5), replace=False)
    pts[bad, rng.integers(0, 3, bad.size)] = rng.choice([np.nan, np.inf, -np.inf], bad.size)
    return pts


def reference_project(points: np.ndarray, spec: ProjectionSpec) -> np.ndarray:
    """Plain-Python reference: mark occupied voxels point by point, then a triple loop over
    (row, column, depth) takes the topmost occupied voxel of each column."""
    N, K, v, h = spec.size, n_levels(spec), spec.voxel, spec.half_extent
    occupied = set()
    for x, y, z in np.asarray(points, dtype=np.float64).tolist():
        cu, cw, ck = (x + h) / v, (y + h) / v, (spec.z_top - z) / v  # NaN / inf fail the tests below
        if 0 <= cu < N and 0 <= cw < N and 0 <= ck < spec.depth / v:
            occupied.add((math.floor(cu), math.floor(cw), math.floor(ck)))
    image = np.zeros((N, N), np.float32)
    for i in range(N):
        for j in range(N):
            for k in range(K + 1):
                if (i, j, k) in occupied:
                    image[i, j] = np.float32((k + 0.5) * v)
                    break
    return image


def depth_index(image: np.ndarray, spec: ProjectionSpec) -> np.ndarray:
    """Integer depth index k of each occupied pixel ((k + 0.5) v -> k); -1 where empty."""
    k = np.rint(image.astype(np.float64) / spec.voxel - 0.5).astype(int)
    return np.where(image > 0, k, -1)


def shifted_window(a: np.ndarray, b: np.ndarray, di: int, dj: int) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping windows with b[i + di, j + dj] aligned to a[i, j]."""
    N = a.shape[0]
    ra, rb = slice(max(0, -di), N - max(0, di)), slice(max(0, di), N - max(0, -di))
    ca, cb = slice(max(0, -dj), N - max(0, dj)), slice(max(0, dj), N - max(0, -dj))
    return a[ra, ca], b[rb, cb]


# ------------------------------------------------------------------------------------------------
# 1-2. Equivariance under whole-voxel translations
# ------------------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    di=st.integers(-10, 10),
    dj=st.integers(-10, 10),
    dtype=st.sampled_from([np.float32, np.float64]),
)
def test_xy_translation_by_whole_voxels_shifts_the_image(seed, di, dj, dtype):
    rng = np.random.default_rng(seed)
    cloud = grid_cloud(rng, SPEC, 500, margin=10, dtype=dtype)
    moved = cloud + np.array([di * SPEC.voxel, dj * SPEC.voxel, 0.0], dtype=dtype)
    a, b = project(cloud, SPEC), project(moved, SPEC)
    wa, wb = shifted_window(a, b, di, dj)
    np.testing.assert_array_equal(wb, wa)
    # Nothing left the grid (margin >= shift), so the windows hold the whole footprints.
    assert np.count_nonzero(wa) == np.count_nonzero(a) == np.count_nonzero(b)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("dk", [-7, -1, 1, 3, 12])
def test_z_translation_by_whole_voxels_shifts_depth_and_keeps_footprint(seed, dk):
    rng = np.random.default_rng(seed)
    cloud = grid_cloud(rng, SPEC, 800, margin=12)
    moved = cloud - np.array([0.0, 0.0, dk * SPEC.voxel])  # dk voxels further down
    a, b = project(cloud, SPEC), project(moved, SPEC)
    np.testing.assert_array_equal(b > 0, a > 0)
    ka, kb = depth_index(a, SPEC), depth_index(b, SPEC)
    footprint = a > 0
    np.testing.assert_array_equal(kb[footprint], ka[footprint] + dk)
    np.testing.assert_array_equal(b[footprint], SPEC.depth_levels[kb[footprint]])  # exactly (k + 0.5) v


# ------------------------------------------------------------------------------------------------
# 3-4. Reference and batch agreement
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_matches_plain_loop_reference_on_small_grid(seed, dtype):
    rng = np.random.default_rng(seed)
    cloud = messy_cloud(rng, SMALL, 300).astype(dtype)
    np.testing.assert_array_equal(project(cloud, SMALL), reference_project(cloud, SMALL))


@pytest.mark.parametrize("seed", range(2))
def test_matches_plain_loop_reference_on_default_grid(seed):
    rng = np.random.default_rng(100 + seed)
    cloud = messy_cloud(rng, SPEC, 2000).astype(np.float32)
    np.testing.assert_array_equal(project(cloud, SPEC), reference_project(cloud, SPEC))


@pytest.mark.parametrize(("T", "M"), [(1, 50), (13, 3000), (3, 20000), (7, 1)])
def test_batch_equals_per_frame(T, M):
    rng = np.random.default_rng(T * 1000 + M)
    clouds = np.stack([messy_cloud(rng, SPEC, M) for _ in range(T)]).astype(np.float32)
    valid = rng.random((T, M)) < 0.8
    batch = project_batch(clouds, SPEC)
    masked = project_batch(clouds, SPEC, valid)
    assert batch.shape == masked.shape == (T, SPEC.size, SPEC.size)
    assert batch.dtype == masked.dtype == np.float32
    for t in range(T):
        np.testing.assert_array_equal(batch[t], project(clouds[t], SPEC))
        np.testing.assert_array_equal(masked[t], project(clouds[t][valid[t]], SPEC))


def test_batch_does_not_depend_on_frame_grouping(monkeypatch):
    rng = np.random.default_rng(7)
    clouds = np.stack([messy_cloud(rng, SPEC, 400) for _ in range(9)])
    expected = project_batch(clouds, SPEC)
    for chunk in (1, 400, 1000, 10**9):  # one frame per group .. all frames in one group
        monkeypatch.setattr(proj, "_CHUNK_POINTS", chunk)
        np.testing.assert_array_equal(project_batch(clouds, SPEC), expected)


# ------------------------------------------------------------------------------------------------
# 5-7. Edge cases, min-z semantics, orientation
# ------------------------------------------------------------------------------------------------


def test_empty_cloud_gives_zeros():
    assert np.array_equal(project(np.zeros((0, 3)), SPEC), np.zeros((SPEC.size, SPEC.size), np.float32))
    assert project_batch(np.zeros((4, 0, 3)), SPEC).shape == (4, SPEC.size, SPEC.size)
    assert not project_batch(np.zeros((4, 0, 3)), SPEC).any()
    assert project_batch(np.zeros((0, 10, 3)), SPEC).shape == (0, SPEC.size, SPEC.size)
    assert not project_batch(np.zeros((2, 5, 3)), SPEC, np.zeros((2, 5), bool)).any()


def test_points_outside_the_grid_are_ignored():
    v, h, top, bottom = SPEC.voxel, SPEC.half_extent, SPEC.z_top, SPEC.z_top - SPEC.depth
    outside = np.array(
        [
            [h + 0.1 * v, 0.0, -0.05],
            [-h - 0.1 * v, 0.0, -0.05],
            [0.0, h + 0.1 * v, -0.05],
            [0.0, -h - 0.1 * v, -0.05],
            [0.0, 0.0, top + 0.1 * v],  # above the top plane
            [0.0, 0.0, bottom - 0.1 * v],  # below the grid
            [5.0, -5.0, 5.0],
        ]
    )
    assert not project(outside, SPEC).any()
    inside = grid_cloud(np.random.default_rng(0), SPEC, 200)
    np.testing.assert_array_equal(project(np.concatenate([inside, outside]), SPEC), project(inside, SPEC))


def test_non_finite_points_are_ignored():
    inside = grid_cloud(np.random.default_rng(1), SPEC, 200)
    bad = np.array(
        [
            [np.nan, 0.0, 0.0],
            [0.0, np.nan, 0.0],
            [0.0, 0.0, np.nan],
            [np.inf, 0, 0],
            [0, -np.inf, 0],
            [0, 0, np.inf],
        ]
    )
    with np.errstate(all="raise"):  # no floating-point warnings either
        mixed = project(np.concatenate([bad, inside, bad]), SPEC)
        assert not project(bad, SPEC).any()
    np.testing.assert_array_equal(mixed, project(inside, SPEC))


def test_column_value_is_the_topmost_point():
    v = SPEC.voxel
    high, low = [0.013, -0.021, 0.02], [0.013, -0.021, -0.15]  # same column, different heights
    for cloud in (np.array([high, low]), np.array([low, high])):
        image = project(cloud, SPEC)
        (i,), (j,) = np.nonzero(image)
        k_high = math.floor((SPEC.z_top - high[2]) / v)
        assert image[i, j] == np.float32((k_high + 0.5) * v)
    assert project(np.array([high]), SPEC).max() < project(np.array([low]), SPEC).max()  # higher => shallower


def test_occupied_values_are_positive_voxel_centres():
    image = project(messy_cloud(np.random.default_rng(2), SPEC, 3000), SPEC)
    values = image[image > 0]
    assert values.size > 0 and values.min() >= 0.5 * SPEC.voxel * (1 - 1e-6)
    assert values.max() < SPEC.depth + 0.5 * SPEC.voxel
    np.testing.assert_array_equal(values, SPEC.depth_levels[depth_index(values, SPEC)])


def test_orientation_rows_follow_x_columns_follow_y():
    def pixel(x, y):
        (i,), (j,) = np.nonzero(project(np.array([[x, y, -0.05]]), SPEC))
        return i, j

    assert pixel(0.05, 0.0)[0] > pixel(-0.05, 0.0)[0]
    assert pixel(0.05, 0.0)[1] == pixel(-0.05, 0.0)[1]
    assert pixel(0.0, 0.05)[1] > pixel(0.0, -0.05)[1]
    assert pixel(0.0, 0.05)[0] == pixel(0.0, -0.05)[0]
    # The gripper origin sits on the corner between pixels N/2 - 1 and N/2.
    half, eps = SPEC.size // 2, 0.5 * SPEC.voxel
    assert pixel(eps, eps) == (half, half)
    assert pixel(-eps, -eps) == (half - 1, half - 1)
    assert pixel(eps, -eps) == (half, half - 1)
    # Pixel i covers x in [(i - N/2) v, (i - N/2 + 1) v).
    assert pixel((3 - half + 0.5) * SPEC.voxel, 0.0)[0] == 3


# ------------------------------------------------------------------------------------------------
# 8. 90-degree rotations about z are np.rot90 of the image (pins the convention for the augmenter)
# ------------------------------------------------------------------------------------------------


def rotate_z(cloud: np.ndarray, quarter_turns: int) -> np.ndarray:
    """Rotate by quarter_turns * 90 degrees about z (counter-clockwise seen from above): (x, y) -> (-y, x)."""
    out = cloud.copy()
    for _ in range(quarter_turns % 4):
        out[:, 0], out[:, 1] = -out[:, 1], out[:, 0].copy()
    return out


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("spec", [SPEC, SMALL], ids=["default", "small"])
def test_quarter_turn_about_z_is_rot90_k1(seed, spec):
    rng = np.random.default_rng(seed)
    cloud = grid_cloud(rng, spec, 600 if spec is SPEC else 40)
    image = project(cloud, spec)
    for r in range(4):
        np.testing.assert_array_equal(project(rotate_z(cloud, r), spec), np.rot90(image, k=r))
    # Pin the sign: (x, y) -> (-y, x) is k = +1, not k = -1.
    assert not np.array_equal(np.rot90(image, k=1), np.rot90(image, k=-1))


def test_quarter_turn_maps_pixel_i_j_to_n_minus_1_minus_j_i():
    N, v, h = SPEC.size, SPEC.voxel, SPEC.half_extent
    i, j = 10, 70
    point = np.array([[(i + 0.5) * v - h, (j + 0.5) * v - h, -0.05]])
    rotated = project(rotate_z(point, 1), SPEC)
    assert list(zip(*np.nonzero(rotated), strict=True)) == [(N - 1 - j, i)]


# ------------------------------------------------------------------------------------------------
# 9. Policy input and uint8 quantisation
# ------------------------------------------------------------------------------------------------


def test_observation_channels():
    rng = np.random.default_rng(3)
    depth = project_batch(np.stack([messy_cloud(rng, SPEC, 500) for _ in range(4)]), SPEC)
    jaw = np.array([0.0, 0.25, 0.9, 1.0])
    obs = observation_channels(depth, jaw, SPEC)
    assert obs.shape == (4, 2, SPEC.size, SPEC.size) and obs.dtype == np.float32
    np.testing.assert_array_equal(obs[:, 0], depth)
    for t in range(4):
        assert np.all(obs[t, 1] == np.float32(jaw[t]))
    with pytest.raises(ValueError):
        observation_channels(depth, jaw[:3], SPEC)
    with pytest.raises(ValueError):
        observation_channels(depth[:, :10], jaw, SPEC)


@pytest.mark.parametrize("seed", range(3))
def test_quantize_roundtrip_error_bound_and_empty_stays_zero(seed):
    rng = np.random.default_rng(seed)
    T = 6
    depth = project_batch(np.stack([messy_cloud(rng, SPEC, 3000) for _ in range(T)]), SPEC)
    obs = observation_channels(depth, rng.uniform(0, 1, T), SPEC)
    codes = quantize(obs, SPEC)
    assert codes.dtype == np.uint8 and codes.shape == obs.shape
    back = dequantize(codes, SPEC)
    assert back.dtype == np.float32 and back.shape == obs.shape
    empty = obs[:, 0] == 0
    assert empty.any() and (~empty).any()
    np.testing.assert_array_equal(codes[:, 0] == 0, empty)  # 0 is exactly "empty", both ways
    assert np.all(back[:, 0][empty] == 0)
    depth_err = np.abs(back[:, 0].astype(np.float64) - obs[:, 0])
    assert depth_err.max() <= SPEC.quant_step / 2 + F32_SLACK
    jaw_err = np.abs(back[:, 1].astype(np.float64) - obs[:, 1])
    assert jaw_err.max() <= 1 / 510 + F32_SLACK


@pytest.mark.parametrize("spec", [SPEC, SMALL, ProjectionSpec(size=32, voxel=0.001, depth=0.2535)], ids=str)
def test_every_depth_level_quantizes_within_half_a_step_to_distinct_nonzero_codes(spec):
    levels = spec.depth_levels[: n_levels(spec)]
    codes = quantize_depth(levels, spec)
    assert codes.min() >= 1 and len(np.unique(codes)) == levels.size
    err = np.abs(dequantize_depth(codes, spec).astype(np.float64) - levels)
    assert err.max() <= spec.quant_step / 2 + F32_SLACK
    assert quantize_depth(np.zeros(3), spec).tolist() == [0, 0, 0]
    assert quantize_depth(np.array([spec.max_value]), spec).tolist() == [255]


def test_jaw_quantization_endpoints():
    obs = np.zeros((3, 2, 4, 4), np.float32)
    obs[:, 1] = np.array([0.0, 0.5, 1.0])[:, None, None]
    codes = quantize(obs, ProjectionSpec(size=4))
    assert codes[:, 1, 0, 0].tolist() == [0, 128, 255]
    np.testing.assert_array_equal(
        dequantize(codes, ProjectionSpec(size=4))[:, 1, 0, 0],
        np.array([0, 128, 255], np.float32) / np.float32(255),
    )


# ------------------------------------------------------------------------------------------------
# Wire-format helper and spec validation
# ------------------------------------------------------------------------------------------------


def test_segments_to_points_marks_unseen_segments_invalid():
    rng = np.random.default_rng(4)
    T, S, P = 3, 4, 5
    points = rng.normal(0, 0.05, (T, S, P, 3)).astype(np.float32)
    counts = np.array([[9, 0, 3, 1], [2, 2, 2, 2], [7, 0, 0, 0]], dtype=np.int32)
    flat, valid = segments_to_points(points, counts)
    assert flat.shape == (T, S * P, 3) and valid.shape == (T, S * P) and valid.dtype == bool
    np.testing.assert_array_equal(flat.reshape(T, S, P, 3), points)
    np.testing.assert_array_equal(
        valid.reshape(T, S, P), np.broadcast_to((counts > 0)[:, :, None], (T, S, P))
    )
    _, all_valid = segments_to_points(points, None)
    assert all_valid.all()
    for t in range(T):
        seen = points[t][counts[t] > 0].reshape(-1, 3)
        np.testing.assert_array_equal(project_batch(flat, SPEC, valid)[t], project(seen, SPEC))


@pytest.mark.parametrize(
    "kwargs",
    [
        {"size": 1},
        {"size": 8.0},
        {"voxel": 0.0},
        {"voxel": -0.01},
        {"voxel": float("nan")},
        {"z_top": float("inf")},
        {"depth": 0.001},  # less than one voxel
        {"depth": 1.3},  # more than 254 voxels
        {"voxel": 0.001, "depth": 0.2541},  # 254 voxels and a bit
        {"depth": "0.4"},
    ],
)
def test_spec_validation(kwargs):
    with pytest.raises(ValueError):
        ProjectionSpec(**kwargs)


def test_spec_defaults_and_value_semantics():
    assert SPEC.size == 84 and math.isclose(SPEC.size * SPEC.voxel, 0.4)
    assert ProjectionSpec() == SPEC and hash(ProjectionSpec()) == hash(SPEC)
    assert ProjectionSpec(size=np.int64(84)).size == 84
    assert not SPEC.depth_levels.flags.writeable
    with pytest.raises(ValueError):
        project(np.zeros((5, 2)), SPEC)
    with pytest.raises(ValueError):
        project_batch(np.zeros((2, 5, 3)), SPEC, np.ones((2, 4), bool))
