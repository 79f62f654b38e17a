"""GasV2Agent end to end on toy worlds (the world model learns, the imagination actor finds the
rewarded action), checkpoints, the published LatentPolicy, and the presets."""

from __future__ import annotations

import io
import json
import math
from dataclasses import replace

import pytest
import torch

from services.algorithms.gasv2.action_features import DISCRETE_FEATURES
from services.algorithms.gasv2.agent import GasV2Agent, LatentPolicy, build_policy
from services.algorithms.gasv2.chunks import ChunkBatch
from services.algorithms.gasv2.config import PRESETS, DreamerConfig
from services.algorithms.gasv2.rssm import RSSMState
from tests.unit.test_gasv2_math import random_batch

pytestmark = [pytest.mark.unit, pytest.mark.usefixtures("one_torch_thread")]
SMOKE = PRESETS["smoke"]
FAST = replace(SMOKE, model_lr=1e-3, actor_lr=1e-3, critic_lr=1e-3)
"""The smoke model with learning rates raised (x10 the paper's model lr) so that toy problems
converge in a few hundred updates; every loss is the paper's."""
FEATURES = torch.as_tensor(DISCRETE_FEATURES)
REQUIRED = ("model_loss", "image_loss", "reward_loss", "discount_loss", "kl", "actor_loss", "critic_loss",
            "actor_entropy", "imag_return", "imag_starts")  # fmt: skip


# --------------------------------------------------------------------------------------------
# (a) a 1-D toy world: the world model learns images, rewards and terminals
# --------------------------------------------------------------------------------------------

CELLS, GOAL = 8, 5


def line_image(p: int) -> torch.Tensor:
    """A bright column over cell p (8 pixels wide) and a goal mark at the bottom."""
    img = torch.zeros(3, 64, 64)
    img[:, :, 8 * p : 8 * p + 8] = 1.0
    img[1, 56:, 8 * GOAL : 8 * GOAL + 8] = 1.0
    return img


def line_world_batch(B: int, L: int, g: torch.Generator) -> ChunkBatch:
    """Episodes from a random non-goal cell; +x / -x at random move one cell (clipped to the line);
    reaching the goal pays 1 and ends the episode (the rest of the window is padding)."""
    images, actions = torch.zeros(B, L, 3, 64, 64), torch.zeros(B, L, 5)
    rewards, discounts = torch.zeros(B, L), torch.zeros(B, L)
    mask, is_first = torch.zeros(B, L, dtype=torch.bool), torch.zeros(B, L, dtype=torch.bool)
    for b in range(B):
        p = int(torch.randint(0, CELLS - 1, (1,), generator=g))
        p += int(p >= GOAL)
        for t in range(L):
            if t > 0:
                a = int(torch.randint(0, 2, (1,), generator=g))  # 0: +x, 1: -x
                p = min(max(p + (1 if a == 0 else -1), 0), CELLS - 1)
                actions[b, t], rewards[b, t] = FEATURES[a], float(p == GOAL)
            images[b, t], mask[b, t], is_first[b, t] = line_image(p), True, t == 0
            discounts[b, t] = float(p != GOAL)
            if p == GOAL:
                break
    return ChunkBatch(images, actions, rewards, discounts, is_first, mask.clone(), mask, torch.zeros(B))


