"""Jump-start episodes (JSRL): the draw, the replay of a demonstration's prefix before the policy
acts, and the demonstrations made again on any actor of any sitting as actor 0 recorded them."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from services.actor import jump_start
from services.actor.config import ActorConfig
from services.actor.rollout import RolloutActor
from services.common.config import ServiceConfig
from services.episodes.rollout import policy_input
from services.plan import actor_config
from services.run_config import RunConfig


def _demo(t: int, seed: int = 5) -> jump_start.Demo:
    return jump_start.Demo(seed, np.zeros((t, 5), np.float32))


def test_draw_follows_the_share_and_hands_over_inside_the_demo():
    rng = np.random.default_rng(0)
    demos = [_demo(2, 1), _demo(30, 2), _demo(1, 3)]  # a 1-step demo leaves the policy nothing after it
    assert all(jump_start.draw(rng, demos, 0.0) is None for _ in range(200))
    drawn = [jump_start.draw(rng, demos, 1.0) for _ in range(2000)]
    assert all(j is not None and j.demo.seed in (1, 2) for j in drawn)
    for seed, length in ((1, 2), (2, 30)):
        replayed = {j.replayed for j in drawn if j.demo.seed == seed}
        assert replayed == set(range(1, length))  # every handover 1 .. T-1, and no other
    half = [jump_start.draw(rng, demos, 0.5) for _ in range(4000)]
    assert 0.45 < np.mean([j is not None for j in half]) < 0.55
    assert jump_start.draw(rng, [_demo(1)], 1.0) is None and jump_start.draw(rng, [], 1.0) is None


def test_the_steps_left_at_the_handover_fall_in_one_bin_each():
    bins = [jump_start.left_bin(k) for k in range(1, 60)]
    assert bins[:13] == ["1-2"] * 2 + ["3-4"] * 2 + ["5-8"] * 4 + ["9-12"] * 4 + ["13+"]
    assert set(bins[12:]) == {"13+"}
    with pytest.raises(ValueError, match="1 or more"):
        jump_start.left_bin(0)


class _Recorder:
    """A policy that records what it read and was told: the runtime's side of a jump start."""

    def __init__(self) -> None:
        self.spec = SimpleNamespace(observation="voxel")
        self.version, self.inputs, self.told, self.resets = 7, [], [], 0

    def reset(self) -> None:
        self.resets += 1

    def act(self, image_codes: np.ndarray) -> np.ndarray:
        self.inputs.append(np.array(image_codes))
        return np.full(5, 0.9, np.float32)  # never executed during the replay

    def executed(self, action: np.ndarray) -> None:
        self.told.append(np.array(action))


@pytest.fixture(scope="module")
def block_pull_demo():
    """Actor 0's first demonstration on Block Pull, from the public start (as recorded)."""
    cfg = ActorConfig(task="block_pull", policy="learned", gripper_start="fixed", jump_start=1.0,
                      jump_start_demos=1, jump_start_seed_base=300)  # fmt: skip
    actor = RolloutActor(jump_start.first_sitting(cfg), "actor-0")
    b = actor.expert_episode(0)
    yield cfg, actor, b
    actor.env.close()


def test_a_jump_start_replays_the_prefix_and_the_policy_follows_it(block_pull_demo):
    cfg, actor, recorded = block_pull_demo
    assert recorded.success
    demo = jump_start.Demo(int(recorded.meta["seed"]), np.stack(recorded.actions))
    t = len(demo.actions)
    policy = _Recorder()
    episode = actor.begin_jump_start(policy, jump_start.JumpStart(demo, t - 1))
    assert not episode.done and episode.builder.num_steps == t - 1
    b = episode.builder
    assert b.meta["policy_kind"] == "jump_start" and b.meta["seed"] == demo.seed and not b.meta["is_demo"]
    assert b.meta["policy_version"] == 7 and policy.resets == 1 and b.jump_left == 1
    np.testing.assert_array_equal(np.stack(b.actions), demo.actions[: t - 1])  # stored = executed
    np.testing.assert_array_equal(np.stack(policy.told), demo.actions[: t - 1])
    assert len(policy.inputs) == t - 1  # it read every observation the demo saw, the same ones
    for k in (0, t - 2):
        np.testing.assert_array_equal(policy.inputs[k], policy_input(recorded.obs[k], "voxel"))
    episode.step(demo.actions[-1])  # the demo's last action finishes it as it did: same states
    assert episode.done and episode.builder.success
    first_id = actor.episode_id(episode.builder)  # as the actor names it when it publishes it
    again = actor.begin_jump_start(_Recorder(), jump_start.JumpStart(demo, 1))
    assert again.builder.meta["seed"] == demo.seed and actor.episode_id(again.builder) != first_id


