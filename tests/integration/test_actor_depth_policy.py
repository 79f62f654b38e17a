"""A learned actor fed by a `depth` policy (the `equirsac` variant): it acts on the rendered depth
image when started with ``depth_image=True``, and refuses such weights (counted, logged, no crash)
when it does not render that image."""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pytest
import torch

import services.actor.main as actor_main
from proto.episode import Episode
from proto.topics import EPISODES_RAW
from proto.weights import WeightsBlob
from services.actor.config import ActorConfig
from services.actor.main import run
from services.algorithms.networks import PRESETS, build_actor
from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors
from services.augmenter.core.pipeline import AugmentSettings, augment_episode
from services.common.bus import Hub, InProcBus, Subscription
from services.common.config import ServiceConfig
from services.common.weights import WeightsServer
from services.episodes.rollout import policy_image, policy_input
from services.tasks.env import Observation

pytestmark = pytest.mark.integration


def _blob(version: int, observation: str, seed: int = 0) -> WeightsBlob:
    torch.manual_seed(seed)
    spec = PolicySpec(PRESETS["cpu-small"], observation=observation)
    return WeightsBlob.create(
        version, "equi_rsac", "run-1", actor_tensors(build_actor(spec.net)), spec.to_json()
    )


def _observation(ep: Episode, t: int) -> Observation:
    depth = None if ep.images is None else ep.images[t, 0]
    return Observation(ep.points[t], ep.point_counts[t], float(ep.jaw[t]), ep.gripper_pose[t],
                       ep.object_poses[t], ep.contacts[t], depth_image=depth)  # fmt: skip


def _cfg(index: int, depth_image: bool) -> ActorConfig:
    return ActorConfig(task="block_pull", policy="learned", episodes=1, index=index, points_per_segment=64,
                       depth_image=depth_image, follow_gate=False,
                       service=ServiceConfig(instance_id=f"actor-{index}", metrics_port=0, log_format="text"))  # fmt: skip


def _learner_side(blob: WeightsBlob) -> tuple[Hub, Subscription, WeightsServer]:
    """A hub whose learner side is faked: a weights server holding ``blob``, a subscriber to raw episodes."""
    hub = Hub()
    observer = InProcBus(hub)
    episodes = observer.subscribe(EPISODES_RAW, capacity=8)
    server = WeightsServer(observer, "learner-0")
    server.publish(blob)
    return hub, episodes, server


@pytest.mark.timeout(180)
def test_depth_policy_acts_on_the_rendered_depth_image():
    blob = _blob(7, "depth")
    hub, episodes, server = _learner_side(blob)
    cfg = _cfg(2, depth_image=True)
    try:
        assert run(cfg, bus_factory=lambda _c: InProcBus(hub)) == 0
    finally:
        server.close()
    (d,) = episodes.drain()
    ep = d.message
    assert ep.policy_kind == "learned" and ep.policy_version == 7
    assert ep.images is not None and ep.images.shape == (ep.num_steps + 1, 1, 84, 84)
    assert ep.num_steps >= 3

    # the actions are the depth policy's: a runtime with the same weights and seed, fed
    # policy_input(obs, "depth") of the recorded observations, reproduces every one of them
    seed = cfg.seed_base + cfg.index * 1_000_000
    runtime = PolicyRuntime(deterministic=False, seed=seed)
    runtime.load(blob)
    inputs = [policy_input(_observation(ep, t), "depth") for t in range(ep.num_steps)]
    for t, x in enumerate(inputs):
        assert x.dtype == np.uint8 and x.shape == (2, 84, 84)
        np.testing.assert_allclose(runtime.act(x), ep.actions[t], atol=1e-5, err_msg=f"step {t}")
    # ... which the voxel input does not (the check can fail)
    voxel = PolicyRuntime(deterministic=False, seed=seed)
    voxel.load(blob)
    diffs = [np.abs(voxel.act(policy_image(_observation(ep, t))) - ep.actions[t]).max() for t in range(3)]
    assert max(diffs) > 1e-3, diffs

    # what the actor fed its policy is bit for bit what the augmenter stores for the learner
    out, _ = augment_episode(ep, AugmentSettings(observation="depth", mea_on="none"))
    np.testing.assert_array_equal(out[0].images[:-1], np.stack(inputs))
    assert len(out) == 5 and all(e.images.dtype == np.uint8 for e in out)


def spy_metrics(monkeypatch) -> list:
    """The actor's metric registries, collected as the actor under test creates them."""
    registries: list = []
    make_metrics = actor_main._metrics

    def spy(ctx):
        registries.append(ctx.metrics.registry)
        return make_metrics(ctx)

    monkeypatch.setattr(actor_main, "_metrics", spy)
    return registries


