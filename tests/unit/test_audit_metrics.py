"""The audit's pure arithmetic: distances between point sets, per-observation checks, transition
validity, phases and tolerances (no simulator)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.augmenter.core.audit_metrics import (
    NON_TRIVIAL,
    TERMINATION,
    TRIVIAL,
    AuditTolerance,
    chamfer_mm,
    compare_observation,
    distinct_points,
    moved_observation,
    observation_checks,
    phases,
    surface_mm,
    valid_transitions,
    yaw_diff,
)

pytestmark = pytest.mark.unit


def test_set_distances():
    rng = np.random.default_rng(0)
    a = rng.uniform(-0.05, 0.05, (200, 3))
    zero = pytest.approx(0.0, abs=1e-4)  # mm
    assert chamfer_mm(a, a) == zero and surface_mm(a, a) == zero
    assert chamfer_mm(a, a + [0.03, 0, 0]) > 10.0  # mm
    assert chamfer_mm(a, np.zeros((0, 3))) == np.inf
    # one-sided: a subset lies on the full cloud, the full cloud does not lie on the subset
    assert surface_mm(a[:50], a) == zero and surface_mm(a, a[:50]) > 1.0


def test_compare_observation_per_segment_with_empty_sides():
    rng = np.random.default_rng(1)
    seen = rng.uniform(-0.05, 0.05, (8, 3))
    sim = np.zeros((3, 8, 3))
    sim[0], sim[1] = seen, seen
    claimed = np.zeros((3, 8, 3))
    claimed[0] = seen
    chamfer, surface = compare_observation(
        sim, np.array([8, 8, 0]), [seen, seen, np.zeros((0, 3))], claimed, np.array([8, 0, 0])
    )
    # gripper: the same points (0); object 0 seen only by the sim (inf); object 1 seen by nobody (0)
    assert chamfer[0] == pytest.approx(0.0, abs=1e-4) and surface[0] == pytest.approx(0.0, abs=1e-4)
    assert chamfer[1] == math.inf and surface[1] == math.inf
    assert chamfer[2] == 0.0 and surface[2] == 0.0
    # only the first ``count`` points of a padded segment take part
    assert len(distinct_points(seen, 3)) == 3 and len(distinct_points(seen, 20)) == 8


def test_observation_checks_and_transition_validity():
    tol = AuditTolerance(9.5, 7.0, 5.0, 0.75, jaw=0.01)
    segments = ["gripper", "object_0", "object_1"]
    chamfer = np.array([[1.0, 1.0, 1.0], [9.6, 1.0, 1.0], [1.0, 1.0, 7.1], [1.0, 1.0, 1.0]])
    surface = np.array([[1.0, 0.5, 0.5], [1.0, 0.5, 0.5], [1.0, 0.5, 0.5], [5.1, 0.76, 0.5]])
    jaw = np.array([0.0, 0.0, 0.0, 0.02])
    checks = observation_checks(chamfer, surface, jaw, segments, tol)
    assert list(checks) == ["jaw", "gripper chamfer", "object chamfer", "gripper surface", "object surface"]
    assert checks["jaw"].tolist() == [True, True, True, False]
    assert checks["gripper chamfer"].tolist() == [True, False, True, True]
    assert checks["object chamfer"].tolist() == [True, True, False, True]
    assert checks["gripper surface"].tolist() == [True, True, True, False]
    assert checks["object surface"].tolist() == [True, True, True, False]
    obs_ok, valid = valid_transitions(checks, np.ones(3, bool), np.array([True, True, False]))
    assert obs_ok.tolist() == [True, False, False, False]
    assert valid.tolist() == [False, False, False]
    ok = {k: np.ones(4, bool) for k in checks}
    _, valid = valid_transitions(ok, np.array([True, False, True]), np.ones(3, bool))
    assert valid.tolist() == [True, False, True]


def test_phases_tolerances_moves_and_yaws():
    assert phases(5, 2).tolist() == [NON_TRIVIAL, NON_TRIVIAL, TRIVIAL, TRIVIAL, TERMINATION]
    assert phases(4, 0).tolist() == [TRIVIAL, TRIVIAL, TRIVIAL, TERMINATION]
    assert phases(3, 5).tolist() == [NON_TRIVIAL] * 3
    pick, turned = AuditTolerance.for_task("block_pick"), AuditTolerance.for_task("block_pick", rotated=True)
    assert (pick.object_chamfer_mm, turned.object_chamfer_mm) == (3.0, 5.0)
    assert AuditTolerance.for_task("no_such_task") == AuditTolerance()
    assert pick.limits("surface", ["gripper", "a", "b"]).tolist() == [5.0, 1.5, 1.5]
    # the pivot moves by (0.1, 0, 0) and turns a quarter: objects shift back, the gripper turns
    points = np.array([[[1.0, 0.0, 0.0]], [[0.2, 0.3, 0.0]]])
    moved = moved_observation(points, np.array([0.1, 0.0, 0.0, math.pi / 2]))
    np.testing.assert_allclose(moved[0, 0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(moved[1, 0], [0.1, 0.3, 0.0])
    assert yaw_diff(math.pi - 0.1, -math.pi + 0.1) == pytest.approx(0.2)
