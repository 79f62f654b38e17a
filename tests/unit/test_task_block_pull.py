"""Block Pull: placement, the hidden movable block, the success predicate, the static fixed block
and both scripted experts."""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest

from services.tasks import make_env
from services.tasks.block_pull import HALF, MIN_SEPARATION, BlockPull, PullExpert, footprint
from services.tasks.robot import WORKSPACE

pytestmark = pytest.mark.unit

# Measured over seeds 0..99 with the default settings and the safe-height approach: direct 100/100
# (mean 9.9 steps, max 13), probe 100/100 (mean 22.6, max 27). (The earlier low-travel experts:
# 300/300 each over 0..299, the probe touching the fixed block in every episode and the direct
# style never touching it.) The expert tests below use the first ten seeds, not a chosen subset.
EXPERT_SEEDS = range(10)


@pytest.fixture(scope="module")
def env():
    e = make_env("block_pull")
    yield e
    e.close()


def _pose(env, body: int) -> tuple[np.ndarray, np.ndarray]:
    pos, quat = pb.getBasePositionAndOrientation(body, physicsClientId=env.client)
    return np.array(pos), np.array(quat)


def _place(env, body: int, xy, yaw: float = 0.0) -> None:
    quat = pb.getQuaternionFromEuler((0, 0, yaw))
    pb.resetBasePositionAndOrientation(body, (xy[0], xy[1], HALF[2]), quat, physicsClientId=env.client)
    pb.resetBaseVelocity(body, (0, 0, 0), (0, 0, 0), physicsClientId=env.client)


@pytest.mark.timeout(60)
def test_reset_places_both_blocks_apart_flat_and_inside_the_workspace(env):
    task = env.task
    for seed in range(20):
        env.reset(seed)
        poses = task.object_poses()
        assert poses.shape == (2, 7)
        assert abs(poses[0, 0] - poses[1, 0]) < 1e-6  # same x, apart along y
        assert abs(poses[0, 1] - poses[1, 1]) > MIN_SEPARATION
        assert not pb.getClosestPoints(task.fixed, task.movable, 0.02, physicsClientId=env.client)
        for pos, quat in zip(poses[:, :3], poses[:, 3:], strict=True):
            roll, pitch, yaw = pb.getEulerFromQuaternion(quat)
            assert (
                abs(pos[2] - HALF[2]) < 1e-3 and abs(roll) < 1e-3 and abs(pitch) < 1e-3
            )  # flat, on the floor
            reach = footprint(yaw)
            assert WORKSPACE[0, 0] < pos[0] - reach and pos[0] + reach < WORKSPACE[0, 1]
            assert WORKSPACE[1, 0] < pos[1] - reach and pos[1] + reach < WORKSPACE[1, 1]
        for body in (task.fixed, task.movable):
            lin, ang = pb.getBaseVelocity(body, physicsClientId=env.client)
            assert np.linalg.norm(lin) < 1e-2 and np.linalg.norm(ang) < 1e-1  # at rest, nothing exploded


@pytest.mark.timeout(60)
def test_which_block_moves_varies_and_is_invisible(env):
    task = env.task
    first = set()
    for seed in range(20):
        env.reset(seed)
        first.add(task.order[0] == task.movable)
    assert first == {True, False}
    # same shape and colour: only the mass differs
    c = env.client
    col = [pb.getCollisionShapeData(b, -1, physicsClientId=c)[0][2:5] for b in (task.fixed, task.movable)]
    vis = [pb.getVisualShapeData(b, physicsClientId=c)[0][2:8] for b in (task.fixed, task.movable)]
    assert col[0] == col[1] and vis[0] == vis[1]
    assert pb.getDynamicsInfo(task.fixed, -1, physicsClientId=c)[0] == 0.0
    assert pb.getDynamicsInfo(task.movable, -1, physicsClientId=c)[0] > 0.0
    # swapping the two bodies (poses and slots) leaves the observation unchanged
    before = env.reset(3)
    p_fixed, p_movable = _pose(env, task.fixed), _pose(env, task.movable)
    pb.resetBasePositionAndOrientation(task.fixed, *p_movable, physicsClientId=c)
    pb.resetBasePositionAndOrientation(task.movable, *p_fixed, physicsClientId=c)
    task.order = task.order[::-1]
    after = env.observe()
    assert np.array_equal(before.points, after.points)
    assert np.array_equal(before.point_counts, after.point_counts)
    assert np.array_equal(before.object_poses, after.object_poses)
    counts = before.point_counts[1:]
    assert abs(int(counts[0]) - int(counts[1])) < 0.25 * counts.mean()  # comparable views of both


