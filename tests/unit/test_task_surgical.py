"""Surgical Grasp Any: the gymnasium contract, determinism, the latched hybrid controller, the grasp
rule (both jaws), refused actions, the step contract and the oracle."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from proto.discrete_actions import NAMES, TOGGLE, index_of
from services.observation.dsa import decode_state_rows, dsa_image, world_clouds
from services.tasks import make_env
from services.tasks.surgical import scene as scene_module
from services.tasks.surgical.env import SurgicalGraspEnv
from services.tasks.surgical.objects import grasp_yaw
from services.tasks.surgical.oracle import Oracle
from services.tasks.surgical.settings import (
    ControllerSettings,
    SurgicalCameraSettings,
    SurgicalSettings,
    real,
)
from tests.helpers.env_asserts import refused_actions_change_nothing

pytestmark = pytest.mark.unit

FIELDS = ("points", "point_counts", "gripper_pose", "object_poses", "contacts", "jaw", "controller_state",
          "fsm_state", "image")  # fmt: skip
SMALL = SurgicalCameraSettings(points_per_segment=64)


@pytest.fixture(scope="module")
def env():
    e = make_env("surgical_grasp_any", SurgicalSettings(camera=SMALL))
    yield e
    e.close()


@pytest.fixture(scope="module")
def free_env():
    """The policy acts from the first step (no P-controller): for placing the tool by hand."""
    e = SurgicalGraspEnv(SurgicalSettings(camera=SMALL, controller=ControllerSettings(enabled=False)))
    yield e
    e.close()


def _rollout(env, seed: int, indices) -> list:
    obs = [env.reset(seed)]
    for i in indices:
        obs.append(env.step(env.discrete_action(int(i)))[0])
    return obs


def _same(a, b) -> None:
    for field in FIELDS:
        assert np.array_equal(getattr(a, field), getattr(b, field)), field


@pytest.mark.timeout(60)
def test_registered_env_passes_the_gymnasium_checker():
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    import services.tasks.gym_env  # noqa: F401 - registers the ids

    env = gym.make("mea/SurgicalGraspAny-v0", points_per_segment=32)
    try:
        check_env(env.unwrapped, skip_render_check=True)
        obs, _ = env.reset(seed=1)
        assert env.observation_space.contains(obs) and obs["controller_state"] == 1
        assert obs["image"].shape == (3, 64, 64) and obs["image"].dtype == np.uint8
        assert decode_state_rows(obs["image"]) == (0, obs["fsm_state"], 1)
        obs, reward, terminated, truncated, info = env.step(NAMES.index("+x"))
        assert env.observation_space.contains(obs) and not terminated and not truncated
        assert {"executed_action", "controller_acted", "fsm", "success", "gripper_pose"} <= set(info)
    finally:
        env.close()


@pytest.mark.timeout(60)
def test_same_seed_and_actions_give_identical_observations(env):
    indices = np.random.default_rng(7).integers(0, len(NAMES), 12)
    first = _rollout(env, 11, indices)
    env.reset(3)  # a whole episode in between (grasp, lift) must leave no trace
    oracle = Oracle(env)
    while not any(env.step(oracle.act())[2:4]):
        pass
    again = _rollout(env, 11, indices)
    fresh_env = make_env("surgical_grasp_any", SurgicalSettings(camera=SMALL))
    try:
        fresh = _rollout(fresh_env, 11, indices)
    finally:
        fresh_env.close()
    for a, b, c in zip(first, again, fresh, strict=True):
        _same(a, b)
        _same(a, c)
    other = _rollout(env, 12, indices[:1])
    assert not np.array_equal(other[0].object_poses, first[0].object_poses)


@pytest.mark.timeout(60)
def test_the_p_controller_hands_over_inside_the_threshold_and_never_acts_again(env):
    """A policy that always climbs (+z) is overridden while the error is outside the threshold on some
    axis; the hand-over happens with every axis inside; afterwards its climb is executed although it
    takes the error far outside again."""
    from services.episodes.rollout import run_episode

    threshold = np.asarray(env.settings.controller.phase_threshold)
    errors, states, infos = [], [], []
    env.reset(5)
    errors.append(env.centroid_error)
    states.append(env.observe().controller_state)
    for _ in range(30):
        obs, _, terminated, truncated, info = env.step(env.discrete_action(NAMES.index("+z")))
        errors.append(env.centroid_error)
        states.append(obs.controller_state)
        infos.append(info)
        assert not (terminated or truncated)
    handover = states.index(0)
    assert handover >= 2, "the controller should act for a few steps from the start"
    gain = np.asarray(env.settings.controller.gain)
    for t in range(handover):  # acting: some axis outside, the controller's P action executed
        outside = np.abs(errors[t]) > threshold
        assert outside.any() and infos[t]["controller_acted"]
        p_action = np.clip(-gain * errors[t] * outside, -1, 1)
        assert np.allclose(infos[t]["executed_action"], [1.0, *p_action, 0.0], atol=1e-6)
    assert (np.abs(errors[handover]) <= threshold).all()
    assert all(s == 0 for s in states[handover:])
    for info in infos[handover:]:  # latched: the policy's +z, every time
        assert not info["controller_acted"] and index_of(info["executed_action"], True) == NAMES.index("+z")
    assert (np.abs(errors[-1]) > threshold).any(), "the climb should leave the threshold again"
    # an episode records what was executed: the controller's actions first, then the policy's
    b = run_episode(env, 5, lambda _o: env.discrete_action(NAMES.index("+z")), _builder(env))
    executed = np.array([info["executed_action"] for info in infos])
    assert np.array_equal(np.stack(b.actions)[: len(executed)], executed)
    assert executed[0][3] < 0  # the controller descended while the policy asked to climb


def _builder(env, seed: int = 5):
    from services.episodes.builder import EpisodeBuilder

    return EpisodeBuilder(task="surgical_grasp_any", seed=seed, actor_id="t", policy_version=-1, policy_kind="random",
                          is_demo=False, segments=env.segment_names)  # fmt: skip


def _rod_seed(settings: SurgicalSettings) -> int:
    """A seed whose object is a rod of scale <= 1 (3 mm thick or less)."""
    for seed in range(200):
        p = scene_module.draw(settings, np.random.default_rng(seed))
        if p.spec.kind == "rod" and p.spec.scale <= 1.0:
            return seed
    raise AssertionError("no such seed")


def _close_at(env, seed: int, offset_real: float):
    """Reset, put the open jaws across the object's grasp axis with the tool ``offset_real`` (m) off
    its grasp point along the closing axis, tips 0.5 mm above the tray, and close."""
    env.reset(seed)
    pose = env.scene.object_pose()
    yaw = grasp_yaw(env.scene.object_yaw())
    yaw = math.remainder(yaw, math.pi)  # within the yaw limit
    u = np.array([math.cos(yaw), math.sin(yaw)])
    tip = np.array([*(pose[:2] - real(offset_real) * u), real(0.0005)])
    env.instrument.reset(env.instrument.pivot_from_tip(tip), yaw, jaw_open=True)
    for _ in range(10):
        env.step_physics()
    assert not any(env.instrument.jaw_contacts(env.scene.object))
    return env.step(env.discrete_action(TOGGLE))


@pytest.mark.timeout(60)
def test_success_needs_both_jaws_on_the_object(free_env):
    env = free_env
    seed = _rod_seed(env.settings)
    # centred: both jaws touch, the object is grasped; lifting it succeeds
    obs, reward, terminated, truncated, info = _close_at(env, seed, 0.0)
    assert all(env.instrument.jaw_contacts(env.scene.object)) and info["grasped"] and not terminated
    assert obs.fsm_state == 0 and obs.contacts[0]
    rest = env.scene.object_pose()[2]
    for _ in range(3):
        obs, reward, terminated, truncated, info = env.step(env.discrete_action(NAMES.index("+z")))
        if terminated:
            break
    assert terminated and not truncated and info["success"] and reward == 1.0
    assert env.scene.object_pose()[2] - rest >= env.settings.lift_height
    # 4.25 mm off-centre: the far jaw sweeps onto the object, the near one cannot reach it: a failure
    obs, reward, terminated, truncated, info = _close_at(env, seed, -0.00425)
    assert sum(env.instrument.jaw_contacts(env.scene.object)) == 1
    assert terminated and not truncated and not info["success"] and reward == pytest.approx(-0.1)
    assert info["fsm"] == "done_fail" and not info["grasped"]
    # beside the object: no contact at all, a failure too
    obs, reward, terminated, truncated, info = _close_at(env, seed, 0.02)
    assert not any(env.instrument.jaw_contacts(env.scene.object))
    assert terminated and info["fsm"] == "done_fail" and reward == pytest.approx(-0.1)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_action_is_refused_without_touching_the_env(env, bad):
    def state():
        st = env.instrument.state
        return (env.t, st.pivot.copy(), st.yaw, st.jaw_open, env.controller.active, env.substeps)

    reference, again = refused_actions_change_nothing(env, env.discrete_action(NAMES.index("+x")), bad, state)
    _same(again, reference)


@pytest.mark.timeout(60)
def test_discrete_steps_move_by_the_discrete_scales_and_the_time_limit_truncates(free_env):
    env = free_env
    env.reset(2)
    acts = env.settings.actions
    tip, yaw = env.tip(), env.instrument.state.yaw
    _, reward, *_ = env.step(env.discrete_action(NAMES.index("-x")))
    assert np.allclose(env.tip() - tip, [-0.3 * real(0.01), 0, 0]) and reward == pytest.approx(-0.001)
    env.step(env.discrete_action(NAMES.index("+yaw")))
    assert env.instrument.state.yaw == pytest.approx(yaw + acts.unit_rotation)
    assert abs(env.instrument.measured_pivot()[1] - env.instrument.state.yaw) < 3e-3
    for t in range(2, env.settings.max_steps):  # alternate turns: nothing ends the episode early
        _, reward, terminated, truncated, _ = env.step(
            env.discrete_action(NAMES.index("-yaw" if t % 2 else "+yaw"))
        )
        assert not terminated and truncated == (t == env.settings.max_steps - 1)


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_the_oracle_grasps_on_a_seeded_sample(env):
    successes = 0
    for seed in range(100, 112):  # mea bench tasks measures 100 seeds
        env.reset(seed)
        oracle = env.task.expert(env, "direct", np.random.default_rng(seed))
        for _ in range(env.settings.max_steps):
            _, _, terminated, truncated, info = env.step(oracle.act())
            if terminated or truncated:
                break
        successes += bool(info["success"])
    assert successes >= 11


@pytest.mark.timeout(60)
def test_a_failed_grasp_terminates_and_is_no_success(env):
    """Closing as soon as the policy has control (the jaws 2 cm real above the object) fails the
    grasp: terminated (not truncated) with -0.1, and the episode does not count as a success."""
    from services.episodes.rollout import run_episode

    b = run_episode(env, 8, lambda _o: env.discrete_action(TOGGLE), _builder(env, 8))
    assert b.terminated[-1] and not any(b.truncated) and b.rewards[-1] == pytest.approx(-0.1)
    assert not b.success and len(b.actions) < env.settings.max_steps
    assert b.obs[-1].fsm_state == 4  # done_fail


@pytest.mark.timeout(60)
def test_domain_randomisation_is_drawn_from_the_seed(env):
    from services.tasks.surgical.settings import RandomisationSettings

    dr = SurgicalGraspEnv(SurgicalSettings(camera=SMALL, randomisation=RandomisationSettings(enabled=True)))
    try:
        indices = [NAMES.index("+x")] * 8
        first = _rollout(dr, 4, indices)
        pose = dr.camera_pose
        again = _rollout(dr, 4, indices)
        for a, b in zip(first, again, strict=True):
            _same(a, b)
        assert dr.camera_pose == pose and pose.distance != 0.0
        assert _rollout(dr, 5, [])[0].point_counts.tolist() != first[0].point_counts.tolist()
        plain = _rollout(env, 4, indices)
        assert not np.array_equal(plain[0].points, first[0].points)  # camera and image noise
        np.testing.assert_array_equal(plain[0].object_poses, first[0].object_poses)  # same scene
        assert not np.array_equal(plain[-1].gripper_pose, first[-1].gripper_pose)  # action noise
    finally:
        dr.close()


class _Recording:
    """The env as ``run_episode`` drives it, keeping every step's info."""

    def __init__(self, env) -> None:
        self.env, self.infos = env, []

    def __getattr__(self, name):
        return getattr(self.env, name)

    def step(self, action):
        out = self.env.step(action)
        self.infos.append(out[4])
        return out


