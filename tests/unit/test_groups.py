"""C4 / D4 conventions: the tables form a group, every action on data is a homomorphism, and the image
action is pinned to the real voxel projection (a world rotated / mirrored by g projects to
``transform_images(project(cloud), g)``, pixel for pixel)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from services.algorithms.groups import (
    C4,
    D4,
    Group,
    action_matrix,
    compose,
    get_group,
    inverse,
    matrix,
    sign,
    transform_actions,
    transform_images,
    transform_regular,
)
from services.observation.projection import DEFAULT_SPEC, ProjectionSpec, project

pytestmark = pytest.mark.unit

GROUPS = [C4, D4]
D4_PAIRS = list(itertools.product(D4.elements, D4.elements))


def _mat(g) -> np.ndarray:
    return np.array(matrix(g), dtype=np.int64)


# ------------------------------------------------------------------------------------------------
# the tables
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("group", GROUPS, ids=lambda g: g.name)
def test_tables_form_a_group(group: Group) -> None:
    G, mul, inv = group.order, group.mul, group.inv
    assert group.elements[0] == (0, 0)  # identity first
    for a in range(G):
        assert mul[0][a] == a and mul[a][0] == a
        assert mul[a][inv[a]] == 0 and mul[inv[a]][a] == 0
        assert sorted(mul[a]) == list(range(G))  # each row is a permutation (Latin square)
    for a, b, c in itertools.product(range(G), repeat=3):
        assert mul[mul[a][b]][c] == mul[a][mul[b][c]]


def test_orders_and_c4_is_the_rotation_subgroup_of_d4() -> None:
    assert (C4.order, D4.order) == (4, 8)
    assert D4.elements[:4] == C4.elements
    assert all(D4.mul[a][b] == C4.mul[a][b] for a in range(4) for b in range(4))
    assert get_group("c4") is C4 and get_group("d4") is D4
    with pytest.raises(ValueError, match="unknown group"):
        get_group("c8")


def test_d4_is_not_abelian_and_mirror_conjugates_rotation() -> None:
    f, r = (1, 0), (0, 1)
    assert compose(f, r) != compose(r, f)
    assert compose(compose(f, r), f) == (0, 3)  # F R F = R^-1


@pytest.mark.parametrize(("g", "h"), D4_PAIRS)
def test_matrices_and_signs_are_homomorphisms(g, h) -> None:
    np.testing.assert_array_equal(_mat(compose(g, h)), _mat(g) @ _mat(h))
    assert sign(compose(g, h)) == sign(g) * sign(h)
    torch.testing.assert_close(action_matrix(compose(g, h)), action_matrix(g) @ action_matrix(h))
    np.testing.assert_array_equal(_mat(inverse(g)) @ _mat(g), np.eye(2, dtype=np.int64))


def test_element_matrices() -> None:
    np.testing.assert_array_equal(_mat((0, 1)), [[0, -1], [1, 0]])  # +90 deg: (x, y) -> (-y, x)
    np.testing.assert_array_equal(_mat((1, 0)), [[1, 0], [0, -1]])  # F: (x, y) -> (x, -y)
    torch.testing.assert_close(D4.matrices()[5], torch.tensor([[0.0, 1.0], [1.0, 0.0]]))  # R F
    torch.testing.assert_close(D4.signs(), torch.tensor([1.0] * 4 + [-1.0] * 4))


# ------------------------------------------------------------------------------------------------
# actions on data
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("g", "h"), D4_PAIRS)
def test_transforms_are_homomorphisms(g, h) -> None:
    """Transforming by g, then by h, equals transforming by h g."""
    gen = torch.Generator().manual_seed(0)
    hg = compose(h, g)
    img = torch.randn(2, 3, 3, 6, 6, generator=gen)
    assert torch.equal(transform_images(transform_images(img, g), h), transform_images(img, hg))
    act = torch.randn(4, 7, 5, generator=gen)
    torch.testing.assert_close(transform_actions(transform_actions(act, g), h), transform_actions(act, hg))
    flat = torch.randn(3, 2 * D4.order, generator=gen)
    assert torch.equal(
        transform_regular(transform_regular(flat, g, D4), h, D4), transform_regular(flat, hg, D4)
    )
    maps = torch.randn(2, 3 * D4.order, 4, 4, generator=gen)
    twice = transform_regular(transform_regular(maps, g, D4, spatial=True), h, D4, spatial=True)
    assert torch.equal(twice, transform_regular(maps, hg, D4, spatial=True))


def test_regular_permutation_moves_the_identity_channel_to_g() -> None:
    """(g f)_h = f_{g^-1 h}: a field that is 1 on the identity channel only becomes 1 on channel g."""
    for k, g in enumerate(D4.elements):
        f = torch.zeros(D4.order)
        f[0] = 1.0
        assert torch.equal(transform_regular(f, g, D4), torch.eye(D4.order)[k])


def test_action_transform_on_basis_vectors() -> None:
    a = torch.tensor([0.3, 1.0, 0.0, -0.4, 0.7])
    rot = transform_actions(a, (0, 1))
    torch.testing.assert_close(rot, torch.tensor([0.3, 0.0, 1.0, -0.4, 0.7]))  # +x -> +y, dtheta kept
    mirrored = transform_actions(torch.tensor([0.3, 0.2, 0.5, -0.4, 0.7]), (1, 0))
    torch.testing.assert_close(mirrored, torch.tensor([0.3, 0.2, -0.5, -0.4, -0.7]))


@pytest.mark.parametrize("g", D4.elements)
def test_mirror_negates_dtheta_and_keeps_jaw_and_dz(g) -> None:
    a = torch.randn(10, 5, generator=torch.Generator().manual_seed(1))
    b = transform_actions(a, g)
    torch.testing.assert_close(b[:, 4], a[:, 4] * (-1 if g[0] else 1))
    torch.testing.assert_close(b[:, [0, 3]], a[:, [0, 3]])
    torch.testing.assert_close(b[:, 1:3].norm(dim=1), a[:, 1:3].norm(dim=1))


def test_transform_actions_rejects_wrong_width() -> None:
    with pytest.raises(ValueError, match="5 entries"):
        transform_actions(torch.zeros(3, 4), (0, 1))


# ------------------------------------------------------------------------------------------------
# pinned to the projection
# ------------------------------------------------------------------------------------------------


def _grid_cloud(rng: np.random.Generator, spec: ProjectionSpec, m: int) -> np.ndarray:
    """Points in the grid, each 0.1-0.9 voxel inside its voxel, so that a world rotation or mirror
    (which maps the grid's voxels onto voxels for even N) never moves a point across a boundary."""
    N, v, h = spec.size, spec.voxel, spec.half_extent
    k_max = int(spec.depth / v) - 1
    a, b = rng.integers(0, N, m), rng.integers(0, N, m)
    c = rng.integers(0, k_max, m)
    u = rng.uniform(0.1, 0.9, (m, 3))
    return np.stack([(a + u[:, 0]) * v - h, (b + u[:, 1]) * v - h, spec.z_top - (c + u[:, 2]) * v], axis=1)


def _world(points: np.ndarray, g) -> np.ndarray:
    out = points.copy()
    out[:, :2] = points[:, :2] @ _mat(g).T.astype(np.float64)
    return out


@pytest.mark.parametrize("g", D4.elements)
def test_world_transform_projects_to_transform_images(g) -> None:
    rng = np.random.default_rng(7)
    for spec in (DEFAULT_SPEC, ProjectionSpec(size=10, voxel=0.01, z_top=0.02, depth=0.06)):
        cloud = _grid_cloud(rng, spec, 600)
        image = torch.from_numpy(project(cloud, spec))
        assert (image > 0).float().mean() > 0.05  # a non-trivial image
        expected = transform_images(image, g)
        assert torch.equal(torch.from_numpy(project(_world(cloud, g), spec)), expected)


def test_world_plus_x_is_image_rows_and_quarter_turn_moves_it_to_columns() -> None:
    spec = DEFAULT_SPEC
    v = spec.voxel
    point = np.array([[10.5 * v, 0.5 * v, 0.0]])  # +x of the gripper: row 42 + 10, column 42
    img = torch.from_numpy(project(point, spec))
    assert torch.nonzero(img).tolist() == [[52, 42]]
    turned = transform_images(img, (0, 1))
    assert torch.nonzero(turned).tolist() == [[41, 52]]  # now at +y (column 52), x = -0.5 v (row 41)
    assert torch.equal(turned, torch.from_numpy(project(_world(point, (0, 1)), spec)))
    wrong = torch.rot90(img, k=-1, dims=(-2, -1))
    assert not torch.equal(wrong, turned)
