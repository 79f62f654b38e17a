"""The state critic's privileged rows and Q: reference numbers, the symmetry they are built to have
(rotation about z and horizontal translation of scene and action together), the objects' own
symmetry, and clear errors where the state cannot be formed."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from services.algorithms.networks import PRESETS, StateCritic, build_critic
from services.algorithms.privileged import STATE_DIM, critic_state, episode_critic_state, yaw_of
from services.algorithms.sac.losses import Batch
from tests.helpers import build_episode

pytestmark = pytest.mark.unit


def yaw_quat(yaw: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w) of turns by ``yaw`` about z."""
    yaw = np.asarray(yaw, np.float64)
    return np.stack([np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2), np.cos(yaw / 2)], -1)


def scene(rng: np.random.Generator, n: int = 6):
    """``n`` random steps: gripper (x, y, z, yaw), two upright objects (x, y, z, quat), contacts, jaw."""
    g = np.c_[rng.uniform(0.3, 0.7, (n, 2)), rng.uniform(0.02, 0.3, n), rng.uniform(-math.pi, math.pi, n)]
    pos = np.c_[rng.uniform(0.3, 0.7, (n * 2, 2)), rng.uniform(0.0, 0.05, n * 2)].reshape(n, 2, 3)
    objects = np.concatenate([pos, yaw_quat(rng.uniform(-math.pi, math.pi, (n, 2)))], -1)
    return g, objects, rng.random((n, 2)) < 0.5, rng.uniform(0, 1, n)


def moved(g: np.ndarray, objects: np.ndarray, angle: float, shift: np.ndarray):
    """The same scene turned by ``angle`` about the world origin, then shifted by ``shift`` (x, y)."""
    c, s = math.cos(angle), math.sin(angle)
    turn = np.array([[c, -s], [s, c]])
    g2, o2 = g.copy(), objects.copy()
    g2[:, :2] = g[:, :2] @ turn.T + shift
    g2[:, 3] = g[:, 3] + angle
    o2[..., :2] = objects[..., :2] @ turn.T + shift
    o2[..., 3:] = yaw_quat(yaw_of(objects[..., 3:]) + angle)
    return g2, o2


def test_reference_numbers_of_a_hand_built_scene():
    # gripper at the origin (z 0.1, yaw 0); movable object at (0.1, 0), immovable at (0.1, 0.1):
    # the frame's x axis points along world +y (phi = pi/2)
    g = np.array([[0.0, 0.0, 0.1, 0.0]])
    objects = np.array([[[0.1, 0.0, 0.02, *yaw_quat(0.0)], [0.1, 0.1, 0.02, *yaw_quat(0.0)]]])
    row = critic_state(
        g, objects, np.array([[True, False]]), np.array([0.5]), fixed_object=1, object_symmetry=4
    )[0]
    assert row.shape == (STATE_DIM,)
    expected = {
        0: math.pi / 2,
        1: 0.0, 2: -0.5,  # movable (0.1, 0) world -> (0, -0.1) in the frame, per 0.2 m
        3: 0.5, 4: -0.5,  # immovable (0.1, 0.1) -> (0.1, -0.1)
        5: -0.4, 6: -0.4, 7: 0.5,  # object z - gripper z, gripper z
        8: math.cos(4 * -math.pi / 2), 9: 0.0,  # block yaw 0 - phi, times its symmetry order 4
        12: math.cos(2 * -math.pi / 2), 13: 0.0,
        14: 0.5, 15: 1.0, 16: 0.0, 17: 0.5,
    }  # fmt: skip
    for col, value in expected.items():
        assert row[col] == pytest.approx(value, abs=1e-6), col


def test_rows_are_invariant_under_turning_and_shifting_the_whole_scene():
    rng = np.random.default_rng(0)
    g, objects, contacts, jaw = scene(rng)
    base = critic_state(g, objects, contacts, jaw, fixed_object=0, object_symmetry=4)
    for angle in (0.3, math.pi / 2, -2.5):
        g2, o2 = moved(g, objects, angle, rng.uniform(-0.2, 0.2, 2))
        turned = critic_state(g2, o2, contacts, jaw, fixed_object=0, object_symmetry=4)
        np.testing.assert_allclose(turned[:, 1:], base[:, 1:], atol=1e-5)
        dphi = np.angle(np.exp(1j * (turned[:, 0] - base[:, 0])))
        np.testing.assert_allclose(dphi, angle if angle <= math.pi else angle - 2 * math.pi, atol=1e-6)


