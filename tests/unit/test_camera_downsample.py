"""The camera rig's voxel downsampling: one point (the mean) per occupied voxel, in the voxels'
lexicographic index order, exactly as a row-wise np.unique would group and order them."""

from __future__ import annotations

import numpy as np
import pytest

from services.tasks.camera import _downsample, _voxel_ids


def _by_rows(points: np.ndarray, voxel: float) -> np.ndarray:
    """The reference: group rows of voxel indices with np.unique(axis=0)."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.reshape(-1), points)
    return sums / counts[:, None]


@pytest.mark.parametrize("seed", range(5))
def test_equals_the_row_wise_grouping_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    # a workspace-sized cloud around negative and positive coordinates, with many points per voxel
    points = rng.normal([0.5, -0.1, 0.05], [0.15, 0.2, 0.05], size=(20_000, 3))
    got, want = _downsample(points, 0.004), _by_rows(points, 0.004)
    assert got.shape == want.shape and len(got) < len(points)
    np.testing.assert_array_equal(got, want)


def test_single_point_and_empty_cloud():
    np.testing.assert_array_equal(_downsample(np.array([[0.1, -0.2, 0.3]]), 0.004), [[0.1, -0.2, 0.3]])
    assert _downsample(np.zeros((0, 3)), 0.004).shape == (0, 3)


def test_ids_order_like_rows_and_fall_back_when_the_span_overflows():
    keys = np.array([[1, 0, 5], [0, 9, 9], [1, 0, 4], [0, 9, 9], [-3, 2, 0]], np.int64)
    ids = _voxel_ids(keys)
    assert list(np.argsort(ids, kind="stable")) == list(np.lexsort(keys.T[::-1]))
    assert ids[1] == ids[3] and len(set(ids.tolist())) == 4
    huge = np.array([[0, 0, 0], [2**21, 2**21, 2**21], [0, 0, 0]], np.int64)
    big = _voxel_ids(huge)
    assert big[0] == big[2] != big[1]
