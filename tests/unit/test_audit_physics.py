"""The physics audit: un-augmented replays, MEA copies and rotated copies pass, wrong copies fail,
and a rotated copy that fits nowhere in the simulator is reported as not simulable.

One block_pick demonstration (direct style, ~8 steps) is recorded once per module; every replay
costs ~40 ms per step on one core.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mea_tools.audit.general import record_demos
from services.augmenter.audit_physics import audit_episode, identity_replay
from services.augmenter.audit_placement import NotSimulableError, place, plan_placement, yaw_branch
from services.augmenter.core.audit_metrics import NON_TRIVIAL, AuditTolerance
from services.augmenter.core.isometric import isometric_copy, rotation_fits
from services.augmenter.core.mea import MeaSettings, augment
from services.augmenter.core.pipeline import episode_seed, isometric_copies

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def pick():
    from services.actor.config import ActorConfig
    from services.actor.rollout import RolloutActor

    actor = RolloutActor(ActorConfig(task="block_pick", policy="expert", expert_style="direct"), "test-audit")
    demos, _ = record_demos(actor, 1, 4)
    assert demos and demos[0].terminated[-1]
    yield actor.env, demos[0]
    actor.env.close()


def mea_copy(demo, k: int):
    copy, draw = augment(demo, MeaSettings(), np.random.default_rng([7, k]), seed=7, copy_index=k,
                         episode_id=f"{demo.episode_id}.mea{k}")  # fmt: skip
    assert copy is not None and copy.augmentation.phase_split >= 1
    return copy, draw


def with_points(ep, points):
    return dataclasses.replace(ep, points=points.astype(np.float32))


@pytest.mark.timeout(60)
def test_identity_replay_is_valid_and_reproduces_rewards(pick):
    env, demo = pick
    r = identity_replay(env, demo)
    assert r.valid.all(), (r.chamfer, r.surface, r.jaw_error)
    assert r.reward_ok.all() and r.terminated_ok.all()
    # the replay draws its points independently of the recording: sampling noise, not a copy
    assert (r.chamfer[:, 0] > 1.0).all()
    assert (r.pivot_error_mm < 1.0).all()


@pytest.mark.timeout(60)
def test_mea_copies_of_a_demo_are_valid(pick):
    env, demo = pick
    nontrivial, consistent = [], []
    for k in range(3):
        copy, _ = mea_copy(demo, k)
        r = audit_episode(env, copy, demo)
        nontrivial.append(r.valid[r.phase == NON_TRIVIAL])
        consistent.append(r.consistent)
    valid = np.concatenate(nontrivial)
    assert len(valid) >= 3 and valid.mean() >= 0.99
    assert np.concatenate(consistent).all()


@pytest.mark.timeout(60)
def test_objects_shifted_3cm_are_flagged(pick):
    env, demo = pick
    copy, _ = mea_copy(demo, 0)
    n = copy.augmentation.phase_split
    points = np.array(copy.points, np.float64)
    points[:n, 1:] += [0.03, 0.0, 0.0]  # objects 3 cm off in every non-trivial start state
    r = audit_episode(env, with_points(copy, points), demo)
    assert not r.valid[:n].any()
    assert (r.chamfer[:n, 1:] > AuditTolerance.for_task("block_pick").object_chamfer_mm).all()
    assert r.reward_ok.all()  # only the observations are wrong


@pytest.mark.timeout(60)
def test_flipped_object_offset_is_flagged(pick):
    env, demo = pick
    copy, draw = mea_copy(demo, 1)
    n = copy.augmentation.phase_split
    D = draw.offset_xyz[draw.start : draw.start + n]
    assert (np.linalg.norm(D, axis=1) > 0.005).any()  # the copy really moves the gripper
    points = np.array(copy.points, np.float64)
    points[:n, 1:] += 2 * D[:, None, None, :]  # objects at +D instead of -D
    r = audit_episode(env, with_points(copy, points), demo)
    far = np.linalg.norm(2 * D, axis=1) >= 0.01
    assert far.any() and not r.valid[:n][far].any()


@pytest.mark.timeout(60)
def test_a_few_millimetres_are_resolved_by_the_surface_distance(pick):
    """Sampling noise hides a 5 mm error from the Chamfer distance of two draws, not from the
    distance to the simulated surface."""
    env, demo = pick
    copy, _ = mea_copy(demo, 2)
    n = copy.augmentation.phase_split
    points = np.array(copy.points, np.float64)
    points[:n, 1:] += [0.0, 0.005, 0.0]
    r = audit_episode(env, with_points(copy, points), demo)
    tol = AuditTolerance.for_task("block_pick")
    assert (r.surface[:n, 1:] > tol.object_surface_mm).all()
    assert not r.valid[:n].any()


@pytest.mark.timeout(60)
def test_wrong_reward_is_flagged(pick):
    env, demo = pick
    rewards = np.array(demo.rewards, copy=True)
    rewards[-1] = 0.0
    r = audit_episode(env, dataclasses.replace(demo, rewards=rewards), demo)
    assert not r.reward_ok[-1] and not r.valid[-1] and r.valid[:-1].all()


def placed_isometric_copy(env, demo):
    """The first of the demo's isometric copies (as the pipeline draws them) that the sim can place."""
    for copy in isometric_copies(demo, 8, episode_seed(0, demo.episode_id)):
        try:
            return copy, plan_placement(env, copy)
        except NotSimulableError:
            continue
    pytest.fail("none of 8 isometric copies can be placed")