@pytest.mark.timeout(60)
@pytest.mark.parametrize("randomised", [False, True])
def test_every_recorded_step_moves_the_pivot_by_one_scale(env, randomised):
    """The transition prior MEA rests on, on recorded episodes (oracle and random policy, controller
    and policy steps alike): pivot_{t+1} - pivot_t = delta_xyz * a_t[dx, dy, dz], where delta_xyz
    is MEA's, unless the env reported the step as clipped or blocked."""
    from services.augmenter.core.mea_discrete import MeaDiscreteSettings
    from services.episodes.rollout import run_episode
    from services.tasks.surgical.settings import RandomisationSettings

    acts = env.settings.actions
    delta = MeaDiscreteSettings().delta_xyz
    assert acts.step_translation == pytest.approx(delta, abs=1e-12)
    settings = SurgicalSettings(camera=SMALL, randomisation=RandomisationSettings(enabled=randomised))
    e = SurgicalGraspEnv(settings) if randomised else env
    # the drive settles within 0.2 mm sim (measured); randomisation adds its action noise per axis
    tol = 5e-4 + (
        math.sqrt(3) * settings.randomisation.action_noise * acts.unit_translation if randomised else 0
    )
    checked = {True: 0, False: 0}
    try:
        for seed in (21, 23):  # the oracle, a random policy
            rec = _Recording(e)
            oracle = {}

            def act(_obs, rec=rec, oracle=oracle, seed=seed):
                if seed == 23:  # a random policy
                    return e.sample_action(np.random.default_rng([seed, e.t]))
                oracle.setdefault("o", Oracle(e))
                return oracle["o"].act()

            ep = run_episode(rec, seed, act, _builder(e, seed)).finish(f"prior-{seed}")
            moved = np.diff(ep.gripper_pose[:, :3].astype(np.float64), axis=0)
            err = np.linalg.norm(moved - delta * ep.actions[:, 1:4].astype(np.float64), axis=1)
            for t, info in enumerate(rec.infos):
                if info["clipped"] or info["blocked"]:
                    continue
                assert err[t] <= tol, (seed, t, info["controller_acted"], err[t])
                checked[bool(info["controller_acted"])] += 1
    finally:
        if randomised:
            e.close()
    assert checked[True] >= 10 and checked[False] >= 10, checked


