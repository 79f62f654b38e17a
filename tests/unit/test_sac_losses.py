"""Recurrent SAC losses tested as math: reference numbers, parameter isolation, masking, no mutation."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from torch import nn

from services.algorithms.sac.agent import RecurrentSAC
from services.algorithms.sac.config import SacSettings
from services.algorithms.sac.losses import (
    Batch,
    PolicyOutputs,
    actor_loss,
    alpha_loss,
    bounded_targets,
    critic_loss,
    critic_targets,
    masked_mean,
    n_step_targets,
    policy_outputs,
    returns_to_go,
    soft_update,
    tanh_gaussian_sample,
)
from tests.helpers.tiny_nets import TinyActor, TinyCritic, check_lerp_update

C, H, W = 2, 4, 4


def make_batch(lengths: list[int], L: int, seed: int = 0, pad: str = "zeros") -> Batch:
    """Episodes of the given lengths padded to L; ``pad='garbage'`` fills the padding with noise."""
    g = torch.Generator().manual_seed(seed)
    B = len(lengths)
    images = torch.rand(B, L + 1, C, H, W, generator=g)
    actions = torch.rand(B, L, 5, generator=g) * 2 - 1
    rewards = torch.randn(B, L, generator=g)
    terminated = torch.zeros(B, L)
    mask = torch.zeros(B, L)
    for b, n in enumerate(lengths):
        mask[b, :n] = 1.0
        terminated[b, n - 1] = float(b % 2 == 0)  # odd episodes end truncated (bootstrap)
    if pad == "zeros":
        obs_mask = torch.cat([torch.ones(B, 1), mask], 1)
        images = images * obs_mask[:, :, None, None, None]
        actions, rewards = actions * mask[..., None], rewards * mask
    else:
        g2 = torch.Generator().manual_seed(seed + 99)
        for b, n in enumerate(lengths):
            images[b, n + 1 :] = torch.rand(images[b, n + 1 :].shape, generator=g2) * 7
            actions[b, n:] = torch.rand(actions[b, n:].shape, generator=g2) * 2 - 1
            rewards[b, n:] = torch.randn(rewards[b, n:].shape, generator=g2) * 100
    return Batch(images, actions, rewards, terminated, mask)


def nets(seed: int = 0) -> tuple[TinyActor, TinyCritic]:
    torch.manual_seed(seed)
    return TinyActor(C * H * W), TinyCritic(C * H * W)


def noise_like(batch: Batch, seed: int) -> torch.Tensor:
    B, L1 = batch.images.shape[:2]
    return torch.randn(B, L1, 5, generator=torch.Generator().manual_seed(seed))


# --------------------------------------------------------------------------------------------
# reference numbers
# --------------------------------------------------------------------------------------------


def test_tanh_gaussian_log_prob_matches_torch_distributions():
    g = torch.Generator().manual_seed(3)
    mean = torch.randn(7, 5, generator=g) * 2
    log_std = torch.randn(7, 5, generator=g) * 0.5
    eps = torch.randn(7, 5, generator=g)
    a, logp = tanh_gaussian_sample(mean, log_std, eps)
    dist = torch.distributions.TransformedDistribution(
        torch.distributions.Normal(mean, log_std.exp()), [torch.distributions.TanhTransform()]
    )
    u = mean + log_std.exp() * eps
    assert torch.allclose(a, torch.tanh(u))
    # TanhTransform's log-det is itself the stable form; compare on the pre-tanh value to avoid atanh
    ref = (dist.base_dist.log_prob(u) - torch.distributions.TanhTransform().log_abs_det_jacobian(u, a)).sum(
        -1
    )
    assert torch.allclose(logp, ref, atol=1e-5)
    # and by hand for one element: log N(u; m, s) - log(1 - tanh(u)^2)
    m, s, e = float(mean[0, 0]), math.exp(float(log_std[0, 0])), float(eps[0, 0])
    uu = m + s * e
    by_hand = -0.5 * e * e - math.log(s) - 0.5 * math.log(2 * math.pi) - math.log(1 - math.tanh(uu) ** 2)
    single, lp = tanh_gaussian_sample(mean[:1, :1], log_std[:1, :1], eps[:1, :1])
    assert lp.item() == pytest.approx(by_hand, rel=1e-5)


class ConstCritic(nn.Module):
    """Q'_1, Q'_2 given per step (B, L): lets the target be computed by hand."""

    def __init__(self, q1: torch.Tensor, q2: torch.Tensor) -> None:
        super().__init__()
        self.q1v, self.q2v = q1, q2

    def features(self, images, prev_actions, state=None, obs_mask=None):
        B, T = images.shape[:2]
        return torch.arange(T, dtype=torch.float32).expand(B, T)[..., None], None

    def features_of(self, batch):
        return self.features(batch.images, batch.prev_actions)[0]

    def q(self, features, actions):
        idx = features[..., 0].long()
        return self.q1v.gather(1, idx), self.q2v.gather(1, idx)


def test_critic_targets_reference_numbers():
    # two steps; r = (1, 0.5); the second step terminates; gamma 0.9, alpha 0.1
    # Q' at observations 0, 1, 2: q1 = (9, 2, 3), q2 = (9, 1.5, 4); log pi at 0, 1, 2 = (0, -1, -2)
    # y_0 = 1 + 0.9 * (min(2, 1.5) - 0.1 * (-1)) = 1 + 0.9 * 1.6 = 2.44;  y_1 = 0.5 (terminal)
    target = ConstCritic(torch.tensor([[9.0, 2.0, 3.0]]), torch.tensor([[9.0, 1.5, 4.0]]))
    batch = Batch(
        images=torch.zeros(1, 3, C, H, W),
        actions=torch.zeros(1, 2, 5),
        rewards=torch.tensor([[1.0, 0.5]]),
        terminated=torch.tensor([[0.0, 1.0]]),
        mask=torch.ones(1, 2),
    )
    policy = PolicyOutputs(torch.zeros(1, 3, 5), torch.tensor([[0.0, -1.0, -2.0]]), None, None)
    y = critic_targets(target, batch, policy, alpha=0.1, gamma=0.9)
    assert y[0].tolist() == pytest.approx([2.44, 0.5])
    # a truncated last step bootstraps from the stored last observation: 0.5 + 0.9 * (3 + 0.2)
    trunc = Batch(batch.images, batch.actions, batch.rewards, torch.zeros(1, 2), batch.mask)
    assert critic_targets(target, trunc, policy, 0.1, 0.9)[0, 1].item() == pytest.approx(0.5 + 0.9 * 3.2)
    # without the entropy backup V(s') is min Q alone: y_0 = 1 + 0.9 * 1.5, y_1 (truncated) = 0.5 + 0.9 * 3
    bare = critic_targets(target, trunc, policy, 0.1, 0.9, backup_entropy=False)
    assert bare[0].tolist() == pytest.approx([1 + 0.9 * 1.5, 0.5 + 0.9 * 3.0])


def _n_step_loop(rewards, terminated, mask, soft_v, gamma, n):
    """Per-episode, per-step reference of the n-step target."""
    y = torch.zeros_like(rewards)
    for b in range(rewards.shape[0]):
        T = int(mask[b].sum())
        for t in range(T):
            m = min(n, T - t)
            g = sum(gamma**k * float(rewards[b, t + k]) for k in range(m))
            j = t + m - 1
            y[b, t] = g + gamma**m * (1.0 - float(terminated[b, j])) * float(soft_v[b, j])
    return y


def test_n_step_targets_reference_numbers():
    # r = (0, 0, 1), last step terminal; V(s_1..s_3) = (0.5, 0.7, 9); gamma 0.9, n = 2
    # y_0 = 0 + 0.9 * 0 + 0.81 * V(s_2) = 0.567; y_1 = 0 + 0.9 * 1 (window ends at the terminal) = 0.9
    # y_2 = 1 (terminal)
    r, term = torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.0, 0.0, 1.0]])
    v, mask = torch.tensor([[0.5, 0.7, 9.0]]), torch.ones(1, 3)
    assert n_step_targets(r, term, mask, v, 0.9, 2)[0].tolist() == pytest.approx([0.567, 0.9, 1.0])
    # truncated instead: the last windows bootstrap from the stored last observation, V(s_3) = 9
    y = n_step_targets(r, torch.zeros(1, 3), mask, v, 0.9, 2)
    assert y[0].tolist() == pytest.approx([0.567, 0.9 + 0.81 * 9.0, 1.0 + 0.9 * 9.0])


@pytest.mark.parametrize("n", [1, 2, 3, 7])
def test_n_step_targets_equal_a_loop_over_padded_episodes(n):
    g = torch.Generator().manual_seed(n)
    B, L = 5, 9
    lengths = torch.tensor([9, 1, 4, 6, 2])
    mask = (torch.arange(L)[None] < lengths[:, None]).float()
    rewards = torch.rand(B, L, generator=g) * mask
    terminated = torch.zeros(B, L)
    terminated[0, 8] = terminated[2, 3] = 1.0  # episodes 1, 3, 4 truncated
    soft_v = torch.randn(B, L, generator=g)
    y = n_step_targets(rewards, terminated, mask, soft_v, 0.9, n)
    ref = _n_step_loop(rewards, terminated, mask, soft_v, 0.9, n)
    assert torch.allclose(y * mask, ref, atol=1e-6)
    if n == 1:  # the one-step target exactly
        assert torch.equal(y, rewards + 0.9 * (1 - terminated) * soft_v)


def success_at_step_3() -> Batch:
    """One three-step episode whose only reward (1) ends it."""
    return Batch(
        images=torch.zeros(1, 4, C, H, W),
        actions=torch.zeros(1, 3, 5),
        rewards=torch.tensor([[0.0, 0.0, 1.0]]),
        terminated=torch.tensor([[0.0, 0.0, 1.0]]),
        mask=torch.ones(1, 3),
    )


def test_n_step_setting_reaches_the_critic_targets():
    # three steps, reward only at the end: with n = 3 the first step sees it, with n = 1 it does not
    target = ConstCritic(torch.zeros(1, 4), torch.zeros(1, 4))
    batch = success_at_step_3()
    policy = PolicyOutputs(torch.zeros(1, 4, 5), torch.zeros(1, 4), None, None)
    assert critic_targets(target, batch, policy, 0.1, 0.5, n_step=1)[0, 0].item() == 0.0
    assert critic_targets(target, batch, policy, 0.1, 0.5, n_step=3)[0, 0].item() == pytest.approx(0.25)


def test_returns_to_go_reference_numbers_and_padding():
    # r = (0, 1, 0.5) then padding; gamma 0.5: G = (0.5 + 0.125, 1 + 0.25, 0.5, 0)
    r = torch.tensor([[0.0, 1.0, 0.5, 7.0]])  # the padded step's reward must not count
    mask = torch.tensor([[1.0, 1.0, 1.0, 0.0]])
    assert returns_to_go(r, mask, 0.5)[0].tolist() == pytest.approx([0.625, 1.25, 0.5, 0.0])


def test_return_bound_raises_only_targets_below_the_observed_return():
    batch = success_at_step_3()
    y = torch.tensor([[0.1, 0.95, 1.0]])  # G = (0.81, 0.9, 1): the first is raised, the second kept
    assert bounded_targets(y, batch, 0.9)[0].tolist() == pytest.approx([0.81, 0.95, 1.0])
    # and it is wired into the update: same seed, same batch, only the setting differs
    losses = []
    for bound in (False, True):
        torch.manual_seed(0)
        sac = RecurrentSAC(TinyActor(C * H * W), TinyCritic(C * H * W), SacSettings(return_bound=bound))
        losses.append(sac.update(batch)["target_q"])
    assert losses[1] > losses[0]


def test_backup_entropy_setting_reaches_the_update():
    # same seed, same batch: a fresh policy's entropy bonus (-alpha log pi > 0 at its wide start)
    # raises the targets with the backup and is absent without it
    targets = []
    for backup in (True, False):
        torch.manual_seed(0)
        settings = SacSettings(backup_entropy=backup)
        sac = RecurrentSAC(TinyActor(C * H * W), TinyCritic(C * H * W), settings)
        targets.append(sac.update(success_at_step_3())["target_q"])
    assert targets[0] > targets[1]


def test_alpha_loss_pushes_toward_target_entropy():
    log_alpha = torch.tensor(0.0, requires_grad=True)
    mask = torch.ones(1, 3)
    # entropy above target (log pi = -10 < 5): d/dlog_alpha = -(logp + target) = -(-10 - 5) > 0 ... alpha falls
    (g_high,) = torch.autograd.grad(
        alpha_loss(log_alpha, torch.full((1, 3), -10.0), mask, -5.0, "log_alpha"), log_alpha
    )
    (g_low,) = torch.autograd.grad(
        alpha_loss(log_alpha, torch.full((1, 3), 10.0), mask, -5.0, "log_alpha"), log_alpha
    )
    assert g_high.item() == pytest.approx(15.0) and g_low.item() == pytest.approx(-5.0)


@pytest.mark.parametrize("log_alpha_value", [math.log(0.1), math.log(3e-4)])
def test_alpha_form_scales_the_gradient_by_alpha(log_alpha_value):
    # the public code's form: the same sign as the log-alpha form, the gradient times alpha, so
    # under Adam alpha falls more slowly as it gets small
    mask = torch.ones(2, 4)
    log_probs = torch.linspace(-9.0, -1.0, 8).reshape(2, 4)
    grads = {}
    for form in ("log_alpha", "alpha"):
        log_alpha = torch.tensor(log_alpha_value, requires_grad=True)
        (grads[form],) = torch.autograd.grad(alpha_loss(log_alpha, log_probs, mask, -5.0, form), log_alpha)
    assert grads["log_alpha"].item() == pytest.approx(10.0)  # -(mean log pi + target) = -(-5 - 5)
    assert grads["alpha"].item() == pytest.approx(10.0 * math.exp(log_alpha_value))


def test_alpha_loss_form_is_checked():
    with pytest.raises(ValueError, match="alpha_loss must be one of"):
        SacSettings(alpha_loss="exp")


def test_soft_update_is_a_lerp():
    check_lerp_update(soft_update, 0.25, seed=0)


# --------------------------------------------------------------------------------------------
# isolation, masking, purity
# --------------------------------------------------------------------------------------------


def test_each_loss_has_gradients_only_for_its_own_parameters():
    actor, critic = nets()
    batch = make_batch([3, 2], L=3)
    policy = policy_outputs(actor, batch, noise_like(batch, 1))
    y = critic_targets(copy.deepcopy(critic), batch, policy, 0.1, 0.9)
    q_loss, feats, _ = critic_loss(critic, batch, y)
    grads = torch.autograd.grad(q_loss, list(actor.parameters()), allow_unused=True)
    assert all(g is None for g in grads), "critic loss reaches the actor"
    pi_loss = actor_loss(critic, feats, batch, policy, 0.1)
    g_actor = torch.autograd.grad(pi_loss, list(actor.parameters()), retain_graph=True, allow_unused=True)
    assert any(g is not None and g.abs().sum() > 0 for g in g_actor)
    g_trunk = torch.autograd.grad(pi_loss, list(critic.trunk.parameters()), allow_unused=True)
    assert all(g is None for g in g_trunk), "actor loss reaches the critic's encoder/LSTM"
    log_alpha = torch.tensor(-1.0, requires_grad=True)
    for form in ("alpha", "log_alpha"):
        a_loss = alpha_loss(log_alpha, policy.log_probs[:, :-1], batch.mask, -5.0, form)
        assert all(
            g is None for g in torch.autograd.grad(a_loss, list(actor.parameters()), allow_unused=True)
        )


@pytest.mark.parametrize("frozen", ["actor", "critic"])
def test_update_moves_only_the_parameters_of_each_loss(frozen):
    actor, critic = nets()
    sac = RecurrentSAC(actor, critic, SacSettings(lr=1e-2))
    getattr(sac, f"{frozen}_opt").param_groups[0]["lr"] = 0.0
    a0, c0, t0 = (copy.deepcopy(m.state_dict()) for m in (actor, critic, sac.critic_target))
    alpha0 = sac.log_alpha.item()
    sac.update(make_batch([3, 2, 3], L=3, seed=4))
    changed = {
        name: any(not torch.equal(v, before[k]) for k, v in m.state_dict().items())
        for name, m, before in (("actor", actor, a0), ("critic", critic, c0))
    }
    assert changed == {"actor": frozen != "actor", "critic": frozen != "critic"}
    assert sac.log_alpha.item() != alpha0
    for k, v in sac.critic_target.state_dict().items():
        assert torch.allclose(v, 0.995 * t0[k] + 0.005 * critic.state_dict()[k], atol=1e-7)


def reference_update(sac: RecurrentSAC, batch: Batch) -> None:
    """The same update written the textbook way (zero_grad / backward / step per loss)."""
    alpha = sac.log_alpha.detach().exp()
    policy = policy_outputs(sac.actor, batch)
    with torch.no_grad():
        tf, _ = sac.critic_target.features(batch.images, batch.prev_actions)
        tq1, tq2 = sac.critic_target.q(tf[:, 1:], policy.actions[:, 1:])
        y = batch.rewards + sac.s.gamma * (1 - batch.terminated) * (
            torch.min(tq1, tq2) - alpha * policy.log_probs[:, 1:]
        )
    feats, _ = sac.critic.features(batch.images, batch.prev_actions)
    q1, q2 = sac.critic.q(feats[:, :-1], batch.actions)
    n = batch.mask.sum()
    q_loss = (((q1 - y) ** 2 + (q2 - y) ** 2) * batch.mask).sum() / n
    sac.critic_opt.zero_grad()
    q_loss.backward()
    sac.critic_opt.step()
    p1, p2 = sac.critic.q(feats[:, :-1].detach(), policy.actions[:, :-1])
    pi_loss = ((alpha * policy.log_probs[:, :-1] - torch.min(p1, p2)) * batch.mask).sum() / n
    sac.actor_opt.zero_grad()
    pi_loss.backward()
    sac.actor_opt.step()
    a_loss = -(sac.log_alpha * ((policy.log_probs[:, :-1].detach() - 5.0) * batch.mask).sum() / n)
    sac.alpha_opt.zero_grad()
    a_loss.backward()
    sac.alpha_opt.step()
    with torch.no_grad():
        for t, s in zip(sac.critic_target.parameters(), sac.critic.parameters(), strict=True):
            t.mul_(1 - sac.s.tau).add_(sac.s.tau * s)


def test_update_equals_the_textbook_update_over_several_steps():
    ours = RecurrentSAC(*nets(5), SacSettings(lr=3e-3))
    ref = RecurrentSAC(*nets(5), SacSettings(lr=3e-3))
    for k in range(3):
        batch = make_batch([4, 2, 3], L=4, seed=10 + k)
        torch.manual_seed(100 + k)
        ours.update(batch)
        torch.manual_seed(100 + k)
        reference_update(ref, batch)
    for m_ours, m_ref in (
        (ours.actor, ref.actor),
        (ours.critic, ref.critic),
        (ours.critic_target, ref.critic_target),
    ):
        for (k, a), b in zip(m_ours.state_dict().items(), m_ref.state_dict().values(), strict=True):
            assert torch.allclose(a, b, atol=1e-6), k
    assert ours.log_alpha.item() == pytest.approx(ref.log_alpha.item(), abs=1e-7)


def test_update_does_not_mutate_its_inputs():
    sac = RecurrentSAC(*nets(), SacSettings())
    batch = make_batch([3, 1], L=3, seed=2)
    before = {k: v.clone() for k, v in batch.__dict__.items() if v is not None}
    sac.update(batch)
    for k, v in batch.__dict__.items():
        assert v is None or torch.equal(v, before[k]), k


def losses(actor, critic, target, batch, noise):
    policy = policy_outputs(actor, batch, noise)
    y = critic_targets(target, batch, policy, 0.1, 0.9)
    q_loss, feats, _ = critic_loss(critic, batch, y)
    return q_loss, actor_loss(critic, feats, batch, policy, 0.1), y


def test_padding_has_no_effect_on_losses():
    actor, critic = nets(7)
    target = copy.deepcopy(critic)
    lengths = [4, 1, 3, 2]
    clean, dirty = make_batch(lengths, L=4, seed=3), make_batch(lengths, L=4, seed=3, pad="garbage")
    noise = noise_like(clean, 8)
    q_c, pi_c, _ = losses(actor, critic, target, clean, noise)
    q_d, pi_d, _ = losses(actor, critic, target, dirty, noise)
    assert q_c.item() == pytest.approx(q_d.item(), rel=1e-6)
    assert pi_c.item() == pytest.approx(pi_d.item(), rel=1e-6)
    # and the garbage really reached the networks (the masks, not luck, remove it)
    assert not torch.equal(clean.rewards, dirty.rewards)


def test_vectorised_losses_equal_a_per_episode_loop():
    actor, critic = nets(11)
    target = copy.deepcopy(critic)
    lengths = [4, 1, 3, 2]
    batch = make_batch(lengths, L=4, seed=6, pad="garbage")
    noise = noise_like(batch, 9)
    q_all, pi_all, y_all = losses(actor, critic, target, batch, noise)
    q_sum = pi_sum = 0.0
    for b, n in enumerate(lengths):
        one = Batch(
            batch.images[b : b + 1, : n + 1],
            batch.actions[b : b + 1, :n],
            batch.rewards[b : b + 1, :n],
            batch.terminated[b : b + 1, :n],
            torch.ones(1, n),
        )
        q_b, pi_b, y_b = losses(actor, critic, target, one, noise[b : b + 1, : n + 1])
        assert torch.allclose(y_b[0], y_all[b, :n], atol=1e-6)
        q_sum, pi_sum = q_sum + q_b.item() * n, pi_sum + pi_b.item() * n
    total = sum(lengths)
    assert q_all.item() == pytest.approx(q_sum / total, rel=1e-5)
    assert pi_all.item() == pytest.approx(pi_sum / total, rel=1e-5)


def test_masked_mean_ignores_masked_entries_and_empty_masks():
    x = torch.tensor([[1.0, 2.0, 1000.0]])
    assert masked_mean(x, torch.tensor([[1.0, 1.0, 0.0]])).item() == pytest.approx(1.5)
    assert masked_mean(x, torch.zeros(1, 3)).item() == 0.0


def test_state_dict_round_trip_continues_identically():
    a = RecurrentSAC(*nets(3), SacSettings(lr=1e-3))
    batch = make_batch([3, 3], L=3, seed=1)
    torch.manual_seed(0)
    a.update(batch)
    b = RecurrentSAC(*nets(99), SacSettings(lr=1e-3))
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    torch.manual_seed(1)
    ma = a.update(batch)
    torch.manual_seed(1)
    mb = b.update(batch)
    assert ma == mb and b.updates == a.updates == 2


def test_settings_reject_bad_values():
    with pytest.raises(ValueError, match="gamma"):
        SacSettings(gamma=1.5)
    with pytest.raises(ValueError, match="tau"):
        SacSettings(tau=0.0)
    with pytest.raises(ValueError, match="n_step"):
        SacSettings(n_step=0)