@pytest.mark.slow
def test_world_model_learns_a_line_world():
    agent = GasV2Agent(FAST, seed=0)
    held_out = line_world_batch(32, 6, torch.Generator().manual_seed(123))
    m = held_out.mask
    assert 0 < held_out.rewards[m].sum() < m.sum()  # some goals reached, not all

    def evaluate() -> dict[str, float]:
        with torch.no_grad():
            _, _, metrics = agent.world_model.loss(held_out, torch.Generator().manual_seed(0))
        return {k: float(v) for k, v in metrics.items()}

    before = evaluate()
    g = torch.Generator().manual_seed(0)
    for _ in range(200):
        agent.update(line_world_batch(8, 6, g))
    after = evaluate()
    # what predictors that ignore the state would score: the mean image, the mean reward
    images = held_out.images[m]
    mean_image_loss = float(0.5 * (images - images.mean(0)).pow(2).sum((1, 2, 3)).mean())
    r = torch.tanh(held_out.rewards[m])
    mean_reward_loss = float(0.5 * (r - r.mean()).pow(2).mean())
    assert after["image_loss"] < before["image_loss"] / 20
    assert after["image_loss"] < mean_image_loss / 4, (after, mean_image_loss)
    assert after["reward_loss"] < before["reward_loss"] / 10
    assert after["reward_loss"] < mean_reward_loss / 5, (after, mean_reward_loss)
    assert after["discount_loss"] < before["discount_loss"] / 5
    assert after["kl"] > 0.5  # the latent carries the position (no posterior collapse)


# --------------------------------------------------------------------------------------------
# (b) a one-step bandit: the imagination actor finds the one rewarded action
# --------------------------------------------------------------------------------------------

BEST = 6  # "+yaw"


def start_image() -> torch.Tensor:
    img = torch.zeros(3, 64, 64)
    img[1, 16:48, 16:48] = 1.0
    return img


def bandit_batch(B: int, g: torch.Generator) -> ChunkBatch:
    """Episodes of one decision: from the start image (handed over) an action uniform over the 9
    leads to a terminal observation, red if it paid 1 (action BEST), black otherwise; then padding."""
    L = 3
    a = torch.randint(0, 9, (B,), generator=g)
    won = (a == BEST).float()
    images = torch.zeros(B, L, 3, 64, 64)
    images[:, 0] = start_image()
    images[:, 1, 0] = won[:, None, None]
    actions = torch.zeros(B, L, 5)
    actions[:, 1] = FEATURES[a]
    rewards = torch.zeros(B, L)
    rewards[:, 1] = won
    row = lambda *v: torch.tensor(v).expand(B, L).clone()  # noqa: E731
    mask = row(True, True, False)
    return ChunkBatch(images, actions, rewards, row(1.0, 0.0, 0.0), row(True, False, False), mask.clone(), mask,
                      torch.zeros(B))  # fmt: skip


def action_probs(policy: LatentPolicy) -> torch.Tensor:
    with torch.no_grad():
        logits, _ = policy.step(
            policy.initial_state(1), torch.zeros(1, 5), start_image()[None], torch.ones(1, dtype=torch.bool),
            sample=False,
        )  # fmt: skip
    return logits.softmax(-1)[0]


@pytest.mark.slow
def test_imagination_actor_finds_the_rewarded_action():
    agent = GasV2Agent(FAST, seed=0)
    assert int(action_probs(agent.policy).argmax()) != BEST  # not by luck of the initialisation
    g = torch.Generator().manual_seed(0)
    for _ in range(200):
        m = agent.update(bandit_batch(16, g))
    assert m["imag_starts"] == 16.0  # only the start observations: the terminal ones are not acted from
    probs = action_probs(agent.policy)
    assert int(probs.argmax()) == BEST, probs
    assert probs[BEST] > 0.5, probs


# --------------------------------------------------------------------------------------------
# (c) checkpoints, metrics, skipping
# --------------------------------------------------------------------------------------------


def test_update_reports_finite_metrics():
    agent = GasV2Agent(SMOKE, seed=1)
    m = agent.update(random_batch(3, 4, seed=1))
    assert set(REQUIRED) <= set(m) and all(math.isfinite(v) for v in m.values()), m
    assert m["imag_starts"] == 9.0 and agent.updates == 1
    assert m["model_loss"] == pytest.approx(
        m["kl"] + m["image_loss"] + m["reward_loss"] + m["discount_loss"], rel=1e-5
    )