@pytest.mark.timeout(180)
def test_actor_without_depth_image_refuses_a_depth_policy_and_runs_on(monkeypatch):
    hub, episodes, server = _learner_side(_blob(7, "depth"))
    registries = spy_metrics(monkeypatch)

    def bad_weights() -> float:
        # None until the actor has registered the counter (a loaded machine can ask before)
        return (registries[0].get_sample_value("mea_actor_bad_weights_total") if registries else None) or 0.0

    cfg = _cfg(3, depth_image=False)
    result: dict = {}
    errors: list[BaseException] = []

    def target() -> None:
        try:
            result["rc"] = run(cfg, bus_factory=lambda _c: InProcBus(hub))
        except BaseException as exc:  # noqa: BLE001 - reported by the test thread
            errors.append(exc)

    actor = threading.Thread(target=target, daemon=True)
    actor.start()
    deadline = time.monotonic() + 60
    while bad_weights() < 1 and time.monotonic() < deadline and actor.is_alive():
        time.sleep(0.05)
    assert bad_weights() == 1, f"depth weights were not refused (errors: {errors})"
    assert episodes.recv(timeout=0.5) is None  # nothing acted with the refused weights
    assert actor.is_alive() and not errors, errors  # still running, waiting for weights it can use

    voxel = _blob(8, "voxel", seed=1)
    server.publish(voxel)
    actor.join(timeout=120)
    server.close()
    assert not actor.is_alive() and not errors and result.get("rc") == 0, errors
    (d,) = episodes.drain()
    ep = d.message
    assert ep.policy_version == 8 and ep.policy_kind == "learned" and ep.images is None
    assert bad_weights() == 1


def test_refused_depth_weights_keep_the_previous_ones():
    """``_load_weights`` on an actor without the depth image: the voxel weights it holds stay."""

    class Counter:
        def __init__(self) -> None:
            self.n = 0

        def inc(self) -> None:
            self.n += 1

    class Client:
        def __init__(self, blobs: list[WeightsBlob]) -> None:
            self.blobs = blobs

        def poll(self) -> WeightsBlob | None:
            return self.blobs.pop(0) if self.blobs else None

    mx = {"bad_weights": Counter()}
    policy = PolicyRuntime(deterministic=True)
    client = Client([_blob(7, "voxel"), _blob(8, "depth", seed=1), _blob(9, "depth", seed=2)])
    actor_main._load_weights(client, policy, mx, {}, depth_image=False)
    assert policy.version == 7 and policy.spec.observation == "voxel" and mx["bad_weights"].n == 0
    actor_main._load_weights(client, policy, mx, {}, depth_image=False)
    assert policy.version == 7 and policy.spec.observation == "voxel" and mx["bad_weights"].n == 1
    # with the depth image rendered, depth weights load
    actor_main._load_weights(client, policy, mx, {}, depth_image=True)
    assert policy.version == 9 and policy.spec.observation == "depth" and mx["bad_weights"].n == 1
    # a bad spec is refused too
    broken = dataclasses.replace(_blob(10, "voxel"), config_json='{"net": {}}')
    actor_main._load_weights(Client([broken]), policy, mx, {}, depth_image=True)
    assert policy.version == 9 and mx["bad_weights"].n == 2


def test_policy_input_needs_the_depth_image():
    ep_obs = Observation(np.zeros((3, 4, 3), np.float32), np.full(3, 4, np.int32), 0.5, np.zeros(4, np.float32),
                         np.zeros((2, 7), np.float32), np.zeros(2, bool))  # fmt: skip
    with pytest.raises(ValueError, match="depth-image"):
        policy_input(ep_obs, "depth")
    with pytest.raises(ValueError, match="observation"):
        policy_input(ep_obs, "rgb")
    np.testing.assert_array_equal(policy_input(ep_obs, "voxel"), policy_image(ep_obs))
    depth = np.full((84, 84), 0.3, np.float32)
    x = policy_input(dataclasses.replace(ep_obs, depth_image=depth), "depth")
    assert x.shape == (2, 84, 84) and x.dtype == np.uint8 and np.all(x[1] == 128)


@pytest.mark.timeout(180)
def test_an_episode_with_a_non_finite_action_is_dropped_counted_and_the_actor_runs_on(monkeypatch):
    from services.algorithms import policy as policy_module

    hub, episodes, server = _learner_side(_blob(9, "voxel"))
    registries = spy_metrics(monkeypatch)
    real_act, calls = policy_module.PolicyRuntime.act, {"n": 0}

    def act(self, x):  # the first episode's third action is NaN, every other one the policy's
        calls["n"] += 1
        a = real_act(self, x)
        return np.full_like(a, np.nan) if calls["n"] == 3 else a

    monkeypatch.setattr(policy_module.PolicyRuntime, "act", act)
    cfg = dataclasses.replace(_cfg(4, depth_image=False), episodes=1)
    try:
        assert run(cfg, bus_factory=lambda _c: InProcBus(hub)) == 0
    finally:
        server.close()
    got = [d.message for d in episodes.drain()]
    assert len(got) == 1 and np.isfinite(got[0].actions).all()  # only the episode that finished
    assert registries[0].get_sample_value("mea_actor_bad_actions_total") == 1