def _yaw(quat):
    x, y, z, w = np.asarray(quat, np.float64).T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


@pytest.mark.timeout(60)
def test_a_rotated_copy_is_played_in_the_turned_scene(pick):
    env, demo = pick
    copy, placement = placed_isometric_copy(env, demo)
    phi = float(copy.augmentation.params["rotation"][0])
    assert phi != 0.0 and placement.phi == phi
    obs = place(env, demo.seed, placement.episode.gripper_pose[0], float(demo.jaw[0]), placement=placement)
    # the sim's objects and gripper start where the placed copy says: turned by phi, shifted alike
    placed = placement.episode
    np.testing.assert_allclose(obs.object_poses[:, :3], placed.object_poses[0, :, :3], atol=1e-3)
    dyaw = _yaw(obs.object_poses[:, 3:]) - _yaw(demo.object_poses[0, :, 3:]) - phi
    assert np.all(np.abs((dyaw + np.pi) % (2 * np.pi) - np.pi) < 1e-3)
    np.testing.assert_allclose(obs.gripper_pose[:3], placed.gripper_pose[0, :3], atol=1e-3)
    shift = placed.gripper_pose[:, :2] - copy.gripper_pose[:, :2]  # one world translation for all
    np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-5)
    # replayed: valid in free space, rewards reproduced, pivot on the turned path
    r = audit_episode(env, copy, demo)
    assert r.valid[~r.touched[1:]].all(), (r.chamfer, r.surface, r.jaw_error)
    assert r.reward_ok.all() and r.terminated_ok.all() and (r.pivot_error_mm < 2.0).all()
    # a shortened first move (what clipping a rotated diagonal did) is flagged
    short = np.array(copy.actions, copy=True)
    assert np.abs(short[0, 1:3]).max() > 0.5
    short[0, 1:3] *= 0.6
    bad = audit_episode(env, dataclasses.replace(copy, actions=short), demo)
    assert not bad.valid[0] and not bad.obs_ok[1]


@pytest.mark.timeout(60)
def test_a_copy_past_the_wrist_range_is_not_simulable(pick):
    env, demo = pick
    phis = [p for p in np.linspace(0, 2 * np.pi, 73)[1:-1] if rotation_fits(demo.actions, p)]
    past = [
        p
        for p in phis
        if yaw_branch(isometric_copy(demo, p, seed=0, copy_index=0, episode_id="x"), 2.9) is None
    ]
    assert past and len(past) < len(phis)
    with pytest.raises(NotSimulableError, match="wrist"):
        audit_episode(env, isometric_copy(demo, past[0], seed=0, copy_index=0, episode_id="x"), demo)
