"""MEA as math: properties on seeded synthetic episodes that obey the transition prior exactly.

The synthetic world has fixed object clouds, a rigid gripper cloud, and a gripper that moves by
a*Delta and turns by a^theta*Delta_theta per step. An augmented copy is valid when the same world,
started from the augmented first pose and driven by the augmented actions, produces exactly the
augmented observations.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from proto.episode import Episode
from services.augmenter.core.isometric import compose_with_mea, isometric_copy, rotate_actions
from services.augmenter.core.mea import (
    DELTA_THETA,
    DELTA_XYZ,
    MeaSettings,
    augment,
    draw_group,
    heights,
    phase_split,
    structured_action,
)
from tests.helpers.synthetic import synthetic_episode

pytestmark = pytest.mark.unit
SETTINGS = MeaSettings()


SEEDS = range(12)


@pytest.mark.parametrize("seed", SEEDS)
def test_augmented_copy_is_what_the_world_produces_from_the_augmented_start(seed):
    ep, world = synthetic_episode(seed)
    out, draw = augment(ep, SETTINGS, np.random.default_rng(seed), seed=seed, copy_index=0, episode_id="a")
    assert out is not None
    start_pose = out.gripper_pose[0].astype(np.float64)
    points, poses = world.rollout(start_pose[:3], float(start_pose[3]), out.actions.astype(np.float64))
    np.testing.assert_allclose(out.points, points, atol=2e-6)
    np.testing.assert_allclose(out.gripper_pose, poses, atol=2e-6)


@pytest.mark.parametrize("seed", SEEDS)
def test_phases_after_hp_are_bit_identical_and_state_at_hp_is_ground_truth(seed):
    ep, _ = synthetic_episode(seed)
    out, draw = augment(ep, SETTINGS, np.random.default_rng(seed), seed=seed, copy_index=0, episode_id="a")
    s0, hp = draw.start, draw.hp
    n = hp - s0  # H_p in the augmented episode's indices
    assert out.augmentation.phase_split == n
    for name in ("points", "point_counts", "jaw", "gripper_pose", "object_poses", "contacts"):
        assert np.array_equal(getattr(out, name)[n:], getattr(ep, name)[hp:]), name
    for name in ("actions", "rewards", "terminated", "truncated"):
        assert np.array_equal(getattr(out, name)[n:], getattr(ep, name)[hp:]), name
    assert np.array_equal(out.rewards, ep.rewards[s0:]) and np.array_equal(out.terminated, ep.terminated[s0:])
    assert np.array_equal(out.jaw, ep.jaw[s0:]) and np.array_equal(out.actions[:, 0], ep.actions[s0:, 0])


@pytest.mark.parametrize("seed", SEEDS)
def test_object_displacement_matches_the_closed_form(seed):
    ep, _ = synthetic_episode(seed)
    out, draw = augment(ep, SETTINGS, np.random.default_rng(seed), seed=seed, copy_index=0, episode_id="a")
    s0, hp = draw.start, draw.hp
    a, abar = ep.actions.astype(np.float64), np.zeros_like(ep.actions, dtype=np.float64)
    abar[s0:] = out.actions
    for t in range(s0, hp):
        D = DELTA_XYZ * (a[t:hp, 1:4] - abar[t:hp, 1:4]).sum(axis=0)
        theta = DELTA_THETA * (a[t:hp, 4] - abar[t:hp, 4]).sum()
        np.testing.assert_allclose(out.points[t - s0, 1:], ep.points[t, 1:] - D, atol=2e-6)
        c, s = math.cos(theta), math.sin(theta)
        g = ep.points[t, 0].astype(np.float64)
        expected = np.stack([c * g[:, 0] - s * g[:, 1], s * g[:, 0] + c * g[:, 1], g[:, 2]], axis=1)
        np.testing.assert_allclose(out.points[t - s0, 0], expected, atol=2e-6)


@pytest.mark.parametrize("seed", SEEDS)
def test_actions_stay_normalised_and_every_copy_differs_in_the_non_trivial_phase(seed):
    ep, _ = synthetic_episode(seed)
    rng = np.random.default_rng(seed)
    copies = [augment(ep, SETTINGS, rng, seed=seed, copy_index=k, episode_id=f"a{k}") for k in range(6)]
    for out, draw in copies:
        assert np.all(np.abs(out.actions) <= 1.0)
        n = draw.hp - draw.start
        assert not np.array_equal(out.actions[:n], ep.actions[draw.start : draw.hp])
        assert not np.array_equal(out.points[:n], ep.points[draw.start : draw.hp])
    assert len({out.actions[:1].tobytes() for out, _ in copies}) == 6


@pytest.mark.parametrize("seed", SEEDS)
def test_augmented_gripper_stays_feasible_and_above_lz(seed):
    ep, _ = synthetic_episode(seed)
    out, draw = augment(ep, SETTINGS, np.random.default_rng(seed), seed=seed, copy_index=0, episode_id="a")
    n = draw.hp - draw.start
    pose = out.gripper_pose[:n].astype(np.float64)
    assert np.all(pose[:, 2] >= SETTINGS.lz - 1e-6)
    assert np.all(pose[:, :3] >= np.array(SETTINGS.pivot_low) - 1e-6)
    assert np.all(pose[:, :3] <= np.array(SETTINGS.pivot_high) + 1e-6)
    assert np.all(np.abs(pose[:, 3]) <= SETTINGS.yaw_limit + 1e-6)


def test_phase_split_uses_the_height_criterion_with_margin():
    ep, _ = synthetic_episode(3)
    h = heights(ep, SETTINGS)
    first_below = int(np.nonzero(h < SETTINGS.lz)[0][0])
    assert phase_split(ep, SETTINGS) == first_below - SETTINGS.margin_steps
    assert phase_split(ep, MeaSettings(margin_steps=0)) == first_below
    rec = MeaSettings(height_from="recorded")
    assert phase_split(ep, rec) == first_below - 1  # the synthetic poses follow the actions exactly


def test_infeasible_draws_are_rejected_and_can_cut_the_episode():
    ep, _ = synthetic_episode(5)
    # a workspace barely larger than the recorded path: most draws leave it
    p = ep.gripper_pose[:, :3]
    tight = MeaSettings(pivot_low=tuple(p.min(0) - 0.001), pivot_high=tuple(p.max(0) + 0.001), max_tries=3)
    out, draw = augment(ep, tight, np.random.default_rng(0), seed=0, copy_index=0, episode_id="a")
    assert draw.rejections > 0
    assert draw.cut and draw.start > 0
    if out is not None:
        assert out.num_steps == ep.num_steps - draw.start


def test_clipped_recorded_motion_cannot_be_augmented_across():
    ep, _ = synthetic_episode(6)
    pose = np.array(ep.gripper_pose, copy=True)
    pose[3:, 0] += 0.01  # step 2 -> 3 moved 1 cm more than commanded (clipping, a push...)
    from dataclasses import replace

    bumped = replace(ep, gripper_pose=pose)
    _, draw = augment(bumped, SETTINGS, np.random.default_rng(0), seed=0, copy_index=0, episode_id="a")
    assert draw.start >= 3


def test_structured_action_scales_rotates_and_clips():
    a = np.array([0.5, 0.4, -0.3, 0.6, 0.1])
    g = np.array([0.8, 0.9, math.pi / 2, 0.3, -1.0])
    out = structured_action(a, g)
    np.testing.assert_allclose(out[1:3], [0.3 * 0.8, 0.4 * 0.8], atol=1e-12)  # R(90deg) (0.32, -0.24)
    np.testing.assert_allclose(out[3], 0.54)
    np.testing.assert_allclose(out[4], 0.1 - 0.3)
    assert out[0] == 0.5
    big = structured_action(np.array([0, 1.0, 1.0, 1.0, 1.0]), np.array([1.0, 1.0, math.pi / 4, 0.3, 1.0]))
    assert np.all(np.abs(big) <= 1.0)


def test_group_draws_respect_their_ranges():
    rng = np.random.default_rng(0)
    g = np.array([draw_group(rng, SETTINGS) for _ in range(2000)])
    assert g[:, 0].min() >= 0.75 and g[:, 0].max() <= 1.0 and g[:, 1].min() >= 0.75
    assert g[:, 2].min() >= 0 and g[:, 2].max() < 2 * math.pi and g[:, 3].max() <= 0.3
    assert g[:, 4].min() >= -1 and g[:, 4].max() <= 1


def test_discrete_actions_rotate_only_xy_by_quarter_turns():
    s = MeaSettings(discrete=True)
    rng = np.random.default_rng(1)
    x = np.array([0, 1.0, 0, 0, 0])
    outs = {tuple(structured_action(x, draw_group(rng, s), True)) for _ in range(400)}
    assert outs <= {(0, 1, 0, 0, 0), (0, 0, 1, 0, 0), (0, -1, 0, 0, 0), (0, 0, -1, 0, 0)}
    rotated = sum(
        o != (0, 1, 0, 0, 0)
        for o in [tuple(structured_action(x, draw_group(rng, s), True)) for _ in range(2000)]
    )
    assert 0.15 < rotated / 2000 < 0.3  # p = 0.3 of drawing a rotation, 3/4 of which change the action
    for z_like in (np.array([0, 0, 0, 1.0, 0]), np.array([0, 0, 0, 0, -1.0]), np.array([1.0, 0, 0, 0, 0])):
        assert np.array_equal(structured_action(z_like, np.array([1, 1, math.pi / 2, 0, 0]), True), z_like)


def test_same_rng_gives_the_same_copy():
    ep, _ = synthetic_episode(2)
    a, _ = augment(ep, SETTINGS, np.random.default_rng(9), seed=9, copy_index=0, episode_id="a")
    b, _ = augment(ep, SETTINGS, np.random.default_rng(9), seed=9, copy_index=0, episode_id="a")
    assert a.encode() == b.encode()


def test_isometric_rotation_is_an_isometry_and_composes_with_mea():
    ep, _ = synthetic_episode(4)
    phi = 0.7
    rot = isometric_copy(ep, phi, seed=1, copy_index=0, episode_id="r")
    assert rot.augmentation.kind == "isometric"
    # pairwise distances inside each observation are preserved
    d0 = np.linalg.norm(ep.points[3, 1] - ep.points[3, 2], axis=-1)
    d1 = np.linalg.norm(rot.points[3, 1] - rot.points[3, 2], axis=-1)
    np.testing.assert_allclose(d0, d1, atol=1e-5)
    np.testing.assert_allclose(rotate_actions(rot.actions, -phi)[:, 3:], ep.actions[:, 3:])
    mea, _ = augment(ep, SETTINGS, np.random.default_rng(0), seed=0, copy_index=0, episode_id="m")
    both = compose_with_mea(mea, phi)
    assert both.augmentation.kind == "mea+isometric" and float(both.augmentation.params["rotation"][0]) == phi
    Episode.decode(both.encode())  # still a valid wire message
