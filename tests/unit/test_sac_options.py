"""The learner's CPU-recipe options tested as math: trimmed batches and skipped padding give the padded
batch's losses and gradients; the BC term; the shared encoder; the critic's LayerNorm keeps Q invariant."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from services.algorithms.batch import to_batch
from services.algorithms.equivariant import GroupLayerNorm
from services.algorithms.groups import get_group, transform_actions, transform_images, transform_regular
from services.algorithms.networks import NetConfig, build_actor, build_critic
from services.algorithms.privileged import STATE_DIM
from services.algorithms.replay import SequenceReplay
from services.algorithms.sac.agent import RecurrentSAC
from services.algorithms.sac.config import SacSettings
from services.algorithms.sac.losses import (
    Batch,
    actor_loss,
    bc_loss,
    conservative_gap,
    critic_loss,
    critic_targets,
    masked_mean,
    policy_outputs,
)
from tests.unit.test_replay import make_episode

pytestmark = pytest.mark.unit

SIZE, SEQ_LEN = 8, 12
NET = NetConfig(group="c4", image_size=SIZE, encoder=((2, 3, 1),), final_kernel=6, image_embed=16,
                action_embed=8, q_action_embed=8, lstm_hidden=16, mlp_hidden=(16,))  # fmt: skip


def replay_with(lengths: list[int], demos: int = 0) -> SequenceReplay:
    replay = SequenceReplay(1_000, image_size=SIZE, seq_len=SEQ_LEN, seed=0)
    for k, T in enumerate(lengths):
        replay.insert(make_episode(T, seed=k, demo=k < demos))
    return replay


def nets(net: NetConfig = NET, seed: int = 0):
    torch.manual_seed(seed)
    actor, critic = build_actor(net), build_critic(net)
    return actor, critic, build_critic(net)


def losses_and_grads(actor, critic, target, batch: Batch, noise: torch.Tensor) -> tuple[list, list]:
    L1 = batch.images.shape[1]
    policy = policy_outputs(actor, batch, noise[:, :L1])
    y = critic_targets(target, batch, policy, 0.1, 0.9)
    q_loss, feats, _ = critic_loss(critic, batch, y)
    pi_loss = actor_loss(critic, feats, batch, policy, 0.1) + bc_loss(policy.mean, batch)
    params = list(critic.parameters()) + list(actor.parameters())
    grads = torch.autograd.grad(q_loss + pi_loss, params, allow_unused=True)
    return [q_loss.detach(), pi_loss.detach()], [
        torch.zeros_like(p) if g is None else g for p, g in zip(params, grads, strict=True)
    ]


def assert_same(a: tuple[list, list], b: tuple[list, list]) -> None:
    for x, y in zip(a[0] + a[1], b[0] + b[1], strict=True):
        torch.testing.assert_close(x, y, atol=1e-6, rtol=1e-5)


def test_trimmed_batch_gives_the_padded_batchs_losses_and_gradients():
    replay = replay_with([3, 5, 4, 6], demos=2)
    padded = replay.sample(6, np.random.default_rng(0), demo_fraction=0.5)
    trimmed = replay.sample(6, np.random.default_rng(0), demo_fraction=0.5, trim=True)
    assert trimmed.seq_len == int(padded.lengths.max()) < padded.seq_len == SEQ_LEN
    noise = torch.randn(6, SEQ_LEN + 1, 5, generator=torch.Generator().manual_seed(1))
    full = to_batch(padded)
    full = dataclasses.replace(full, obs_mask=None)  # encode every padded image, as before trimming
    assert_same(losses_and_grads(*nets(), full, noise), losses_and_grads(*nets(), to_batch(trimmed), noise))


def test_skipping_padded_images_in_the_encoders_changes_nothing():
    replay = replay_with([2, 9, 4])
    batch = to_batch(replay.sample(5, np.random.default_rng(2)))
    assert not batch.obs_mask.all()
    noise = torch.randn(5, SEQ_LEN + 1, 5, generator=torch.Generator().manual_seed(3))
    assert_same(
        losses_and_grads(*nets(), dataclasses.replace(batch, obs_mask=None), noise),
        losses_and_grads(*nets(), batch, noise),
    )


@pytest.mark.parametrize("lengths", [[2, 9, 4], [SEQ_LEN, SEQ_LEN]])
def test_images_gathered_once_per_batch_give_the_same_bits(lengths):
    """``to_batch`` gathers the real observations' images once on the CPU (``Batch.real_images``);
    every loss and gradient is bit for bit what each encoder's own gather gave, with padding and
    without."""
    batch = to_batch(replay_with(lengths).sample(len(lengths), np.random.default_rng(2)))
    assert batch.real_images is not None
    assert batch.real_images.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(batch.real_images, batch.images[batch.obs_mask])
    assert bool(batch.obs_mask.all()) == (lengths == [SEQ_LEN, SEQ_LEN])
    noise = torch.randn(len(lengths), SEQ_LEN + 1, 5, generator=torch.Generator().manual_seed(3))
    own = losses_and_grads(*nets(), dataclasses.replace(batch, real_images=None), noise)
    once = losses_and_grads(*nets(), batch, noise)
    for x, y in zip(own[0] + own[1], once[0] + once[1], strict=True):
        assert torch.equal(x, y)


def test_gathered_images_that_do_not_match_the_mask_are_refused():
    batch = to_batch(replay_with([2, 9, 4]).sample(3, np.random.default_rng(2)))
    actor, _, _ = nets()
    stale = dataclasses.replace(batch, real_images=batch.real_images[1:])
    with pytest.raises(ValueError, match="gathered images for"):
        policy_outputs(actor, stale)


def test_bc_loss_is_the_squared_error_on_demo_transitions_only():
    replay = replay_with([3, 4, 5], demos=1)
    batch = to_batch(replay.sample(4, np.random.default_rng(4), demo_fraction=0.5, trim=True))
    actor, _, _ = nets()
    policy = policy_outputs(actor, batch)
    expected, count = 0.0, 0
    for b in range(4):
        if batch.demo[b]:
            n = int(batch.mask[b].sum())
            expected += float((torch.tanh(policy.mean[b, :n].detach()) - batch.actions[b, :n]).pow(2).sum())
            count += n
    assert count > 0
    torch.testing.assert_close(bc_loss(policy.mean, batch), torch.tensor(expected / count))
    no_demo = dataclasses.replace(batch, demo=torch.zeros(4))
    assert float(bc_loss(policy.mean, no_demo).detach()) == 0.0


@pytest.mark.slow
def test_bc_weight_pulls_the_policy_mean_to_the_demo_actions():
    batch = to_batch(replay_with([5], demos=1).sample(1, np.random.default_rng(5)))

    def bc_after(weight: float) -> tuple[float, float]:
        actor, critic, _ = nets()
        sac = RecurrentSAC(actor, critic, SacSettings(bc_weight=weight, lr=3e-3, share_encoder=True))
        with torch.no_grad():
            before = float(bc_loss(policy_outputs(sac.actor, batch).mean, batch))
        for _ in range(80):
            sac.update(batch)
        with torch.no_grad():
            return before, float(bc_loss(policy_outputs(sac.actor, batch).mean, batch))

    before, with_bc = bc_after(10.0)
    _, without = bc_after(0.0)
    assert with_bc < 0.5 * before and with_bc < 0.5 * without, (before, with_bc, without)


def test_shared_encoder_is_trained_by_the_critic_and_bc_never_by_the_sac_actor_loss():
    actor, critic, _ = nets()
    sac = RecurrentSAC(actor, critic, SacSettings(share_encoder=True))
    assert sac.actor.encoder is sac.critic.encoder
    encoder = {id(p) for p in sac.critic.encoder.parameters()}
    assert encoder and not encoder & {id(p) for p in sac._actor_params}
    # the policy's weights blob still carries the encoder (the actor acts on its own)
    assert any(k.startswith("encoder.") for k in sac.actor.state_dict())
    batch = to_batch(replay_with([4, 6], demos=1).sample(3, np.random.default_rng(6)))
    feats, _ = sac.critic.features(batch.images, batch.prev_actions, obs_mask=batch.obs_mask)
    policy = policy_outputs(sac.actor, batch, embedding=feats[..., -NET.image_embed :].detach())
    pi_loss = actor_loss(sac.critic, feats, batch, policy, 0.1)
    grads = torch.autograd.grad(pi_loss, list(sac.critic.encoder.parameters()), allow_unused=True)
    assert all(g is None for g in grads)
    enc_before = [p.clone() for p in sac.critic.encoder.parameters()]
    sac.update(batch)
    assert any(
        not torch.equal(a, b) for a, b in zip(enc_before, sac.critic.encoder.parameters(), strict=True)
    )


def test_bc_term_trains_the_shared_encoder():
    """Without it the actor of a sparse-reward task would depend on features only the critic shapes."""
    batch = to_batch(replay_with([4, 6], demos=1).sample(4, np.random.default_rng(8), demo_fraction=0.5))

    def encoder_change(bc_weight: float) -> float:
        actor, critic, _ = nets()
        sac = RecurrentSAC(actor, critic, SacSettings(share_encoder=True, bc_weight=bc_weight))
        sac.critic_opt = torch.optim.SGD(sac._critic_params, lr=1.0)  # the step is the gradient itself
        before = [p.clone() for p in sac.critic.encoder.parameters()]
        sac.update(batch)
        return sum(
            float((p - b).abs().sum()) for p, b in zip(sac.critic.encoder.parameters(), before, strict=True)
        )

    assert abs(encoder_change(100.0) - encoder_change(0.0)) > 1e-3 * max(encoder_change(0.0), 1e-6)


def test_shared_encoder_update_equals_separate_passes_on_the_same_weights():
    """With the actor's encoder set to the critic's and no BC, computing the embedding once is the
    same update as running it for each."""
    batch = to_batch(replay_with([4, 6, 3], demos=1).sample(3, np.random.default_rng(7)))
    torch.manual_seed(9)
    a1, c1, _ = nets()
    shared = RecurrentSAC(a1, c1, SacSettings(share_encoder=True))
    a2, c2 = build_actor(NET), build_critic(NET)
    a2.load_state_dict(a1.state_dict())
    c2.load_state_dict(c1.state_dict())
    a2.encoder = c2.encoder
    plain = RecurrentSAC(a2, c2, SacSettings(share_encoder=False))
    plain._actor_params = [p for p in a2.parameters() if all(p is not q for q in c2.encoder.parameters())]
    plain.actor_opt = torch.optim.Adam(plain._actor_params, lr=plain.s.lr)
    torch.manual_seed(11)
    i1 = shared.update(batch)
    torch.manual_seed(11)
    i2 = plain.update(batch)
    for k in ("critic_loss", "actor_loss"):
        assert i1[k] == pytest.approx(i2[k], rel=1e-5, abs=1e-6), k
    for p, q in zip(shared.actor.parameters(), plain.actor.parameters(), strict=True):
        torch.testing.assert_close(p, q, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("group", ["c4", "d4"])
@torch.no_grad()
def test_group_layer_norm_is_equivariant_and_per_field(group):
    G = get_group(group)
    norm = GroupLayerNorm(G, 3)
    norm.weight.copy_(torch.tensor([0.5, 2.0, -1.0]))
    norm.bias.copy_(torch.tensor([0.1, -0.3, 0.7]))
    x = torch.randn(4, 3 * G.order)
    y = norm(x)
    for g in G.elements:
        torch.testing.assert_close(norm(transform_regular(x, g, G)), transform_regular(y, g, G))
    # a per-channel affine would not be equivariant: the check above can fail
    w = torch.randn(3 * G.order)
    bad = torch.nn.functional.layer_norm(x, x.shape[-1:], w)
    g = G.elements[1]
    assert not torch.allclose(
        torch.nn.functional.layer_norm(transform_regular(x, g, G), x.shape[-1:], w),
        transform_regular(bad, g, G),
    )


@pytest.mark.parametrize("group", ["c4", "d4"])
@torch.no_grad()
def test_critic_with_layer_norm_keeps_q_invariant(group):
    net = dataclasses.replace(NET, group=group, critic_layer_norm=True)
    torch.manual_seed(1)
    critic = build_critic(net)
    assert any(isinstance(m, GroupLayerNorm) for m in critic.modules())
    for m in critic.modules():
        if isinstance(m, GroupLayerNorm):
            m.weight.uniform_(0.5, 1.5)
            m.bias.uniform_(-0.5, 0.5)
    gen = torch.Generator().manual_seed(2)
    images = torch.rand(2, 4, 2, SIZE, SIZE, generator=gen)
    prev = torch.rand(2, 4, 5, generator=gen) * 2 - 1
    actions = torch.rand(2, 4, 5, generator=gen) * 2 - 1
    q1, q2 = critic.q(critic.features(images, prev)[0], actions)
    G = get_group(group)
    for g in G.elements:
        feats_g, _ = critic.features(transform_images(images, g), transform_actions(prev, g))
        q1g, q2g = critic.q(feats_g, transform_actions(actions, g))
        torch.testing.assert_close(q1g, q1, atol=1e-4, rtol=1e-5)
        torch.testing.assert_close(q2g, q2, atol=1e-4, rtol=1e-5)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="bc_weight"):
        SacSettings(bc_weight=-1.0)
    with pytest.raises(ValueError, match="conservative_weight must be >= 0"):
        SacSettings(conservative_weight=-0.5)


@pytest.mark.parametrize("actor_lr", [None, 1e-5])
def test_the_actor_steps_at_its_own_rate_and_the_critic_at_lr(actor_lr):
    """Adam's first step moves each parameter with a gradient by its rate (the bias-corrected
    g / |g|), so the largest move of each network is its rate."""
    batch = to_batch(replay_with([5, 4], demos=1).sample(2, np.random.default_rng(1), trim=True))
    actor, critic, _ = nets()
    sac = RecurrentSAC(actor, critic, SacSettings(lr=1e-3, actor_lr=actor_lr))
    before = {
        k: [p.detach().clone() for p in m.parameters()]
        for k, m in (("actor", sac.actor), ("critic", sac.critic))
    }
    sac.update(batch)
    moved = {k: max(float((p.detach() - q).abs().max()) for p, q in zip(m.parameters(), before[k], strict=True))
             for k, m in (("actor", sac.actor), ("critic", sac.critic))}  # fmt: skip
    assert moved["critic"] == pytest.approx(1e-3, rel=1e-2)  # float32 rounding of the moves
    assert moved["actor"] == pytest.approx(1e-3 if actor_lr is None else actor_lr, rel=1e-2)
    with pytest.raises(ValueError, match="actor_lr"):
        SacSettings(actor_lr=0.0)


class ActionCritic(torch.nn.Module):
    """Twin Q = a . w (+ 0.5 on the second): values known for any action, features ignored."""

    def __init__(self, w: torch.Tensor) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(w.clone())

    def q(self, feats: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        v = actions @ self.w
        return v, v + 0.5


def test_the_conservative_gap_is_logsumexp_of_untried_actions_less_the_tried_ones_value():
    batch = to_batch(replay_with([4, 6], demos=1).sample(2, np.random.default_rng(3), trim=True))
    B, L, A = batch.actions.shape
    feats = torch.zeros(B, L + 1, 1)
    policy = torch.full((B, L, A), 0.25)
    flat = ActionCritic(torch.zeros(A))  # every action worth the same: nothing to push
    assert conservative_gap(flat, feats, batch, policy, 4).item() == pytest.approx(0.0, abs=1e-6)
    w = torch.tensor([0.0, 1.0, 0.0, -1.0, 0.0])
    torch.manual_seed(7)
    got = conservative_gap(ActionCritic(w), feats, batch, policy, 3)
    torch.manual_seed(7)  # the same uniform draws, by hand
    draws = [torch.rand_like(batch.actions) * 2 - 1 for _ in range(3)]
    values = torch.stack([x @ w for x in (*draws, policy)])  # (4, B, L); the twins differ by a constant
    per_step = torch.logsumexp(values, 0) - np.log(4) - batch.actions @ w
    m = batch.mask.float()
    torch.testing.assert_close(got, 2 * (per_step * m).sum() / m.sum())


def test_descending_the_conservative_gap_ranks_the_tried_action_above_the_others():
    batch = to_batch(replay_with([4, 6], demos=1).sample(2, np.random.default_rng(4), trim=True))
    B, L, A = batch.actions.shape
    feats, policy = torch.zeros(B, L + 1, 1), torch.zeros(B, L, A)
    critic = ActionCritic(torch.zeros(A))
    opt = torch.optim.SGD(critic.parameters(), lr=0.5)
    torch.manual_seed(0)
    for _ in range(20):
        opt.zero_grad()
        conservative_gap(critic, feats, batch, policy, 4).backward()
        opt.step()
    m = batch.mask.bool()
    tried = (batch.actions @ critic.w.detach())[m]
    untried = (torch.rand(64, B, L, A) * 2 - 1) @ critic.w.detach()
    assert float(tried.mean()) > float(untried[:, m].mean()) + 0.5


def test_the_calibrated_term_floors_the_policys_value_at_the_return_to_go():
    """Cal-QL: the policy action's Q enters the logsumexp as max(Q, floor); where the floor is above
    it, descending the term no longer lowers the policy action's value."""
    batch = to_batch(replay_with([4, 6], demos=1).sample(2, np.random.default_rng(3), trim=True))
    B, L, A = batch.actions.shape
    feats = torch.zeros(B, L + 1, 1)
    policy = torch.rand(B, L, A, generator=torch.Generator().manual_seed(1)) * 2 - 1
    critic = ActionCritic(torch.linspace(-0.5, 0.5, A))
    floor = torch.rand(B, L, generator=torch.Generator().manual_seed(2))
    torch.manual_seed(0)
    got = conservative_gap(critic, feats, batch, policy, 4, floor)
    torch.manual_seed(0)
    draws = [torch.rand_like(batch.actions) * 2 - 1 for _ in range(4)]
    want = 0.0
    for offset in (0.0, 0.5):  # the twin's two heads
        q = [x @ critic.w + offset for x in draws] + [torch.maximum(policy @ critic.w + offset, floor)]
        want = want + torch.logsumexp(torch.stack(q), 0) - math.log(5) - (batch.actions @ critic.w + offset)
    torch.testing.assert_close(got, masked_mean(want, batch.mask))
    # with the floor above every value, the policy's action no longer matters to the term
    other = policy.flip(0)
    for fl, same in ((torch.full((B, L), 10.0), True), (None, False)):
        grads = []
        for acts in (policy, other):
            critic.w.grad = None
            torch.manual_seed(0)
            conservative_gap(critic, feats, batch, acts, 4, fl).backward()
            grads.append(critic.w.grad.clone())
        assert torch.allclose(grads[0], grads[1]) == same
    with pytest.raises(ValueError, match="conservative_calibrated"):
        SacSettings(conservative_calibrated=True)