@pytest.mark.timeout(60)
def test_the_controller_and_the_image_share_the_task_dsa_grid(env):
    """One voxelisation: the env's spec is the observation module's, a 200^3 world-aligned grid over
    a 1-sim-unit cube centred on the workspace centre; each downsampled point is one voxel of it, and
    the P-controller's error is the difference of its ``voxel_centroid``s plus the offset."""
    from services.observation import dsa
    from services.tasks.surgical.scene import WORKSPACE

    spec = env.settings.dsa
    assert spec == dsa.SURGICAL_GRASP_ANY
    assert (spec.grid, spec.scale, spec.origin) == (200, 1.0, (0.0, 0.0, real(0.035)))
    assert np.allclose(WORKSPACE.mean(axis=1), spec.origin)
    env.reset(3)
    world = env._perceive()
    for name, pts in world.items():
        assert len(pts) > 0 and dsa.in_cube(pts, spec).all(), name
        assert len(dsa.voxelize(dsa.to_occupancy(pts, spec), spec)) == len(pts), name
    offset = np.asarray(env.settings.controller.error_offset)
    want = dsa.voxel_centroid(world["gripper"], spec) - dsa.voxel_centroid(world["object_0"], spec) + offset
    assert np.array_equal(env.centroid_error, want)
    shifted = dataclasses.replace(spec, origin=(0.0, 0.0, 0.0))
    assert not np.array_equal(dsa.voxelize(dsa.to_occupancy(world["gripper"], shifted), shifted),
                              dsa.voxelize(dsa.to_occupancy(world["gripper"], spec), spec))  # fmt: skip


