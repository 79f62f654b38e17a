"""`mea bench reach`: the known-answer task is equivariant, its expert solves it, and the bench's loop
stores what it acts on and learns through the learner's own pieces."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mea_tools.bench import reach as rb
from mea_tools.bench import reach_task as rt
from services.algorithms.groups import get_group, matrix, transform_actions, transform_images
from services.algorithms.replay import SequenceReplay
from services.algorithms.tensors import images_from_codes


def _expert(s: rt.ReachState, _t: int):
    return rt.expert_action(s)


def _turned(s: rt.ReachState, g) -> rt.ReachState:
    R = np.array(matrix(g), float)
    return rt.ReachState(R @ s.point, R @ s.goal)


@pytest.mark.parametrize("observation", ["image", "centred"])
@pytest.mark.parametrize("g", get_group("d4").elements)
def test_turning_the_world_turns_the_image_and_the_step(g, observation):
    rng = np.random.default_rng(3)
    for _ in range(50):
        s = rt.draw_start(rng)
        img = torch.from_numpy(rt.observe(s, observation, 11))
        turned = torch.from_numpy(rt.observe(_turned(s, g), observation, 11))
        assert torch.equal(turned, transform_images(img, g))
        a = rng.uniform(-1.5, 1.5, 5).astype(np.float32)  # beyond the box too: clipping commutes
        ga = transform_actions(torch.from_numpy(a), g).numpy()
        nxt, r, done = rt.step(s, a)
        g_nxt, g_r, g_done = rt.step(_turned(s, g), ga)
        np.testing.assert_allclose(g_nxt.point, _turned(nxt, g).point, atol=1e-6)
        assert (g_r, g_done) == (r, done)


def test_the_expert_reaches_every_goal_and_random_actions_rarely_do():
    rng = np.random.default_rng(0)
    wins = [rb.rollout(rt.draw_start(rng), _expert, rb.ReachBenchConfig())[2] for _ in range(200)]
    assert all(wins)
    cfg = rb.ReachBenchConfig()
    random = [
        rb.rollout(rt.draw_start(rng), lambda _s, _t: rng.uniform(-1, 1, 5), cfg)[2] for _ in range(200)
    ]
    assert sum(random) < 100


def test_the_centred_image_marks_the_goal_at_its_offset_from_the_point():
    s = rt.ReachState(np.array([0.6, -0.2]), np.array([-0.4, 0.8]))  # offset (-1.0, 1.0): 5 pixels each way
    img = rt.observe(s, "centred", 11)
    assert img.shape == (2, 21, 21)
    assert [tuple(np.argwhere(img[c])[0]) for c in (0, 1)] == [(10, 10), (5, 15)]
    assert img.sum() == 2 * 255


@pytest.mark.parametrize("observation", ["state", "image", "centred"])
def test_a_goal_shown_for_k_steps_is_gone_from_the_observation_after_them(observation):
    s = rt.ReachState(np.array([0.6, -0.2]), np.array([-0.4, 0.8]))
    seen = [rt.observe(s, observation, 11, t, goal_steps=2) for t in range(4)]
    assert np.array_equal(seen[0], seen[1]) and np.array_equal(seen[2], seen[3])
    if observation == "state":
        assert seen[0].shape == (5, 1, 1) and seen[0][4, 0, 0] == 255 and seen[2][4, 0, 0] == 0
        np.testing.assert_array_equal(seen[0][:2], seen[2][:2])  # the point stays
    else:
        np.testing.assert_array_equal(seen[0][0], seen[2][0])
        assert seen[0][1].sum() == 255 and seen[2][1].sum() == 0
    assert np.array_equal(
        rt.observe(s, observation, 11, 9), rt.observe(s, observation, 11, 0)
    )  # K = 0: always


def test_episodes_store_what_the_policy_saw_at_each_step_of_a_hidden_goal():
    cfg = rb.ReachBenchConfig(goal_steps=1)
    states, actions, reached = rb.rollout(rt.draw_start(np.random.default_rng(2)), _expert, cfg)
    ep = rb.episode(states, actions, reached, cfg, "expert_direct", 0)
    assert ep.images.shape == (len(states), 5, 1, 1) and rb.net_config(cfg).in_channels == 5
    assert ep.images[0, 4, 0, 0] == 255 and (ep.images[1:, 4] == 0).all()


def test_the_state_observation_codes_the_coordinates():
    s = rt.ReachState(np.array([-1.0, 1.0]), np.array([0.0, 0.5]))
    codes = rt.observe(s, "state", 11)
    assert codes.shape == (4, 1, 1) and codes.dtype == np.uint8
    np.testing.assert_allclose(codes.ravel() / 255.0 * 2 - 1, [-1.0, 1.0, 0.0, 0.5], atol=1 / 255)


@pytest.mark.parametrize("observation", ["state", "image", "centred"])
def test_episodes_fit_the_learners_replay_as_they_were_acted(observation):
    cfg = rb.ReachBenchConfig(observation=observation)
    net = rb.net_config(cfg)
    states, actions, reached = rb.rollout(rt.draw_start(np.random.default_rng(1)), _expert, cfg)
    ep = rb.episode(states, actions, reached, cfg, "expert_direct", 0)
    replay = SequenceReplay(1000, image_size=net.image_size, seq_len=rt.MAX_STEPS, constant_channels=(),
                            channels=net.in_channels, seed=0)  # fmt: skip
    assert replay.insert_episode(ep) == len(actions)
    batch = replay.gather(replay.slots())
    np.testing.assert_array_equal(batch.actions[0, : len(actions)], np.stack(actions))
    np.testing.assert_array_equal(batch.images_uint8()[0, : len(states)], ep.images)
    assert reached and batch.rewards[0, len(actions) - 1] == 1.0 and batch.terminated[0, len(actions) - 1]


def test_a_short_run_updates_once_per_env_step_and_evaluates_on_schedule():
    cfg = rb.ReachBenchConfig(
        env_steps=150, demos=3, random_episodes=2, eval_every=100, eval_goals=2, batch_size=4
    )
    out = rb.train(cfg, seed=0)
    steps = [r["env_steps"] for r in out["curve"]]
    assert steps[0] == 0 and len(steps) >= 2 and steps[-1] >= 100
    assert out["env_steps"] >= 150 and out["updates"] == out["env_steps"]  # one update per env step added
    assert np.isfinite(out["curve"][-1]["alpha"]) and out["curve"][-1]["alpha"] < 0.1  # α moved


def test_a_learner_that_imitates_the_expert_solves_the_state_task():
    """The greedy policy runtime on the bench's evaluation reads what the actor learned: a state actor
    cloned from 60 expert episodes (a few hundred steps of its own BC) solves most fixed goals, an
    untrained one almost none."""
    torch.manual_seed(0)
    cfg = rb.ReachBenchConfig(eval_goals=10)
    sac = rb.sac_config(cfg)
    agent = sac.build(0, torch.device("cpu"))
    greedy = rb.ActorRuntime.of(agent.actor, sac.spec(), deterministic=True)
    before = rb.evaluate_headings(greedy, cfg)["success"]
    rng = np.random.default_rng(0)
    eps = [rb.rollout(rt.draw_start(rng), _expert, cfg) for _ in range(60)]
    opt = torch.optim.Adam(agent.actor.parameters(), lr=3e-3)
    for _ in range(300):
        loss = 0.0
        for states, actions, _ in eps[::6]:
            img = images_from_codes(
                torch.from_numpy(np.stack([rt.observe(s, "state", 1) for s in states[:-1]]))
            )[None]
            prev = torch.from_numpy(np.concatenate([np.zeros((1, 5), np.float32), np.stack(actions)[:-1]]))[
                None
            ]
            mean, _, _ = agent.actor(img, prev)
            loss = loss + ((torch.tanh(mean) - torch.from_numpy(np.stack(actions))[None]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = rb.evaluate_headings(greedy, cfg)["success"]
    assert before <= 0.2 and after >= 0.8, (before, after)


def test_heading_is_the_cosine_between_the_move_and_the_way_to_the_goal():
    s = rt.ReachState(np.zeros(2), np.array([1.0, 0.0]))
    move = lambda dx, dy: np.array([0.0, dx, dy, 0.0, 0.0], np.float32)  # noqa: E731
    assert rb.heading(s, move(1.0, 0.0)) == pytest.approx(1.0)
    assert rb.heading(s, move(-0.5, 0.0)) == pytest.approx(-1.0)
    assert rb.heading(s, move(0.0, 0.7)) == pytest.approx(0.0, abs=1e-12)
    assert rb.heading(s, move(0.3, 0.3)) == pytest.approx(np.sqrt(0.5))
    assert rb.heading(s, move(0.0, 0.0)) == 0.0  # no move: no heading


def test_clone_updates_start_the_actor_from_a_clone_of_the_demonstrations():
    """With ``clone_updates`` the actor is cloned from the stored demos before its first rollout: the
    evaluation recorded there heads for the goal, first move and next, where the untrained actor does
    not; the clone's updates are not SAC updates (one per env step, as before)."""
    cfg = rb.ReachBenchConfig(env_steps=70, demos=10, random_episodes=0, eval_every=10000, eval_goals=5,
                              batch_size=8, clone_updates=150)  # fmt: skip
    out = rb.train(cfg, seed=0)
    start, cloned = out["curve"][0], out["curve"][1]
    assert start["heading_first"] < 0.5 and start["heading_later"] < 0.5, start
    assert cloned["heading_first"] > 0.9 and cloned["heading_later"] > 0.9, cloned
    assert cloned["updates"] == cloned["env_steps"] and out["updates"] == out["env_steps"]