def test_update_without_start_states_skips_the_behaviour_step():
    agent = GasV2Agent(SMOKE, seed=2)
    batch = random_batch(2, 3, seed=2)
    batch = replace(batch, handover=torch.zeros_like(batch.handover))  # the controller never handed over
    actor = [p.clone() for p in agent.actor.parameters()]
    critic = [p.clone() for p in agent.critic.parameters()]
    m = agent.update(batch)
    assert m["imag_starts"] == 0.0 and m["critic_loss"] == 0.0 and m["actor_loss"] == 0.0
    assert all(math.isfinite(v) for v in m.values())
    assert all(torch.equal(a, b) for a, b in zip(agent.actor.parameters(), actor, strict=True))
    assert all(torch.equal(a, b) for a, b in zip(agent.critic.parameters(), critic, strict=True))
    assert m["model_loss"] > 0 and agent.updates == 1


def flat_state(agent: GasV2Agent) -> dict[str, torch.Tensor]:
    """Every tensor of the agent's checkpoint, by path."""
    out: dict[str, torch.Tensor] = {}

    def walk(x, path: str) -> None:
        if isinstance(x, torch.Tensor):
            out[path] = x
        elif isinstance(x, dict):
            for k, v in x.items():
                walk(v, f"{path}/{k}")
        elif isinstance(x, list | tuple):
            for i, v in enumerate(x):
                walk(v, f"{path}/{i}")

    walk(agent.state_dict(), "")
    return out


def test_state_dict_round_trip_through_torch_save_gives_a_bit_identical_next_update():
    cfg = replace(SMOKE, slow_target_every=2)
    a = GasV2Agent(cfg, seed=3)
    for k in range(3):
        a.update(random_batch(3, 4, seed=10 + k))
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    b = GasV2Agent(cfg, seed=99)  # other weights, other generator
    b.load_state_dict(torch.load(buf, weights_only=True))
    assert b.updates == 3
    batch = random_batch(3, 4, seed=20)
    ma, mb = a.update(batch), b.update(batch)  # the 4th update also syncs the slow critic
    assert ma == mb
    sa, sb = flat_state(a), flat_state(b)
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert any(k.startswith("/model_opt/state") for k in sa) and any(k.startswith("/slow_critic") for k in sa)


# --------------------------------------------------------------------------------------------
# (d) the published policy
# --------------------------------------------------------------------------------------------


def test_policy_holds_only_encoder_rssm_and_actor_shared_with_the_agent():
    agent = GasV2Agent(SMOKE, seed=4)
    keys = agent.policy.state_dict().keys()
    assert {k.split(".")[0] for k in keys} == {"encoder", "rssm", "actor"}
    assert agent.policy.encoder is agent.world_model.encoder and agent.policy.actor is agent.actor
    before = {k: v.clone() for k, v in agent.policy.state_dict().items()}
    agent.update(random_batch(2, 3, seed=4))  # training moves the published modules too
    after = agent.policy.state_dict()
    for part in ("encoder.", "rssm.", "actor."):
        assert any(not torch.equal(v, before[k]) for k, v in after.items() if k.startswith(part)), part
    rssm = agent.world_model.rssm.state_dict()
    published = {k.removeprefix("rssm."): v for k, v in after.items() if k.startswith("rssm.")}
    assert published.keys() == rssm.keys() and all(torch.equal(v, rssm[k]) for k, v in published.items())


@pytest.mark.parametrize("preset", ["smoke", "cpu-small"])
def test_build_policy_loads_the_agents_policy_and_acts_identically(preset):
    cfg = PRESETS[preset]
    agent = GasV2Agent(cfg, seed=5)
    standalone = build_policy(cfg, seed=6)
    ours, theirs = agent.policy.state_dict(), standalone.state_dict()
    assert ours.keys() == theirs.keys() and all(ours[k].shape == theirs[k].shape for k in ours)
    standalone.load_state_dict(ours)
    batch = random_batch(2, 4, seed=5)
    outs = []
    for policy in (agent.policy, standalone):
        g, state, logits = torch.Generator().manual_seed(7), policy.initial_state(2), []
        with torch.no_grad():
            for t in range(4):
                lg, state = policy.step(
                    state, batch.actions[:, t], batch.images[:, t], batch.is_first[:, t], generator=g
                )
                logits.append(lg)
        outs.append((torch.stack(logits), state))
    assert torch.equal(outs[0][0], outs[1][0])
    assert all(torch.equal(x, y) for x, y in zip(outs[0][1], outs[1][1], strict=True))