@pytest.mark.timeout(60)
def test_the_policy_image_is_rendered_from_the_stored_points_and_recorded(env):
    """Every observation's image is ``dsa_image`` of exactly the points the episode stores (observed
    rows plus the stored pivot) with the state row of the step; an episode records it in
    ``images`` and the wire keeps it."""
    from proto.episode import Episode
    from services.episodes.rollout import run_episode

    b = run_episode(env, 6, lambda _o: Oracle(env).act(), _builder(env, 6))
    assert b.success
    ep = Episode.decode(b.finish("image-6").encode())
    assert ep.images.dtype == np.uint8 and ep.images.shape == (ep.num_steps + 1, 3, 64, 64)
    closed = np.r_[False, ep.actions[:, 0] < 0]  # the jaw command after each step (row t: after step t-1)
    states = []
    for t, obs in enumerate(b.obs):
        gripper, obj = world_clouds(ep.points[t], ep.point_counts[t], ep.gripper_pose[t, :3])
        want = dsa_image(gripper, obj, env.settings.dsa, gripper_state=int(closed[t]), fsm_state=obs.fsm_state,
                         controller_state=obs.controller_state)  # fmt: skip
        assert np.array_equal(ep.images[t], want), t
        states.append(decode_state_rows(ep.images[t]))
        assert (ep.images[t, 0] > 0).any(), t  # the gripper is always in view
    assert [s[2] for s in states] == [o.controller_state for o in b.obs]
    assert states[0][2] == 1 and states[-1] == (1, 5, 0)  # at the end: closed, done_success, policy
    assert any(s[0] == 0 for s in states) and (ep.images[:, 1] > 0).any()  # open jaws; the object seen