def test_the_demonstrations_are_made_again_on_any_actor_of_a_later_sitting(block_pull_demo):
    _, first, recorded = block_pull_demo
    run = RunConfig(task="block_pull", demos=1, seed=3, jump_start=0.5, gripper_start="fixed")
    sitting0 = actor_config(run, 0, ServiceConfig())
    later = actor_config(dataclasses.replace(run, resumes=2), 1, ServiceConfig())
    assert later.seed_base != sitting0.seed_base and later.demos == 0 == later.random_steps
    assert later.jump_start == 0.5 and later.jump_start_demos == 1
    want = RolloutActor(sitting0, "actor-0", first.env).expert_episode(0)  # what actor 0 published
    made = jump_start.regenerate(dataclasses.replace(later, incarnation=1), first.env, "actor-1")
    assert len(made) == 1 and made[0].seed == want.meta["seed"]
    np.testing.assert_array_equal(made[0].actions, np.stack(want.actions))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"jump_start": 1.5}, "in \\[0, 1\\]"),
        ({"jump_start": 0.5, "demos": 0}, "--demos"),
        ({"jump_start": 0.5, "task": "surgical_grasp_any", "variant": "gasv2"}, "manipulation tasks"),
    ],
)
def test_a_run_refuses_a_jump_start_it_cannot_replay(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RunConfig(**kwargs)


def test_an_actor_refuses_jump_starts_without_demonstrations_or_a_policy():
    with pytest.raises(ValueError, match="jump_start"):
        ActorConfig(policy="learned", jump_start=0.5)
    with pytest.raises(ValueError, match="jump_start"):
        ActorConfig(policy="random", jump_start=0.5, jump_start_demos=2)
    with pytest.raises(ValueError, match="jump_start"):
        ActorConfig(policy="learned", jump_start=-0.1, jump_start_demos=2)


def test_a_jump_starts_outcome_is_charted_apart_from_the_policys(tmp_path):
    from services.actor.main import EpisodeScalars
    from services.episodes.builder import EpisodeBuilder

    class _Log:
        due, added = False, []

        def add(self, values, step):
            self.added.append((dict(values), step))

    charts = EpisodeScalars(ActorConfig(tensorboard_dir=tmp_path), "actor-0", None, 0)
    charts.log = _Log()
    for kind, left, reward in (("learned", None, 1.0), ("jump_start", 6, 1.0), ("jump_start", 20, 0.0)):
        b = EpisodeBuilder(task="block_pull", seed=1, actor_id="actor-0", policy_version=1,
                           policy_kind=kind, is_demo=False, segments=("gripper",))  # fmt: skip
        b.step(np.zeros(5), reward, reward > 0, False)
        b.jump_left = left
        charts.episode(b, 10, None)
    (plain, _), (near, _), (far, step) = charts.log.added
    assert plain == {"charts/episodic_return": 1.0, "charts/success": 1.0}
    assert near == {"charts/jump_start_episodic_return": 1.0, "charts/jump_start_success": 1.0,
                    "charts/jump_start_success_left_5-8": 1.0}  # fmt: skip
    assert far["charts/jump_start_success_left_13+"] == 0.0 and "charts/success" not in far and step == 10