def test_the_known_answers_shown_are_those_of_the_task_run():
    state = [r["run"] for r in rb.known_rows(rb.ReachBenchConfig())]
    memory = [r["run"] for r in rb.known_rows(rb.ReachBenchConfig(goal_steps=1))]
    assert any("SB3" in r for r in state) and not any("SB3" in r for r in memory)
    assert len(memory) == 2 and all("public code" in r for r in memory)
    assert rb.known_rows(rb.ReachBenchConfig(observation="centred", group="c4")) == []
    assert rb.known_rows(rb.ReachBenchConfig(goal_steps=2)) == []


def test_bad_settings_are_refused_in_one_line():
    with pytest.raises(ValueError, match="--group c4 needs --observation image"):
        rb.ReachBenchConfig(group="c4")
    with pytest.raises(ValueError, match="odd"):
        rb.ReachBenchConfig(observation="image", image_size=12)
    with pytest.raises(ValueError, match="--observation"):
        rb.ReachBenchConfig(observation="pixels")
    with pytest.raises(ValueError, match="--fixed-alpha"):
        rb.ReachBenchConfig(fixed_alpha=-1.0)
    with pytest.raises(ValueError, match="--goal-steps"):
        rb.ReachBenchConfig(goal_steps=-1)
    with pytest.raises(ValueError, match="--alpha-loss"):
        rb.ReachBenchConfig(alpha_loss="alpha2")
    with pytest.raises(ValueError, match="--clone-updates"):
        rb.ReachBenchConfig(clone_updates=10, demos=0)


def test_the_arm_names_what_differs_from_the_public_recipe():
    assert rb.arm_name(rb.ReachBenchConfig()) == "state-none"
    cfg = rb.ReachBenchConfig(observation="centred", group="c4", share_encoder=True, alpha_loss="log_alpha",
                              alpha_lr=3e-4)  # fmt: skip
    assert rb.arm_name(cfg) == "centred-c4-shared-log_alpha0.0003"
    assert rb.sac_config(cfg).sac.alpha_loss == "log_alpha" and rb.sac_config(cfg).sac.share_encoder
    held = rb.ReachBenchConfig(goal_steps=1, actor_prev_action=False, fixed_alpha=0.005, clone_updates=500)
    assert rb.arm_name(held) == "state-none-goal1-noprev-alpha0.005-clone500"
    sac = rb.sac_config(held)
    assert not sac.net.actor_prev_action and sac.sac.init_alpha == 0.005 and not sac.sac.autotune_alpha
    assert rb.sac_config(rb.ReachBenchConfig()).sac.autotune_alpha
