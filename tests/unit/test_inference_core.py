"""The inference server's core: weights offers, sessions pinned to a version, and every hold reason."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from proto.actions import ACTION_DIM, DELTA_XYZ, JAW
from proto.inference import ActRequest, ResetRequest
from proto.weights import WeightsBlob
from services.algorithms.networks import PRESETS, build_actor
from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors
from services.inference.core.envelope import Limits
from services.inference.core.sessions import InferenceCore, ServeSettings, SwapRefusedError
from tests.helpers.learner import SIZE, TINY_NET

TINY = TINY_NET
SPEC = PolicySpec(TINY)
T0 = 1_000.0  # monotonic clock of the tests
WALL = 1_800_000_000.0
POSE = np.array([0.0, 0.0, 0.1, 0.0, 1.0], np.float32)


def blob(version: int, seed: int = 0, run_id: str = "run-a", spec: PolicySpec = SPEC) -> WeightsBlob:
    torch.manual_seed(seed)
    return WeightsBlob.create(
        version, "equi_rsac", run_id, actor_tensors(build_actor(spec.net)), spec.to_json()
    )


def image(seed: int, size: int = SIZE) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (2, size, size), dtype=np.uint8)


def act_request(step: int, episode: int = 1, session: str = "arm-1", stamp: float = WALL, **kw) -> ActRequest:
    fields = {"state": POSE, "image": image(step)} | kw
    return ActRequest(session=session, episode=episode, step=step, stamp=stamp, **fields)


def reset(core: InferenceCore, session: str = "arm-1", task: str = "block_pull", now: float = T0):
    return core.reset(ResetRequest(session=session, task=task, created_at=WALL), now)


@pytest.fixture
def core() -> InferenceCore:
    c = InferenceCore(ServeSettings())
    c.offer(blob(1))
    return c


def test_no_weights_no_episode_and_unknown_sessions_hold():
    c = InferenceCore(ServeSettings())
    r = reset(c)
    assert not r.accepted and "no weights" in r.reason
    reply = c.act(act_request(0), T0, WALL)
    assert reply.held and reply.reasons == ["no_session"] and reply.policy_version == -1
    assert reply.action[JAW] == 1.0 and not reply.action[1:].any()  # jaw state 1.0: kept open


def test_versions_only_go_forward_and_a_refused_blob_keeps_the_old_policy(core):
    for bad, reason in [
        (blob(1, seed=5), "not_newer"),
        (blob(0), "not_newer"),
        (blob(7, run_id="run-b"), "other_run"),
    ]:
        with pytest.raises(SwapRefusedError) as e:
            core.offer(bad)
        assert e.value.reason == reason
        assert core.current.version == 1
    corrupt = dataclasses.replace(blob(2), digest="0" * 64)
    with pytest.raises(SwapRefusedError) as e:
        core.offer(corrupt)
    assert e.value.reason == "digest" and core.current.version == 1
    other_net = dataclasses.replace(TINY, lstm_hidden=16)
    wrong = blob(3)
    misfit = WeightsBlob.create(3, "equi_rsac", "run-a", wrong.tensors, PolicySpec(other_net).to_json())
    with pytest.raises(SwapRefusedError) as e:
        core.offer(misfit)
    assert e.value.reason == "load" and core.current.version == 1
    assert core.offer(blob(4, seed=1)).version == 4  # a good one still goes through after refusals


def test_a_pinned_run_id_refuses_other_runs_even_first():
    c = InferenceCore(ServeSettings(run_id="run-z"))
    with pytest.raises(SwapRefusedError, match="run-z"):
        c.offer(blob(1))
    assert c.current is None


def test_an_episode_keeps_its_version_and_state_across_a_swap(core):
    """No mixed state: the episode started under v1 goes on with v1's actions exactly as a v1 runtime
    stepped alone would give them; the next episode is v2."""
    ref = PolicyRuntime(deterministic=True)
    ref.load(blob(1))
    r = reset(core)
    assert r.accepted and r.policy_version == 1 and r.observation == "voxel"
    got, want = [], []
    for step in range(6):
        if step == 3:
            core.offer(blob(2, seed=9))  # swap mid-episode
        reply = core.act(act_request(step, executed=None if step == 0 else got[-1]), T0 + step, WALL)
        assert reply.policy_version == 1 and not reply.held
        got.append(reply.action)
        if step:
            ref.executed(want[-1])
        want.append(ref.act(image(step)))
    np.testing.assert_array_equal(np.stack(got), np.stack(want))
    r2 = reset(core, now=T0 + 10)
    assert r2.episode == 2 and r2.policy_version == 2
    assert core.act(act_request(0, episode=2), T0 + 11, WALL).policy_version == 2


def test_sessions_are_independent(core):
    reset(core, "arm-1")
    reset(core, "arm-2")
    a = [core.act(act_request(s, session="arm-1"), T0, WALL).action for s in range(3)]
    b0 = core.act(act_request(0, session="arm-2"), T0, WALL).action
    np.testing.assert_array_equal(a[0], b0)  # arm-2's first step is not arm-1's fourth


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"stamp": WALL - 0.6}, "watchdog"),
        ({"state": np.array([np.nan, 0, 0.1, 0, 1], np.float32)}, "non_finite_observation"),
        ({"state": np.array([0, 0, 0.1, np.inf, 1], np.float32)}, "non_finite_observation"),
        ({"state": np.array([5.0, 0, 0.1, 0, 1], np.float32)}, "out_of_workspace"),
        ({"image": np.zeros((3, 64, 64), np.uint8)}, "bad_observation"),
        ({"image": np.zeros((2, 84, 84), np.uint8)}, "bad_observation"),
        ({"episode": 7}, "stale_episode"),
        ({"executed": np.full(ACTION_DIM, 3.0, np.float32), "step": 1}, "bad_observation"),
    ],
)
def test_bad_observations_hold_with_their_reason_and_do_not_advance_the_policy(core, change, reason):
    reset(core)
    change = dict(change)
    reply = core.act(act_request(change.pop("step", 0), **change), T0, WALL)
    assert reply.held and reply.reasons == [reason]
    assert not reply.action[1:].any() and reply.action[JAW] == 1.0
    # the policy state did not move: the next good request gives what a fresh episode gives
    fresh = InferenceCore(ServeSettings())
    fresh.offer(blob(1))
    reset(fresh)
    np.testing.assert_array_equal(core.act(act_request(0), T0, WALL).action,
                                  fresh.act(act_request(0), T0, WALL).action)  # fmt: skip


def test_points_are_projected_and_non_finite_or_far_points_refused():
    core = InferenceCore(ServeSettings())
    core.offer(blob(1, spec=PolicySpec(PRESETS["cpu-small"])))  # an 84-pixel policy: what points project to
    reset(core)
    pts = np.random.default_rng(0).uniform(-0.1, 0.1, (3, 16, 3)).astype(np.float32)
    counts = np.full(3, 16, np.int32)
    ok = core.act(act_request(0, image=None, points=pts, point_counts=counts), T0, WALL)
    assert not ok.held
    for bad, reason in [
        (np.where(pts > 0.09, np.nan, pts), "non_finite_observation"),
        (pts * 100, "out_of_workspace"),
    ]:
        reply = core.act(
            act_request(1, image=None, points=bad.astype(np.float32), point_counts=counts), T0, WALL
        )
        assert reply.held and reply.reasons == [reason]


def test_estop_holds_every_session_until_released(core):
    reset(core)
    core.estop = True
    assert core.act(act_request(0), T0, WALL).reasons == ["estop"]
    core.estop = False
    assert not core.act(act_request(0), T0, WALL).held


class _Adversary:
    """A policy that asks for the worst: huge, NaN or alternating extreme actions."""

    def __init__(self, actions):
        self.actions = list(actions)

    def act(self, _image):
        return np.asarray(self.actions.pop(0), np.float32)

    def executed(self, _a):
        pass


def test_the_envelope_bounds_an_adversarial_policy_every_step(core):
    lim = Limits(max_translation=0.02, max_rotation=0.1, workspace_low=(-0.1, -0.1, 0.05),
                 workspace_high=(0.1, 0.1, 0.2))  # fmt: skip
    c = InferenceCore(ServeSettings(), lambda _s: lim)
    c.offer(blob(1))
    reset(c)
    rng = np.random.default_rng(3)
    evil = [rng.choice([-50.0, 50.0, -1.0, 1.0], ACTION_DIM) for _ in range(40)] + [[np.nan] * 5]
    c.sessions["arm-1"].runtime = _Adversary(evil)
    pivot = np.array([0.09, -0.09, 0.19])
    for step in range(41):
        state = np.append(pivot, [0.0, 1.0]).astype(np.float32)
        reply = c.act(act_request(step, state=state), T0 + step, WALL)
        a = reply.action.astype(np.float64)
        if step == 40:
            assert reply.held and reply.reasons == ["non_finite_action"]
            break
        move = a[1:4] * lim.metres_per_unit
        assert np.linalg.norm(move) <= lim.max_translation + 1e-7
        assert abs(a[4] * lim.radians_per_unit) <= lim.max_rotation + 1e-7
        pivot = pivot + move
        assert (pivot >= np.array(lim.workspace_low) - 1e-7).all() and (
            pivot <= np.array(lim.workspace_high) + 1e-7
        ).all()
        assert np.abs(a).max() <= 1.0


def test_rate_limit_and_session_limits():
    c = InferenceCore(ServeSettings(max_sessions=1, session_timeout=5.0), lambda _s: Limits(min_interval=0.1))
    c.offer(blob(1))
    assert reset(c, "arm-1").accepted
    assert not reset(c, "arm-2").accepted  # one session only
    assert not c.act(act_request(0), T0, WALL).held
    assert c.act(act_request(1), T0 + 0.05, WALL).reasons == ["rate"]
    assert not c.act(act_request(2), T0 + 0.2, WALL).held
    assert reset(c, "arm-2", now=T0 + 6.0).accepted  # arm-1 idle past session_timeout: dropped
    assert "arm-1" not in c.sessions


def test_a_dsa_policy_is_refused_for_a_general_task_and_the_other_way_round(core):
    r = reset(core, task="surgical_grasp_any")
    assert not r.accepted and "cannot observe" in r.reason


def test_the_translation_unit_is_the_tasks():
    assert Limits().metres_per_unit == DELTA_XYZ


def test_a_session_belongs_to_the_robot_that_opened_it_and_replies_echo_the_nonce(core):
    assert core.reset(
        ResetRequest(session="arm-1", task="block_pull", created_at=WALL), T0, "robot/r1"
    ).accepted
    other = core.reset(ResetRequest(session="arm-1", task="block_pull", created_at=WALL), T0, "robot/r2")
    assert not other.accepted and "robot/r1" in other.reason
    stolen = core.act(act_request(0, nonce=5), T0, WALL, "robot/r2")
    assert stolen.held and stolen.reasons == ["no_session"] and stolen.nonce == 5
    mine = core.act(act_request(0, nonce=2**62 + 3), T0, WALL, "robot/r1")
    assert not mine.held and mine.nonce == 2**62 + 3