@pytest.mark.timeout(60)
def test_success_when_the_blocks_touch_and_not_when_apart(env):
    task = env.task
    env.reset(0)
    assert not task.success(env)
    x, y = _pose(env, task.fixed)[0][:2]
    side = 1.0 if y < 0 else -1.0
    _place(env, task.fixed, (x, y))
    _place(env, task.movable, (x, y + side * (2 * HALF[1] + 0.005)))  # 5 mm gap
    assert not task.success(env)
    _place(env, task.movable, (x, y + side * (2 * HALF[1] + 0.001)))  # 1 mm: touching
    assert task.success(env)
    _place(env, task.movable, (x, y + side * 2 * HALF[1]))  # face to face, settled by physics
    for _ in range(10):
        env.step_physics()
    assert pb.getContactPoints(task.fixed, task.movable, physicsClientId=env.client)
    assert task.success(env)
    # a corner against a face counts too
    _place(env, task.movable, (x, y + side * (HALF[1] + HALF[0] * math.sqrt(2))), yaw=math.pi / 4)
    assert task.success(env)


@pytest.mark.timeout(60)
def test_fixed_block_does_not_move_when_pushed(env):
    task = env.task
    env.reset(4)
    start = _pose(env, task.fixed)
    expert = PullExpert(env, task, [task.fixed])  # drags at the fixed block for the whole episode
    pressed = 0
    for _ in range(20):
        env.step(expert.act())
        pressed += bool(env.gripper_touches(task.fixed))
    assert pressed >= 5
    end = _pose(env, task.fixed)
    assert np.array_equal(start[0], end[0]) and np.array_equal(start[1], end[1])


def _run_expert(env, seed: int, style: str) -> dict:
    task = env.task
    env.reset(seed)
    fixed0 = _pose(env, task.fixed)
    movable0 = _pose(env, task.movable)[0]
    expert = task.expert(env, style, np.random.default_rng(seed))
    touched_fixed, success, steps = False, False, 0
    for _ in range(env.settings.max_steps):
        a = expert.act()
        assert a.shape == (5,) and np.all(np.abs(a) <= 1.0)
        _, reward, terminated, truncated, info = env.step(a)
        steps += 1
        touched_fixed |= bool(env.gripper_touches(task.fixed))
        if terminated or truncated:
            success = bool(info["success"]) and reward == 1.0
            break
    fixed1 = _pose(env, task.fixed)
    return {
        "success": success,
        "steps": steps,
        "touched_fixed": touched_fixed,
        "fixed_still": np.array_equal(fixed0[0], fixed1[0]) and np.array_equal(fixed0[1], fixed1[1]),
        "movable_moved": float(np.linalg.norm(_pose(env, task.movable)[0] - movable0)),
    }


@pytest.mark.timeout(60)
@pytest.mark.parametrize("style", ["direct", "probe"])
@pytest.mark.slow
def test_expert_pulls_the_movable_block_into_the_fixed_one(env, style):
    runs = [_run_expert(env, seed, style) for seed in EXPERT_SEEDS]
    assert all(r["success"] for r in runs), runs
    assert all(r["fixed_still"] and r["movable_moved"] > 0.01 for r in runs), runs
    if style == "probe":  # the demo really interacts with the fixed block first
        assert all(r["touched_fixed"] for r in runs), runs
    else:
        assert not any(r["touched_fixed"] for r in runs), runs
    assert max(r["steps"] for r in runs) <= (30 if style == "probe" else 15), runs


@pytest.mark.timeout(60)
def test_reset_after_a_pressed_contact_places_the_blocks_as_sampled(env):
    """Regression: stale contact manifolds (blocks pressed together at the end of seed 235) once
    carried over through pb.restoreState and shot the movable block across the table at seed 236."""
    assert _run_expert(env, 235, "direct")["success"]
    env.reset(236)
    x, ys, _ = BlockPull.sample_layout(np.random.default_rng(236))
    poses = env.task.object_poses()
    assert np.allclose(poses[:, 0], x, atol=1e-4)
    assert np.allclose(np.sort(poses[:, 1]), np.sort(ys), atol=1e-4)
    for body in (env.task.fixed, env.task.movable):
        lin, _ = pb.getBaseVelocity(body, physicsClientId=env.client)
        assert np.linalg.norm(lin) < 1e-2


def test_unknown_expert_style_is_rejected(env):
    with pytest.raises(ValueError):
        env.task.expert(env, "teleport", np.random.default_rng(0))