def test_policy_steps_track_the_world_models_posterior():
    agent = GasV2Agent(SMOKE, seed=8)
    agent.update(random_batch(2, 4, seed=8))  # trained a little: not the initial weights
    batch = random_batch(3, 5, seed=9)
    is_first = batch.is_first.clone()
    is_first[1, 3] = True  # window 1 holds the start of a second episode
    batch = replace(batch, is_first=is_first)
    with torch.no_grad():
        _, posts, _ = agent.world_model.loss(batch, torch.Generator().manual_seed(11))
        g, state = torch.Generator().manual_seed(11), agent.policy.initial_state(3)
        for t in range(5):
            logits, state = agent.policy.step(
                state, batch.actions[:, t], batch.images[:, t], batch.is_first[:, t], generator=g
            )
            post_t = RSSMState(*(x[:, t] for x in posts))
            for name, x, y in zip(RSSMState._fields, state, post_t, strict=True):
                assert torch.allclose(x, y, atol=1e-5), (t, name)
            assert torch.allclose(logits, agent.actor(torch.cat([post_t.stoch, post_t.deter], -1)), atol=1e-5)


# --------------------------------------------------------------------------------------------
# (e) configuration and presets
# --------------------------------------------------------------------------------------------


def test_presets_keep_the_papers_losses_and_latent_shape():
    paper = PRESETS["paper"]
    assert paper == DreamerConfig()
    assert (paper.deter, paper.hidden, paper.stoch, paper.classes, paper.cnn_depth) == (
        1024,
        1024,
        32,
        32,
        48,
    )
    assert (paper.kl_balance, paper.actor_entropy, paper.horizon, paper.slow_target_every) == (
        0.8,
        2e-3,
        15,
        100,
    )
    sizes = ("deter", "hidden", "stoch", "classes", "cnn_depth", "mlp_layers", "mlp_units")
    for name in ("cpu-small", "smoke"):
        cfg = PRESETS[name]
        assert {k: v for k, v in cfg.to_dict().items() if k not in sizes} == {
            k: v for k, v in paper.to_dict().items() if k not in sizes
        }, name
    assert (PRESETS["cpu-small"].stoch, PRESETS["cpu-small"].classes) == (32, 32)


@pytest.mark.parametrize("preset", ["paper", "cpu-small", "smoke"])
def test_presets_round_trip_through_json_and_construct(preset):
    cfg = PRESETS[preset]
    assert DreamerConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    agent = GasV2Agent(cfg, seed=0)
    assert agent.world_model.rssm.cell.layer.weight.shape == (3 * cfg.deter, cfg.hidden + cfg.deter)
    assert agent.actor.net[-1].out_features == 9 and agent.policy.rssm is agent.world_model.rssm
    if preset == "paper":
        assert agent.world_model.encoder.embed_dim == 1536  # 2 x 2 x 384, DreamerV2's 64 x 64 encoder


def test_config_rejects_bad_values_and_unknown_keys():
    with pytest.raises(ValueError, match="nonsense"):
        DreamerConfig.from_dict({"deter": 8, "nonsense": 1})
    bad = {
        "kl_balance": 1.5, "act": "gelu", "reward_transform": "sign", "deter": 0, "horizon": 0,
        "decoder_kernels": (5, 5, 6), "model_lr": 0.0, "slow_target_fraction": 0.0, "discount": 1.5,
        "encoder_kernels": (4, 4, 4, 4, 4, 4, 4),
    }  # fmt: skip
    for key, value in bad.items():
        with pytest.raises(ValueError, match=key.split("_")[0]):
            replace(SMOKE, **{key: value})
    assert DreamerConfig.from_dict({"decoder_kernels": [5, 5, 6, 6]}).decoder_kernels == (5, 5, 6, 6)
