"""The physics audit of Surgical Grasp Any (``services.augmenter.audit_surgical``): raw demonstrations
replay within the tolerances, MEA copies do too, and copies whose claims the physics contradicts are
found out."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from proto.episode import Episode
from services.augmenter.audit_surgical import SurgicalTolerance, audit_surgical, floor_covered
from services.augmenter.core.audit_metrics import NON_TRIVIAL
from services.augmenter.core.mea_discrete import MeaDiscreteSettings, mea_discrete_copies, phase_split

pytestmark = pytest.mark.unit
S = MeaDiscreteSettings()


@pytest.fixture(scope="module")
def env():
    from services.tasks import make_env

    e = make_env("surgical_grasp_any")
    yield e
    e.close()


@pytest.fixture(scope="module")
def demo(env) -> Episode:
    from services.episodes.builder import EpisodeBuilder
    from services.episodes.rollout import run_episode
    from services.tasks.surgical.oracle import Oracle

    b = EpisodeBuilder(task="surgical_grasp_any", seed=7, actor_id="t", policy_version=-1,
                       policy_kind="expert_direct", is_demo=True, segments=env.segment_names)  # fmt: skip
    run_episode(env, 7, lambda _o: Oracle(env).act(), b)
    assert b.success
    return b.finish("demo-7")


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_the_demonstration_and_its_copies_replay_within_the_tolerances(env, demo):
    tol = SurgicalTolerance()
    raw = audit_surgical(env, demo, demo, phase_split(demo, S), tol)
    assert raw.valid.all() and all(floor_covered([raw], tol).values())
    assert not raw.moved.any() and (raw.phase == NON_TRIVIAL).sum() == phase_split(demo, S)
    copies = mea_discrete_copies(demo, dataclasses.replace(S, copies=6), 11, None)
    results = [audit_surgical(env, c, demo, c.augmentation.phase_split, tol) for c in copies]
    valid = np.concatenate([r.valid for r in results])
    moved = np.concatenate([r.moved for r in results])
    assert moved.sum() >= 50 and valid.mean() >= 0.99, (moved.sum(), valid.mean())
    worst = max(float(r.pivot_mm[r.moved].max()) for r in results if r.moved.any())
    assert worst < tol.pivot_mm and worst > float(raw.pivot_mm.max())  # turned moves lag their own way


@pytest.mark.timeout(60)
def test_claims_the_physics_contradicts_are_invalid(env, demo):
    """A copy's action turned without moving its poses (the pivot ends 3 mm sim off), and a copy
    whose instrument sits in the object (the object is pushed or the tool blocked)."""
    copy = mea_discrete_copies(demo, dataclasses.replace(S, copies=1), 11, None)[0]
    hp = copy.augmentation.phase_split
    t = next(t for t in range(hp) if np.any(copy.actions[t, 1:3] != 0))
    turned = copy.actions.copy()
    turned[t, 1:3] = [-turned[t, 2], turned[t, 1]]
    r = audit_surgical(env, dataclasses.replace(copy, actions=turned), demo, hp)
    assert not r.valid[t] and not r.checks["pivot"][t] and r.pivot_mm[t] > 0.5
    assert r.valid[:t].all()
    # the instrument placed straight down onto the object: the jaws land on it, not around it
    inside = copy.gripper_pose.copy()
    grasp = demo.object_poses[0, 0, :3]
    env.reset(demo.seed)
    top = env.instrument.pivot_from_tip(np.r_[grasp[:2], 0.0])  # tips at the tray, on the object
    inside[t, :3] = top
    inside[t + 1, :3] = top + 0.015 * copy.actions[t, 1:4]
    r = audit_surgical(env, dataclasses.replace(copy, gripper_pose=inside), demo, hp)
    assert not r.valid[t] and not (r.checks["object"][t] and r.checks["pivot"][t]), (
        r.object_mm[t],
        r.pivot_mm[t],
    )


@pytest.mark.timeout(60)
def test_the_augmenters_background_audit_replays_surgical_copies(demo):
    from services.augmenter.audit_worker import PhysicsAudit

    copy = mea_discrete_copies(demo, dataclasses.replace(S, copies=1), 3, None)[0]
    audit = PhysicsAudit()
    try:
        valid = audit(copy, demo)
    finally:
        audit.close()
    assert valid.shape == (copy.num_steps,) and valid.dtype == bool and valid.mean() >= 0.9