def test_the_conservative_term_is_reported_and_moves_the_critic_only_when_on():
    batch = to_batch(replay_with([4, 6], demos=1).sample(3, np.random.default_rng(9), trim=True))
    runs = {}
    for w in (0.0, 1.0):
        actor, critic, _ = nets()
        sac = RecurrentSAC(actor, critic, SacSettings(conservative_weight=w))
        torch.manual_seed(2)
        info = sac.update(batch)
        runs[w] = (info, [p.detach().clone() for p in sac.critic.parameters()])
    assert "conservative_gap" not in runs[0.0][0] and np.isfinite(runs[1.0][0]["conservative_gap"])
    assert runs[0.0][0]["critic_loss"] == pytest.approx(runs[1.0][0]["critic_loss"])  # the TD part alone
    assert any(not torch.equal(a, b) for a, b in zip(runs[0.0][1], runs[1.0][1], strict=True))


@torch.no_grad()
def test_actor_without_previous_action_ignores_it_and_stays_equivariant():
    net = dataclasses.replace(NET, actor_prev_action=False)
    torch.manual_seed(3)
    actor = build_actor(net)
    gen = torch.Generator().manual_seed(4)
    images = torch.rand(2, 5, 2, SIZE, SIZE, generator=gen)
    prev = torch.rand(2, 5, 5, generator=gen) * 2 - 1
    mean, log_std, _ = actor(images, prev)
    mean0, log_std0, _ = actor(images, torch.zeros_like(prev))
    torch.testing.assert_close(mean, mean0)
    torch.testing.assert_close(log_std, log_std0)
    G = get_group("c4")
    for g in G.elements:
        mean_g, _, _ = actor(transform_images(images, g), transform_actions(prev, g))
        torch.testing.assert_close(mean_g, transform_actions(mean, g), atol=1e-4, rtol=1e-5)
    # the default (Equi-RSAC) actor does read a_{t-1}: the check above can fail
    torch.manual_seed(3)
    with_prev = build_actor(NET)
    assert not torch.allclose(with_prev(images, prev)[0], with_prev(images, torch.zeros_like(prev))[0])