def test_meas_workspace_is_the_envs_pivot_workspace(env):
    """MEA refuses copies whose pivot leaves ``MeaDiscreteSettings``' bounds: they must be the env's
    (the tips' workspace raised by the calibrated pivot height), or copies would be refused for
    places the env reaches, or claim places it clips."""
    from services.augmenter.core.mea_discrete import MeaDiscreteSettings

    low, high = env.pivot_bounds()
    s = MeaDiscreteSettings()
    assert np.allclose(s.pivot_low, low, atol=1e-4) and np.allclose(s.pivot_high, high, atol=1e-4)
    assert s.bound_tolerance <= 5 * env.settings.tolerance


def test_each_episode_records_what_it_drew(env):
    """Episode.conditions: the randomisation switch, the camera offsets and the object, from the seed."""
    from proto.episode import Episode
    from services.episodes.builder import EpisodeBuilder
    from services.episodes.rollout import run_episode
    from services.tasks.surgical.settings import RandomisationSettings

    env.reset(3)
    plain = env.episode_conditions()
    assert plain["randomised"].tolist() == [0] and not np.any(plain["camera_offsets"])
    dr = make_env(
        "surgical_grasp_any",
        SurgicalSettings(camera=SMALL, randomisation=RandomisationSettings(enabled=True)),
    )
    try:
        dr.reset(3)
        drawn = dr.episode_conditions()
        assert drawn["randomised"].tolist() == [1] and np.any(drawn["camera_offsets"])
        assert drawn["object_kind"] == plain["object_kind"] and drawn["object_scale"] == plain["object_scale"]
        dr.reset(4)
        assert not np.array_equal(dr.episode_conditions()["camera_offsets"], drawn["camera_offsets"])
        b = EpisodeBuilder(task="surgical_grasp_any", seed=3, actor_id="a-0", policy_version=-1, policy_kind="random",
                           is_demo=False, segments=dr.segment_names)  # fmt: skip
        rng = np.random.default_rng(0)
        run_episode(dr, 3, lambda obs: dr.sample_action(rng), b)
        ep = Episode.decode(b.finish("a-0-3-0").encode())
        assert ep.conditions is not None
        assert np.array_equal(ep.conditions["camera_offsets"], drawn["camera_offsets"])
    finally:
        dr.close()
