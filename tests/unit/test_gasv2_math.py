"""GASv2 (DreamerV2) math tested as math: KL balancing and free nats by autograd, lambda-returns
against a loop and hand numbers, REINFORCE signs and baseline, slow critic, gradient isolation,
padding, terminals and resets."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from torch import nn

from services.algorithms.gasv2.action_features import DISCRETE_FEATURES
from services.algorithms.gasv2.agent import GasV2Agent
from services.algorithms.gasv2.behaviour import (
    Imagination,
    actor_loss,
    behaviour_losses,
    critic_loss,
    imagination_targets,
    lambda_returns,
    start_states,
    trajectory_weights,
    update_slow_target,
)
from services.algorithms.gasv2.chunks import ChunkBatch
from services.algorithms.gasv2.config import PRESETS
from services.algorithms.gasv2.rssm import (
    RSSM,
    GRUCell,
    RSSMState,
    categorical_kl,
    features,
    kl_loss,
    sample_one_hot,
)
from services.algorithms.gasv2.world_model import Decoder, Encoder, WorldModel
from tests.helpers.tiny_nets import check_lerp_update

pytestmark = [pytest.mark.unit, pytest.mark.usefixtures("one_torch_thread")]
SMOKE = PRESETS["smoke"]


def random_batch(
    B: int, L: int, lengths: list[int] | None = None, seed: int = 0, size: int = 64
) -> ChunkBatch:
    """Windows of random content; window b has ``lengths[b]`` real observations (then padding, all
    zero), starts its episode, every real observation handed over, the last real one terminal."""
    g = torch.Generator().manual_seed(seed)
    lengths = lengths or [L] * B
    mask = torch.arange(L)[None] < torch.tensor(lengths)[:, None]
    is_first = torch.zeros(B, L, dtype=torch.bool)
    is_first[:, 0] = True
    discounts = mask.float()
    for b, n in enumerate(lengths):
        discounts[b, n - 1] = 0.0
    m = mask.float()
    return ChunkBatch(
        images=torch.rand(B, L, 3, size, size, generator=g) * m[..., None, None, None],
        actions=torch.randn(B, L, 5, generator=g) * (m * ~is_first)[..., None],
        rewards=torch.rand(B, L, generator=g) * m * ~is_first,
        discounts=discounts,
        is_first=is_first,
        handover=mask.clone(),
        mask=mask,
        demo=torch.zeros(B),
    )


# --------------------------------------------------------------------------------------------
# KL balancing and free nats
# --------------------------------------------------------------------------------------------


def logits_pair(seed: int = 0, shape: tuple[int, ...] = (3, 4, 5, 6)) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    post = (torch.randn(shape, generator=g) * 2).requires_grad_(True)
    prior = (torch.randn(shape, generator=g) * 2).requires_grad_(True)
    return post, prior


def test_categorical_kl_equals_torch_distributions():
    post, prior = logits_pair(1)
    ref = torch.distributions.kl_divergence(
        torch.distributions.Categorical(logits=post), torch.distributions.Categorical(logits=prior)
    ).sum(-1)
    assert torch.allclose(categorical_kl(post, prior), ref, atol=1e-5)
    assert torch.allclose(categorical_kl(post, post), torch.zeros(3, 4), atol=1e-6)


@pytest.mark.parametrize("balance", [0.8, 0.5, 0.1])
def test_kl_balance_splits_the_gradient_between_prior_and_posterior(balance):
    post, prior = logits_pair(2)
    loss, value = kl_loss(post, prior, balance, free=0.0, free_avg=True)
    g_post, g_prior = torch.autograd.grad(loss, (post, prior))
    plain = categorical_kl(post, prior).mean()
    p_post, p_prior = torch.autograd.grad(plain, (post, prior))
    assert loss.item() == pytest.approx(plain.item(), rel=1e-6)  # the value is the plain KL
    assert torch.allclose(value, categorical_kl(post, prior).detach())
    assert torch.allclose(g_prior, balance * p_prior, atol=1e-7)
    assert torch.allclose(g_post, (1 - balance) * p_post, atol=1e-7)
    assert g_prior.abs().sum() > 0 and g_post.abs().sum() > 0


def test_free_nats_on_the_average_stop_the_gradient_below_the_threshold():
    post, prior = logits_pair(3)
    mean_kl = categorical_kl(post, prior).mean().item()
    # under the mean KL: the free nats do nothing
    loss, _ = kl_loss(post, prior, 0.8, free=mean_kl - 1.0, free_avg=True)
    assert loss.item() == pytest.approx(mean_kl, rel=1e-6)
    # above it: the loss is the constant and nothing is learned
    loss, _ = kl_loss(post, prior, 0.8, free=mean_kl + 1.0, free_avg=True)
    assert loss.item() == pytest.approx(mean_kl + 1.0)
    grads = torch.autograd.grad(loss, (post, prior), allow_unused=True)
    assert all(g is None or g.abs().sum() == 0 for g in grads)


def test_free_nats_per_step_clamp_each_step_before_the_mean():
    post, prior = logits_pair(4)
    per_step = categorical_kl(post, prior).detach()
    free = float(per_step.median())
    loss, _ = kl_loss(post, prior, 0.8, free=free, free_avg=False)
    assert loss.item() == pytest.approx(per_step.clamp_min(free).mean().item(), rel=1e-6)
    # the averaged form differs here (the mean is above the median): the two are really different
    avg, _ = kl_loss(post, prior, 0.8, free=free, free_avg=True)
    assert avg.item() != pytest.approx(loss.item(), rel=1e-4)
    # steps under the threshold get no gradient
    g_prior = torch.autograd.grad(loss, prior)[0]
    under = per_step < free
    assert under.any() and (g_prior[under] == 0).all() and (g_prior[~under].abs().sum() > 0)


def test_kl_loss_averages_over_the_mask_only():
    post, prior = logits_pair(5)
    mask = torch.zeros(3, 4, dtype=torch.bool)
    mask[0, :2] = mask[2, 3] = True
    loss, _ = kl_loss(post, prior, 0.8, 0.0, True, mask)
    assert loss.item() == pytest.approx(categorical_kl(post, prior)[mask].mean().item(), rel=1e-6)


def test_straight_through_sample_is_one_hot_with_the_gradient_of_the_probabilities():
    logits = torch.randn(4, 3, 5, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    s = sample_one_hot(logits, generator=torch.Generator().manual_seed(1))
    assert set(s.detach().unique().tolist()) <= {0.0, 1.0} and torch.equal(
        s.detach().sum(-1), torch.ones(4, 3)
    )
    w = torch.randn(4, 3, 5)
    (g,) = torch.autograd.grad((s * w).sum(), logits)
    (g_ref,) = torch.autograd.grad((logits.softmax(-1) * w).sum(), logits)
    assert torch.allclose(g, g_ref)
    # the samples follow the distribution
    many = sample_one_hot(
        logits.detach()[:1, :1].expand(20000, 1, 5), generator=torch.Generator().manual_seed(2)
    )
    assert torch.allclose(many.mean(0)[0], logits.detach()[0, 0].softmax(-1), atol=0.015)


# --------------------------------------------------------------------------------------------
# lambda-returns and weights
# --------------------------------------------------------------------------------------------


def lambda_returns_loop(rewards, values, discounts, bootstrap, lam):
    """Per column, per step, the recursion written out with Python floats."""
    H, N = rewards.shape
    out = torch.zeros(H, N)
    for n in range(N):
        nxt = float(bootstrap[n])
        for t in reversed(range(H)):
            v_next = float(values[t + 1, n]) if t + 1 < H else float(bootstrap[n])
            nxt = float(rewards[t, n]) + float(discounts[t, n]) * ((1 - lam) * v_next + lam * nxt)
            out[t, n] = nxt
    return out


@pytest.mark.parametrize("lam", [0.0, 0.3, 0.95, 1.0])
def test_lambda_returns_equal_a_python_loop(lam):
    g = torch.Generator().manual_seed(7)
    H, N = 6, 5
    r, v = torch.randn(H, N, generator=g), torch.randn(H, N, generator=g)
    d = torch.rand(H, N, generator=g) * (torch.rand(H, N, generator=g) > 0.2)
    boot = torch.randn(N, generator=g)
    assert torch.allclose(
        lambda_returns(r, v, d, boot, lam), lambda_returns_loop(r, v, d, boot, lam), atol=1e-5
    )


def test_lambda_returns_reference_numbers():
    # rewards (1, 0, 2), values (9 unread, 0.5, 1.0), discounts (0.9, 0.9, 0.5), bootstrap 4, lam 0.5
    # R_2 = 2 + 0.5 * (0.5 * 4   + 0.5 * 4)    = 4.0
    # R_1 = 0 + 0.9 * (0.5 * 1.0 + 0.5 * 4.0)  = 0.9 * 2.5   = 2.25
    # R_0 = 1 + 0.9 * (0.5 * 0.5 + 0.5 * 2.25) = 1 + 0.9 * 1.375 = 2.2375
    R = lambda_returns(
        torch.tensor([[1.0], [0.0], [2.0]]),
        torch.tensor([[9.0], [0.5], [1.0]]),
        torch.tensor([[0.9], [0.9], [0.5]]),
        torch.tensor([4.0]),
        0.5,
    )
    assert R[:, 0].tolist() == pytest.approx([2.2375, 2.25, 4.0])


def test_lambda_one_is_monte_carlo_and_lambda_zero_is_one_step_td():
    g = torch.Generator().manual_seed(8)
    H, N = 5, 3
    r, v, d = torch.randn(H, N, generator=g), torch.randn(H, N, generator=g), torch.rand(H, N, generator=g)
    boot = torch.randn(N, generator=g)
    mc = torch.zeros(H, N)
    for t in range(H):  # sum_k (d_t ... d_{k-1}) r_k + (d_t ... d_{H-1}) bootstrap
        acc = torch.ones(N)
        for k in range(t, H):
            mc[t] += acc * r[k]
            acc = acc * d[k]
        mc[t] += acc * boot
    assert torch.allclose(lambda_returns(r, v, d, boot, 1.0), mc, atol=1e-5)
    next_v = torch.cat([v[1:], boot[None]])
    assert torch.allclose(lambda_returns(r, v, d, boot, 0.0), r + d * next_v, atol=1e-6)


def test_lambda_returns_reject_mismatched_shapes():
    with pytest.raises(ValueError, match="bootstrap"):
        lambda_returns(torch.zeros(3, 2), torch.zeros(3, 2), torch.zeros(3, 2), torch.zeros(3), 0.9)


def test_weights_vanish_after_a_predicted_terminal():
    d = torch.tensor([[0.9, 0.5], [0.0, 0.5], [0.9, 0.5], [0.9, 0.5]])  # column 0: z_2 is terminal
    w = trajectory_weights(d)
    assert w[:, 0].tolist() == pytest.approx([1.0, 0.9, 0.0, 0.0])
    assert w[:, 1].tolist() == pytest.approx([1.0, 0.5, 0.25, 0.125])


def smoke_world(seed: int = 0, **changes) -> tuple[WorldModel, nn.Module, nn.Module, nn.Module]:
    agent = GasV2Agent(replace(SMOKE, **changes), seed=seed)
    return agent.world_model, agent.actor, agent.critic, agent.slow_critic


def test_imagination_stops_at_a_predicted_terminal():
    wm, actor, _, slow = smoke_world()
    head = wm.discount_head[-1]
    with torch.no_grad():  # P(continue) = sigmoid(-100): every imagined state is terminal
        head.weight.zero_()
        head.bias.fill_(-100.0)
    feats = torch.randn(4, 3, SMOKE.feat_dim, generator=torch.Generator().manual_seed(0))
    tg = imagination_targets(wm, slow, Imagination(feats, torch.zeros(3, 3, dtype=torch.long)), lam=0.95)
    assert tg.weights[0].tolist() == [1.0, 1.0, 1.0] and (tg.weights[1:] < 1e-30).all()
    assert torch.allclose(tg.returns, tg.rewards, atol=1e-6)  # R_t = r_{t+1}: nothing after a terminal
    # and with a certain continue, the discount is cfg.discount
    with torch.no_grad():
        head.bias.fill_(100.0)
    tg = imagination_targets(wm, slow, Imagination(feats, torch.zeros(3, 3, dtype=torch.long)), lam=0.95)
    assert torch.allclose(tg.discounts, torch.full((3, 3), SMOKE.discount))


# --------------------------------------------------------------------------------------------
# actor and critic losses
# --------------------------------------------------------------------------------------------


def log_pi(actor: nn.Module, feats: torch.Tensor, a: int) -> float:
    return float(actor(feats).detach().log_softmax(-1)[..., a].sum())


@pytest.mark.parametrize("advantage", [1.0, -1.0])
def test_reinforce_raises_the_log_prob_of_an_action_with_positive_advantage(advantage):
    torch.manual_seed(0)
    actor = nn.Linear(6, 9)
    feats = torch.randn(1, 1, 6)
    a = torch.tensor([[4]])
    before = log_pi(actor, feats, 4)
    loss, _ = actor_loss(
        actor, feats, a, torch.tensor([[advantage + 0.3]]), torch.tensor([[0.3]]), torch.ones(1, 1), 0.0
    )
    loss.backward()
    torch.optim.SGD(actor.parameters(), lr=0.1).step()
    after = log_pi(actor, feats, 4)
    assert (after - before) * advantage > 0


def test_baseline_and_returns_are_detached_and_leave_the_expected_gradient_unchanged():
    torch.manual_seed(1)
    actor = nn.Linear(6, 9)
    feats = torch.randn(1, 1, 6).expand(1, 9, 6)  # one state, every action enumerated
    actions = torch.arange(9)[None]
    rewards = torch.randn(1, 9)
    probs = actor(feats).softmax(-1)[0, 0].detach()
    weights = probs[None] * 9  # mean over the 9 actions = expectation under pi
    grads = []
    for b in (0.0, 5.0):
        baseline = torch.full((1, 9), b, requires_grad=True)
        returns = rewards.clone().requires_grad_(True)
        loss, _ = actor_loss(actor, feats, actions, returns, baseline, weights, 0.0)
        g_b, g_r = torch.autograd.grad(loss, (baseline, returns), retain_graph=True, allow_unused=True)
        assert g_b is None and g_r is None  # detached
        grads.append(torch.autograd.grad(loss, list(actor.parameters())))
    for g0, g5 in zip(*grads, strict=True):
        assert torch.allclose(g0, g5, atol=1e-5)  # sum_a pi(a) grad log pi(a) b = 0
    assert any(g.abs().sum() > 1e-3 for g in grads[0])


def test_entropy_bonus_raises_the_entropy():
    torch.manual_seed(2)
    actor = nn.Linear(6, 9)
    feats = torch.randn(4, 3, 6)
    zero = torch.zeros(4, 3)  # no advantage: only the entropy term acts
    acts = torch.zeros(4, 3, dtype=torch.long)
    ent = lambda: float(actor_loss(actor, feats, acts, zero, zero, torch.ones(4, 3), 0.0)[1]["actor_entropy"])  # noqa: E731
    before = ent()
    loss, _ = actor_loss(actor, feats, acts, zero, zero, torch.ones(4, 3), 1.0)
    assert loss.item() == pytest.approx(-before, rel=1e-5)  # loss = -scale x entropy
    loss.backward()
    torch.optim.SGD(actor.parameters(), lr=0.1).step()
    assert ent() > before


def test_critic_loss_is_a_weighted_half_squared_error_onto_detached_returns():
    critic = nn.Sequential(nn.Linear(4, 1), nn.Flatten(-2))
    feats = torch.randn(3, 2, 4)
    returns = torch.randn(3, 2, requires_grad=True)
    w = torch.tensor([[1.0, 1.0], [0.5, 0.0], [0.25, 0.0]])
    loss = critic_loss(critic, feats, returns, w)
    v = critic(feats).detach()
    assert loss.item() == pytest.approx((w * 0.5 * (v - returns.detach()) ** 2).mean().item(), rel=1e-6)
    assert torch.autograd.grad(loss, returns, allow_unused=True)[0] is None


# --------------------------------------------------------------------------------------------
# slow critic
# --------------------------------------------------------------------------------------------


def test_update_slow_target_copies_at_fraction_one_and_moves_by_the_fraction_otherwise():
    slow, critic = check_lerp_update(update_slow_target, 0.25, seed=3)
    update_slow_target(slow, critic, 1.0)
    for s, c in zip(slow.parameters(), critic.parameters(), strict=True):
        assert torch.equal(s, c)


def params(m: nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in m.parameters()]


@pytest.mark.parametrize("fraction", [1.0, 0.5])
def test_slow_critic_follows_the_critic_every_n_updates(fraction):
    agent = GasV2Agent(
        replace(SMOKE, slow_target_every=3, slow_target_fraction=fraction, critic_lr=1e-2), seed=1
    )
    batch = random_batch(2, 3, seed=1)
    slow = params(agent.slow_critic)
    for k in range(1, 7):
        agent.update(batch)
        now, critic = params(agent.slow_critic), params(agent.critic)
        if k % 3:
            assert all(torch.equal(a, b) for a, b in zip(now, slow, strict=True)), k  # unchanged between
            assert not all(torch.equal(a, b) for a, b in zip(now, critic, strict=True))
        else:
            for n, s, c in zip(now, slow, critic, strict=True):
                assert (
                    torch.allclose(n, s + fraction * (c - s), atol=1e-7)
                    if fraction < 1
                    else torch.equal(n, c)
                )
        slow = now


# --------------------------------------------------------------------------------------------
# gradient isolation
# --------------------------------------------------------------------------------------------


def no_grads(m: nn.Module) -> bool:
    return all(p.grad is None for p in m.parameters())


def some_grads(m: nn.Module) -> bool:
    return any(p.grad is not None and p.grad.abs().sum() > 0 for p in m.parameters())


def test_each_loss_reaches_only_its_own_network():
    wm, actor, critic, slow = smoke_world(2)
    agent_features = torch.as_tensor(DISCRETE_FEATURES)
    model_loss, posts, _ = wm.loss(random_batch(3, 4, seed=2), torch.Generator().manual_seed(0))
    model_loss.backward()
    assert some_grads(wm) and no_grads(actor) and no_grads(critic) and no_grads(slow)
    wm.zero_grad(set_to_none=True)
    start = start_states(posts, random_batch(3, 4, seed=2))
    assert start.deter.shape[0] == 9 and not start.deter.requires_grad  # 3 x 4 real, 3 terminal
    a_loss, c_loss, _ = behaviour_losses(wm, actor, critic, slow, start, SMOKE, agent_features)
    a_loss.backward()
    assert some_grads(actor) and no_grads(wm) and no_grads(critic) and no_grads(slow)
    actor.zero_grad(set_to_none=True)
    c_loss.backward()
    assert some_grads(critic) and no_grads(wm) and no_grads(actor) and no_grads(slow)


def test_behaviour_update_leaves_the_world_model_unchanged():
    agent = GasV2Agent(SMOKE, seed=3)
    agent.model_opt.param_groups[0]["lr"] = 0.0  # AdamW's decay is lr x wd: nothing moves the model
    agent.model_opt.param_groups[0]["weight_decay"] = 0.0
    before, actor_before = params(agent.world_model), params(agent.actor)
    m = agent.update(random_batch(2, 4, seed=3))
    assert m["imag_starts"] == 6.0
    assert all(torch.equal(a, b) for a, b in zip(params(agent.world_model), before, strict=True))
    assert not all(torch.equal(a, b) for a, b in zip(params(agent.actor), actor_before, strict=True))


# --------------------------------------------------------------------------------------------
# padding, terminals, resets
# --------------------------------------------------------------------------------------------


def with_garbage_padding(batch: ChunkBatch, seed: int) -> ChunkBatch:
    g = torch.Generator().manual_seed(seed)
    pad = ~batch.mask

    def r(x: torch.Tensor) -> torch.Tensor:
        where = pad.view(*pad.shape, *[1] * (x.dim() - 2))
        return torch.where(where, torch.rand(x.shape, generator=g) * 5, x)

    def rand_bool(x: torch.Tensor) -> torch.Tensor:
        return torch.where(pad, torch.rand(x.shape, generator=g) > 0.5, x)

    return ChunkBatch(
        images=r(batch.images), actions=r(batch.actions), rewards=r(batch.rewards), discounts=r(batch.discounts),
        is_first=rand_bool(batch.is_first), handover=rand_bool(batch.handover), mask=batch.mask, demo=batch.demo,
    )  # fmt: skip


def test_padding_does_not_change_the_world_model_loss():
    wm, *_ = smoke_world(4)
    clean = random_batch(4, 5, lengths=[5, 2, 3, 1], seed=4)
    dirty = with_garbage_padding(clean, 5)
    assert not torch.equal(clean.images, dirty.images) and not torch.equal(clean.is_first, dirty.is_first)
    lc, pc, mc = wm.loss(clean, torch.Generator().manual_seed(0))
    ld, pd, md = wm.loss(dirty, torch.Generator().manual_seed(0))
    for k in mc:
        assert mc[k].item() == pytest.approx(md[k].item(), rel=1e-5, abs=1e-6), k
    assert torch.allclose(pc.deter[clean.mask], pd.deter[clean.mask], atol=1e-6)
    # the padded start states are not imagined from either
    assert start_states(pc, clean).deter.shape[0] == start_states(pd, dirty).deter.shape[0] == 7


def test_discount_head_learns_the_batch_discounts_zero_at_terminal_rows():
    wm, *_ = smoke_world(5)
    batch = random_batch(3, 4, lengths=[4, 2, 3], seed=5)
    assert batch.discounts[batch.mask].tolist().count(0.0) == 3  # one terminal per window
    _, posts, metrics = wm.loss(batch, torch.Generator().manual_seed(0))
    logits = wm.discount_head(features(posts)).squeeze(-1).detach()
    bce = nn.functional.binary_cross_entropy_with_logits(logits, batch.discounts, reduction="none")
    assert metrics["discount_loss"].item() == pytest.approx(bce[batch.mask].mean().item(), rel=1e-5)
    # a head sure that nothing ends pays at the terminal rows only
    with torch.no_grad():
        wm.discount_head[-1].weight.zero_()
        wm.discount_head[-1].bias.fill_(20.0)
    _, _, metrics = wm.loss(batch, torch.Generator().manual_seed(0))
    assert metrics["discount_loss"].item() == pytest.approx(20.0 * 3 / 9, rel=1e-3)


def test_world_model_loss_terms_by_hand():
    wm, *_ = smoke_world(6)
    batch = random_batch(2, 3, lengths=[3, 2], seed=6)
    loss, posts, m = wm.loss(batch, torch.Generator().manual_seed(0))
    feat = features(posts)[batch.mask]
    image = 0.5 * (wm.decoder(feat) - (batch.images[batch.mask] - 0.5)).pow(2).sum((1, 2, 3)).mean()
    reward = 0.5 * (wm.reward(feat) - torch.tanh(batch.rewards[batch.mask])).pow(2).mean()
    assert m["image_loss"].item() == pytest.approx(image.item(), rel=1e-5)
    assert m["reward_loss"].item() == pytest.approx(reward.item(), rel=1e-5)
    total = m["kl"] + m["image_loss"] + m["reward_loss"] + m["discount_loss"]  # kl_scale 1, free 0
    assert loss.item() == pytest.approx(total.item(), rel=1e-5)


def test_world_model_loss_does_not_mutate_the_batch():
    wm, *_ = smoke_world(7)
    batch = random_batch(2, 3, seed=7)
    before = {k: v.clone() for k, v in batch.__dict__.items()}
    wm.loss(batch)
    assert all(torch.equal(v, before[k]) for k, v in batch.__dict__.items())


def smoke_rssm(seed: int = 0) -> RSSM:
    torch.manual_seed(seed)
    return RSSM(SMOKE, embed_dim=7)


def test_obs_step_resets_state_and_action_at_is_first():
    rssm = smoke_rssm(1)
    g = torch.Generator().manual_seed(0)
    B = 3
    c = SMOKE
    state = RSSMState(
        torch.randn(B, c.deter, generator=g),
        torch.randn(B, c.stoch, c.classes, generator=g),
        torch.rand(B, c.stoch_dim, generator=g),
    )
    action, embed = torch.randn(B, 5, generator=g), torch.randn(B, 7, generator=g)
    is_first = torch.tensor([True, False, True])
    post, prior = rssm.obs_step(state, action, embed, is_first, sample=False)
    no_reset = torch.zeros(B, dtype=torch.bool)
    fresh, fresh_prior = rssm.obs_step(rssm.initial(B), torch.zeros(B, 5), embed, no_reset, sample=False)
    for a, b in ((post, fresh), (prior, fresh_prior)):
        assert torch.allclose(a.deter[is_first], b.deter[is_first]) and torch.allclose(
            a.logits[is_first], b.logits[is_first]
        )
        assert not torch.allclose(a.deter[1], b.deter[1])


def test_observe_restarts_at_is_first_inside_a_window():
    rssm = smoke_rssm(2)
    g = torch.Generator().manual_seed(1)
    embeds, actions = torch.randn(2, 5, 7, generator=g), torch.randn(2, 5, 5, generator=g)
    is_first = torch.zeros(2, 5, dtype=torch.bool)
    is_first[:, 2] = True  # a new episode starts at t = 2
    posts, priors = rssm.observe(embeds, actions, is_first, sample=False)
    tail, tail_priors = rssm.observe(embeds[:, 2:], actions[:, 2:], is_first[:, 2:], sample=False)
    assert torch.allclose(posts.deter[:, 2:], tail.deter, atol=1e-6)
    assert torch.allclose(posts.logits[:, 2:], tail.logits, atol=1e-6)
    assert torch.allclose(priors.logits[:, 2:], tail_priors.logits, atol=1e-6)
    # without the reset the history matters
    no_reset, _ = rssm.observe(embeds, actions, torch.zeros(2, 5, dtype=torch.bool), sample=False)
    assert not torch.allclose(no_reset.deter[:, 2:], tail.deter, atol=1e-3)


def test_observe_equals_repeated_obs_step_and_imagine_equals_repeated_img_step():
    rssm = smoke_rssm(3)
    g = torch.Generator().manual_seed(2)
    embeds, actions = torch.randn(2, 4, 7, generator=g), torch.randn(2, 4, 5, generator=g)
    is_first = torch.zeros(2, 4, dtype=torch.bool)
    is_first[:, 0] = True
    posts, priors = rssm.observe(embeds, actions, is_first, generator=torch.Generator().manual_seed(9))
    gen, state = torch.Generator().manual_seed(9), rssm.initial(2)
    for t in range(4):
        state, prior = rssm.obs_step(state, actions[:, t], embeds[:, t], is_first[:, t], generator=gen)
        assert torch.equal(state.stoch, posts.stoch[:, t]) and torch.equal(prior.deter, priors.deter[:, t])
    start = RSSMState(*(x[:, 1] for x in posts))
    imagined = rssm.imagine(actions[:, 1:], start, sample=False)
    state = start
    for t in range(3):
        state = rssm.img_step(state, actions[:, 1 + t], sample=False)
        assert torch.equal(state.deter, imagined.deter[:, t])


def test_gru_cell_reference_formula():
    torch.manual_seed(4)
    cell = GRUCell(3, 2, norm=True)
    x, h = torch.randn(5, 3), torch.randn(5, 2)
    parts = torch.cat([x, h], -1) @ cell.layer.weight.T + cell.layer.bias
    mu, var = parts.mean(-1, keepdim=True), parts.var(-1, unbiased=False, keepdim=True)
    parts = (parts - mu) / torch.sqrt(var + 1e-3)  # Keras LayerNormalization, epsilon 1e-3
    r, c, u = parts[:, :2], parts[:, 2:4], parts[:, 4:]
    c = torch.tanh(torch.sigmoid(r) * c)
    u = torch.sigmoid(u - 1.0)  # update bias -1
    assert torch.allclose(cell(x, h), u * c + (1 - u) * h, atol=1e-6)


@pytest.mark.parametrize("preset", ["smoke", "cpu-small"])
def test_encoder_and_decoder_shapes(preset):
    cfg = PRESETS[preset]
    enc, dec = Encoder(cfg), Decoder(cfg)
    # 64 -> 31 -> 14 -> 6 -> 2 with kernels 4 and stride 2; depth doubles to 8 x cnn_depth
    assert enc.embed_dim == 8 * cfg.cnn_depth * 2 * 2
    assert enc(torch.rand(2, 3, 3, 64, 64)).shape == (2, 3, enc.embed_dim)
    assert dec(torch.randn(4, cfg.feat_dim)).shape == (4, 3, 64, 64)  # 1 -> 5 -> 13 -> 30 -> 64
    with pytest.raises(ValueError, match="images"):
        enc(torch.rand(2, 3, 32, 32))