def test_a_state_critic_trains_from_the_batch_rows_and_the_actor_still_reads_images():
    net = dataclasses.replace(NET, critic_input="state", state_critic_hidden=(16,))
    actor, critic, _ = nets(net)
    with pytest.raises(ValueError, match="share_encoder"):
        RecurrentSAC(actor, critic, SacSettings(share_encoder=True))
    replay = SequenceReplay(1_000, image_size=SIZE, seq_len=SEQ_LEN, seed=0, state_dim=STATE_DIM)
    rng = np.random.default_rng(0)
    for k in range(6):
        ep = make_episode(3 + k, seed=k, demo=k < 2)
        replay.insert(ep, rng.standard_normal((ep.num_steps + 1, STATE_DIM)).astype(np.float32))
    batch = to_batch(replay.sample(4, np.random.default_rng(1)))
    assert batch.state is not None and batch.state.shape == (4, batch.images.shape[1], STATE_DIM)
    sac = RecurrentSAC(actor, critic, SacSettings())
    before_actor = [p.detach().clone() for p in actor.encoder.parameters()]
    before_critic = [p.detach().clone() for p in critic.parameters()]
    info = sac.update(batch)
    assert np.isfinite(info["critic_loss"]) and np.isfinite(info["actor_loss"])
    assert any(not torch.equal(a, p) for a, p in zip(before_actor, actor.encoder.parameters(), strict=True))
    assert all(not torch.equal(a, p) for a, p in zip(before_critic, critic.parameters(), strict=True))
    # the state rows drive the critic: other rows, other targets
    other = dataclasses.replace(batch, state=batch.state + 1.0)
    with torch.no_grad():
        a = torch.zeros_like(batch.actions)
        assert not torch.allclose(critic.q(batch.state[:, :-1], a)[0], critic.q(other.state[:, :-1], a)[0])
