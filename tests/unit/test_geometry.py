"""services.geometry: rotations about z give the same bits as the formulas each caller wrote before
(float32 and float64), loops and vectorised calls agree, and reference values and conventions hold."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.geometry import rotate_quat_z, rotate_z, rotate_z_per_step, turn_xy, wrap_angle

pytestmark = pytest.mark.unit

ANGLES = [0.0, 1e-9, 0.3, -1.2, math.pi / 2, math.pi, 2.5, -3.1, 7.0, 1e3]

# ----------------------------------------------------------------------------------------------
# the formulas as they were written at each call site (the reference the module must reproduce)
# ----------------------------------------------------------------------------------------------


def old_prior_rot_z(points: np.ndarray, angle: float) -> np.ndarray:  # services.tasks.prior._rot_z
    c, s = math.cos(angle), math.sin(angle)
    out = points.copy()
    out[:, 0] = c * points[:, 0] - s * points[:, 1]
    out[:, 1] = s * points[:, 0] + c * points[:, 1]
    return out


def old_mea_rotate_points(points: np.ndarray, angles: np.ndarray) -> np.ndarray:  # mea._rotate_points
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    out = points.copy()
    out[..., 0] = c * points[..., 0] - s * points[..., 1]
    out[..., 1] = s * points[..., 0] + c * points[..., 1]
    return out


def old_mea_rotate_xy(v: np.ndarray, angle: float) -> np.ndarray:  # mea.rotate_xy
    c, s = math.cos(angle), math.sin(angle)
    out = np.array(v, dtype=np.float64, copy=True)
    out[..., 0] = c * v[..., 0] - s * v[..., 1]
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    return out


def old_isometric_rotate_points(
    points: np.ndarray, c: float, s: float
) -> np.ndarray:  # isometric.rotate_points
    p = np.asarray(points, np.float64)
    out = np.array(points, dtype=np.float32, copy=True)
    out[..., 0] = c * p[..., 0] - s * p[..., 1]
    out[..., 1] = s * p[..., 0] + c * p[..., 1]
    return out


def old_rotate_quat_z(quats: np.ndarray, phi: float) -> np.ndarray:  # isometric._rotate_quat_z
    qz, qw = math.sin(phi / 2), math.cos(phi / 2)
    x, y, z, w = quats[..., 0], quats[..., 1], quats[..., 2], quats[..., 3]
    return np.stack([qw * x - qz * y, qw * y + qz * x, qw * z + qz * w, qw * w - qz * z], axis=-1)


def old_wrap(angle):  # services.tasks.robot.wrap and the inline wrap in mea.free_motion_start
    return (angle + math.pi) % (2 * math.pi) - math.pi


def assert_same_bits(got: np.ndarray, want: np.ndarray) -> None:
    assert got.dtype == want.dtype and got.shape == want.shape
    assert got.tobytes() == want.tobytes()


def cloud(seed: int, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    return (np.random.default_rng(seed).standard_normal(shape) * 0.3).astype(dtype)


# ----------------------------------------------------------------------------------------------
# bit-identical to the old formulas
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rotate_z_matches_the_old_prior_formula(dtype: type) -> None:
    points = cloud(0, (50, 3), dtype)
    before = points.copy()
    for angle in [*ANGLES, float(np.radians(np.float64(0.1)) + 0.7), np.float64(-0.25)]:
        assert_same_bits(rotate_z(points, angle), old_prior_rot_z(points, angle))
    assert_same_bits(points, before)  # the input is not modified


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rotate_z_per_step_matches_the_old_mea_formula(dtype: type) -> None:
    points = cloud(1, (7, 40, 3), dtype)
    angles = np.random.default_rng(2).uniform(-4, 4, 7)
    assert_same_bits(rotate_z_per_step(points, angles), old_mea_rotate_points(points, angles))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_turn_xy_into_a_float64_copy_matches_the_old_rotate_xy(dtype: type) -> None:
    v = cloud(3, (5, 3), dtype)
    for angle in ANGLES:
        c, s = math.cos(angle), math.sin(angle)
        got = turn_xy(v, c, s, out=np.array(v, dtype=np.float64, copy=True))
        assert_same_bits(got, old_mea_rotate_xy(v, angle))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_turn_xy_in_float64_into_float32_matches_the_old_isometric_formula(dtype: type) -> None:
    points = cloud(4, (6, 3, 20, 3), dtype)
    for c, s in [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0), (math.cos(0.7), math.sin(0.7))]:
        got = turn_xy(np.asarray(points, np.float64), c, s, out=np.array(points, dtype=np.float32, copy=True))
        assert_same_bits(got, old_isometric_rotate_points(points, c, s))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rotate_quat_z_matches_the_old_isometric_formula(dtype: type) -> None:
    quats = cloud(5, (9, 2, 4), dtype)
    for phi in ANGLES:
        assert_same_bits(rotate_quat_z(quats, phi), old_rotate_quat_z(quats, phi))


def test_wrap_angle_matches_the_old_formula() -> None:
    values = np.random.default_rng(6).uniform(-20, 20, 200)
    assert_same_bits(wrap_angle(values), old_wrap(values))
    for v in [*values[:20].tolist(), math.pi, -math.pi, 0.0, 3 * math.pi]:
        assert wrap_angle(v) == old_wrap(v) and type(wrap_angle(v)) is float


# ----------------------------------------------------------------------------------------------
# loops and vectorised calls agree
# ----------------------------------------------------------------------------------------------


def test_per_step_rotation_equals_a_loop_of_single_rotations() -> None:
    points = cloud(7, (12, 30, 3), np.float64)
    angles = np.random.default_rng(8).uniform(-math.pi, math.pi, 12)
    batch = rotate_z_per_step(points, angles)
    for t in range(len(angles)):
        # np.cos and math.cos (and SIMD and scalar np.cos) may differ in the last bit
        np.testing.assert_allclose(batch[t], rotate_z(points[t], float(angles[t])), rtol=0, atol=1e-15)
        np.testing.assert_allclose(
            batch[t], rotate_z_per_step(points[t : t + 1], angles[t : t + 1])[0], rtol=0, atol=1e-15
        )


def test_per_step_angles_may_cover_several_leading_axes() -> None:
    points = cloud(9, (4, 3, 10, 3), np.float64)
    angles = np.random.default_rng(10).uniform(-3, 3, (4, 3))
    batch = rotate_z_per_step(points, angles)
    for i in range(4):
        np.testing.assert_allclose(batch[i], rotate_z_per_step(points[i], angles[i]), rtol=0, atol=1e-15)


def test_quaternions_and_wrap_loop_equals_vectorised() -> None:
    quats = cloud(11, (20, 4), np.float64)
    batch = rotate_quat_z(quats, 0.9)
    for i, q in enumerate(quats):
        assert_same_bits(batch[i], rotate_quat_z(q, 0.9))
    angles = np.random.default_rng(12).uniform(-10, 10, 50)
    assert wrap_angle(angles).tolist() == [wrap_angle(float(a)) for a in angles]


# ----------------------------------------------------------------------------------------------
# reference values and conventions
# ----------------------------------------------------------------------------------------------


def test_quarter_turn_takes_x_to_y_counter_clockwise() -> None:
    p = np.array([[1.0, 0.0, 0.5], [0.0, 2.0, -1.0]])
    got = rotate_z(p, math.pi / 2)
    np.testing.assert_allclose(got, [[0.0, 1.0, 0.5], [-2.0, 0.0, -1.0]], atol=1e-15)
    assert got[0, 0] == math.cos(math.pi / 2)  # 6.1e-17, not 0: exact quarter turns are the caller's
    np.testing.assert_array_equal(turn_xy(p, 0.0, 1.0), [[0.0, 1.0, 0.5], [-2.0, 0.0, -1.0]])
    np.testing.assert_array_equal(rotate_z(p, 0.0), p)


def test_rotation_keeps_lengths_and_z() -> None:
    p = cloud(13, (100, 3), np.float64)
    got = rotate_z(p, 1.1)
    np.testing.assert_allclose(np.hypot(got[:, 0], got[:, 1]), np.hypot(p[:, 0], p[:, 1]), rtol=1e-12)
    assert_same_bits(got[:, 2].copy(), p[:, 2].copy())
    np.testing.assert_allclose(rotate_z(got, -1.1), p, atol=1e-12)


def yaw_of(q: np.ndarray) -> float:
    x, y, z, w = q
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def test_rotate_quat_z_reference_values() -> None:
    identity = np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(rotate_quat_z(identity, 0.8), [0.0, 0.0, math.sin(0.4), math.cos(0.4)])
    np.testing.assert_allclose(rotate_quat_z(identity, math.pi), [0.0, 0.0, 1.0, 0.0], atol=1e-15)
    q = rotate_quat_z(identity, 0.3)
    assert yaw_of(rotate_quat_z(q, 0.5)) == pytest.approx(0.8, abs=1e-12)
    np.testing.assert_allclose(rotate_quat_z(rotate_quat_z(q, 0.5), 0.2), rotate_quat_z(q, 0.7), atol=1e-15)
    tilted = np.array([math.sin(0.2), 0.0, 0.0, math.cos(0.2)])  # 0.4 rad about x: z-turns keep the norm
    assert np.linalg.norm(rotate_quat_z(tilted, 1.3)) == pytest.approx(1.0, abs=1e-15)


def test_wrap_angle_reference_values() -> None:
    assert wrap_angle(math.pi) == -math.pi
    assert wrap_angle(-math.pi) == -math.pi
    assert wrap_angle(0.0) == 0.0
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2, abs=1e-15)
    assert wrap_angle(-7.0) == pytest.approx(-7.0 + 2 * math.pi, abs=1e-15)
    got = wrap_angle(np.linspace(-50, 50, 1001))
    assert got.min() >= -math.pi and got.max() < math.pi