def test_an_objects_own_symmetry_does_not_change_its_row_but_the_fixed_one_does():
    rng = np.random.default_rng(1)
    g, objects, contacts, jaw = scene(rng)
    base = critic_state(g, objects, contacts, jaw, fixed_object=1, object_symmetry=4)
    quarter = objects.copy()
    quarter[:, 0, 3:] = yaw_quat(yaw_of(objects[:, 0, 3:]) + math.pi / 2)  # a square block turned by 90 deg
    np.testing.assert_allclose(
        critic_state(g, quarter, contacts, jaw, fixed_object=1, object_symmetry=4), base, atol=1e-5
    )
    # the same turn of a body without that symmetry (a drawer) is a different state
    assert not np.allclose(
        critic_state(g, quarter, contacts, jaw, fixed_object=1, object_symmetry=1),
        critic_state(g, objects, contacts, jaw, fixed_object=1, object_symmetry=1),
        atol=1e-3,
    )
    # which object is the immovable one is what the policy must find out: the critic knows it
    swapped = critic_state(g, objects, contacts, jaw, fixed_object=0, object_symmetry=4)
    assert not np.allclose(swapped[:, 1:], base[:, 1:], atol=1e-3)
    np.testing.assert_allclose(swapped[:, [15, 16]], base[:, [16, 15]])


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"fixed_object": -1}, "fixed_object"),
        ({"fixed_object": 2}, "fixed_object"),
        ({"object_symmetry": 0}, "object_symmetry"),
        ({"objects": np.zeros((6, 3, 7))}, "object_poses"),
        ({"objects": np.full((6, 2, 7), np.nan)}, "non-finite"),
    ],
)
def test_a_state_that_cannot_be_formed_is_refused_by_name(kwargs, field):
    g, objects, contacts, jaw = scene(np.random.default_rng(2))
    args = {"fixed_object": 0, "object_symmetry": 4, "objects": objects} | kwargs
    with pytest.raises(ValueError, match=field):
        critic_state(g, args.pop("objects"), contacts, jaw, **args)


def test_an_episode_without_its_immovable_object_is_refused():
    ep = build_episode(T=4, seed=0)
    assert ep.fixed_object == -1  # the Episode default: producer did not say
    with pytest.raises(ValueError, match="fixed_object"):
        episode_critic_state(ep)
    rows = episode_critic_state(dataclasses.replace(ep, fixed_object=1))
    assert rows.shape == (5, STATE_DIM) and rows.dtype == np.float32


def test_state_critic_q_is_invariant_when_scene_and_action_turn_together():
    torch.manual_seed(0)
    critic = build_critic(dataclasses.replace(PRESETS["cpu-small"], critic_input="state"))
    assert isinstance(critic, StateCritic)
    rng = np.random.default_rng(3)
    g, objects, contacts, jaw = scene(rng)
    actions = rng.uniform(-1, 1, (len(g), 5)).astype(np.float32)
    angle = 1.1
    g2, o2 = moved(g, objects, angle, np.array([0.05, -0.1]))
    turned = actions.copy()
    c, s = math.cos(angle), math.sin(angle)
    turned[:, 1], turned[:, 2] = c * actions[:, 1] - s * actions[:, 2], s * actions[:, 1] + c * actions[:, 2]

    def q(gp, op, a):
        rows = torch.from_numpy(critic_state(gp, op, contacts, jaw, fixed_object=0, object_symmetry=4))
        return torch.stack(critic.q(rows, torch.from_numpy(a)))

    with torch.no_grad():
        torch.testing.assert_close(q(g2, o2, turned), q(g, objects, actions), atol=1e-4, rtol=1e-4)
        # the action's direction matters to it (what the image critic did not learn to see)
        assert (q(g, objects, turned) - q(g, objects, actions)).abs().max() > 1e-3


def test_state_critic_needs_the_batch_rows():
    critic = build_critic(dataclasses.replace(PRESETS["cpu-small"], critic_input="state"))
    batch = Batch(
        images=torch.zeros(1, 3, 2, 8, 8), actions=torch.zeros(1, 2, 5), rewards=torch.zeros(1, 2),
        terminated=torch.zeros(1, 2), mask=torch.ones(1, 2),
    )  # fmt: skip
    with pytest.raises(ValueError, match="state"):
        critic.features_of(batch)
    rows = torch.zeros(1, 3, STATE_DIM)
    assert critic.features_of(dataclasses.replace(batch, state=rows)) is rows
