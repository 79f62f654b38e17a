"""Observable experts: they decide only from what an observation carries, so a policy can imitate them.

Each general task's observable expert goes first to the object nearest the gripper, probes it, and
switches to the other one exactly when the probed object is not seen to move. The tests hide the
task's fixedness (its body attributes and ``fixed_index``), the contacts and the env's contact
queries while the expert decides, and swap which body is fixed after the first decision, where the
observation cannot tell: the expert must follow the motion it sees. The demo recorder gets one
probe-style and one direct-style demonstration from the layouts of its seed stream.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pybullet as pb
import pytest

from services.actor.config import ActorConfig
from services.actor.rollout import RolloutActor
from services.tasks import GENERAL_TASKS, make_env
from services.tasks.experts import layout_style, nearest_object, seed_for_style

pytestmark = pytest.mark.unit

HIDDEN = ("fixed", "movable", "locked", "unlocked", "order")  # what tells the objects apart


@pytest.fixture(scope="module", params=GENERAL_TASKS)
def env(request):
    e = make_env(request.param)
    yield e
    e.close()


def _refuse(*_args, **_kwargs):
    raise AssertionError("the observable expert read privileged state")


def _blind_act(env, expert, obs) -> np.ndarray:
    """``expert.act`` with the fixedness, the contacts and the contact queries out of reach."""
    task = env.task
    saved = {k: task.__dict__.pop(k) for k in HIDDEN if k in task.__dict__}
    task.fixed_index = env.contacts = env.gripper_touches = _refuse
    try:
        return expert.act(dataclasses.replace(obs, contacts=None))
    finally:
        del task.fixed_index, env.contacts, env.gripper_touches
        task.__dict__.update(saved)


def _swap_bodies(env) -> None:
    """Exchange the two objects (poses and slots): the observation stays the same, but the body
    at each place, and so which place holds the fixed one, is swapped."""
    task, c = env.task, env.client
    a, b = task.order
    pose_a = pb.getBasePositionAndOrientation(a, physicsClientId=c)
    pose_b = pb.getBasePositionAndOrientation(b, physicsClientId=c)
    pb.resetBasePositionAndOrientation(a, *pose_b, physicsClientId=c)
    pb.resetBasePositionAndOrientation(b, *pose_a, physicsClientId=c)
    task.order = [b, a]


def _episode(env, seed: int, swap: bool = False) -> dict:
    """The observable expert on ``seed``; ``swap``: swap the bodies after its first decision."""
    obs = env.reset(seed)
    nearest = nearest_object(obs)
    expert = env.task.observable_expert(env)
    touched: list[int] = []  # slots in the order the gripper first touched them
    targets: list[int] = []  # slots in the order the expert acted on them
    for _ in range(env.settings.max_steps):
        obs, _, terminated, truncated, _ = env.step(_blind_act(env, expert, obs))
        if not targets or targets[-1] != expert.target:
            targets.append(expert.target)
        if swap and env.t == 1:
            before = obs
            _swap_bodies(env)
            obs = env.observe()
            assert np.array_equal(before.points, obs.points)  # nothing the expert could see
        touched += [i for i in np.flatnonzero(obs.contacts) if i not in touched]
        if terminated or truncated:
            break
    return {"success": bool(terminated), "nearest": nearest, "targets": targets, "touched": touched,
            "fixed": env.task.fixed_index(), "steps": env.t}  # fmt: skip


def _check(r: dict, switched: bool) -> None:
    """The expert acted on the nearest object first and switched to the other exactly when the
    nearest one is fixed; the gripper touched the fixed object exactly when it switched."""
    assert r["success"], r
    assert r["targets"][0] == r["nearest"] and r["touched"][:1] in ([], [r["nearest"]]), r
    if switched:
        assert r["nearest"] == r["fixed"] and r["targets"] == [r["nearest"], 1 - r["nearest"]], r
        assert r["fixed"] in r["touched"], r
    else:
        assert r["nearest"] != r["fixed"] and r["targets"] == [r["nearest"]], r
        assert r["fixed"] not in r["touched"], r


def _style_seeds(env) -> dict[str, int]:
    """The first seed (from 0) of each layout style: not a chosen subset."""
    return {style: seed_for_style(env, style, itertools.count(0)) for style in ("probe", "direct")}


@pytest.mark.timeout(120)
def test_goes_to_the_nearest_object_and_switches_only_when_it_does_not_move(env):
    for style, seed in _style_seeds(env).items():
        # probe layout: the nearest is fixed, probed, seen not to move, then the other one;
        # direct layout: the nearest moves, no switch, the fixed object is never touched
        _check(_episode(env, seed), switched=style == "probe")


@pytest.mark.timeout(120)
def test_decides_from_motion_when_the_fixed_body_is_swapped_after_the_first_decision(env):
    """On a probe layout the swap makes the nearest object the movable one (no switch may follow);
    on a direct layout the fixed one (the expert must switch). The observation is the same either
    way, so only the motion seen while probing can tell the expert."""
    for style, seed in _style_seeds(env).items():
        _check(_episode(env, seed, swap=True), switched=style == "direct")


@pytest.mark.timeout(120)
def test_two_demos_are_one_probe_and_one_direct_from_the_layouts_of_the_seed_stream():
    actor = RolloutActor(ActorConfig(task="block_pull", policy="expert", demos=2, seed_base=500), "test")
    try:
        episodes = [actor.expert_episode(k) for k in range(2)]
        assert [b.meta["policy_kind"] for b in episodes] == ["expert_probe", "expert_direct"]
        assert all(b.success for b in episodes)
        seeds = [b.meta["seed"] for b in episodes]
        # the first seed of the stream whose layout gives each style, in turn (deterministic)
        stream = itertools.count(500)
        expected = [seed_for_style(actor.env, "probe", stream), seed_for_style(actor.env, "direct", stream)]
        assert seeds == expected
        for seed, style in zip(seeds, ("probe", "direct"), strict=True):
            assert layout_style(actor.env, actor.env.reset(seed)) == style
        # the probe demonstration touches the fixed block, the direct one never; both drag the other
        for b, touches_fixed in zip(episodes, (True, False), strict=True):
            fixed = int(b.meta["fixed_object"])
            assert any(o.contacts[fixed] for o in b.obs) == touches_fixed
            drag = b.obs[-1].object_poses[1 - fixed, :3] - b.obs[0].object_poses[1 - fixed, :3]
            assert np.linalg.norm(drag) > 0.01
    finally:
        actor.env.close()
