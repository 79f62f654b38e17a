"""DreamerV2's actor and critic learned in imagination, for GASv2's nine discrete actions.

Both learn from lambda-returns of H-step rollouts of the frozen world model (the actor by REINFORCE
with the slow critic as baseline); neither loss reaches the world model.

Design notes: docs/architecture-notes.md, services/algorithms/gasv2/behaviour.py."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from services.algorithms.gasv2.chunks import ChunkBatch
from services.algorithms.gasv2.config import DreamerConfig
from services.algorithms.gasv2.rssm import (
    RSSM,
    RSSMState,
    detach_state,
    features,
    gumbel_argmax,
    select_states,
)
from services.algorithms.gasv2.world_model import WorldModel, mlp


class LatentActor(nn.Module):
    """Features (..., F) -> logits (..., num_actions) of a categorical policy."""

    def __init__(self, cfg: DreamerConfig) -> None:
        super().__init__()
        self.net = mlp(cfg.feat_dim, cfg.num_actions, cfg.mlp_layers, cfg.mlp_units, cfg.act)

    def forward(self, feat: Tensor) -> Tensor:
        return self.net(feat)


class LatentCritic(nn.Module):
    """Features (..., F) -> value (...)."""

    def __init__(self, cfg: DreamerConfig) -> None:
        super().__init__()
        self.net = mlp(cfg.feat_dim, 1, cfg.mlp_layers, cfg.mlp_units, cfg.act)

    def forward(self, feat: Tensor) -> Tensor:
        return self.net(feat).squeeze(-1)


# ------------------------------------------------------------------------------------------------
# returns and weights
# ------------------------------------------------------------------------------------------------


def lambda_returns(
    rewards: Tensor, values: Tensor, discounts: Tensor, bootstrap: Tensor, lam: float
) -> Tensor:
    """DreamerV2's ``lambda_return`` over time-major tensors (H, N):

        R_t = rewards_t + discounts_t [(1 - lam) values_{t+1} + lam R_{t+1}],  values_H = R_H = bootstrap (N)

    ``values[0]`` is not read. lam = 1: discounted Monte-Carlo return plus the discounted
    bootstrap; lam = 0: one-step TD targets rewards_t + discounts_t values_{t+1}."""
    if not rewards.shape == values.shape == discounts.shape or bootstrap.shape != rewards.shape[1:]:
        raise ValueError(
            f"rewards, values, discounts must be (H, N) and bootstrap (N), got {tuple(rewards.shape)}, "
            f"{tuple(values.shape)}, {tuple(discounts.shape)}, {tuple(bootstrap.shape)}"
        )
    next_values = torch.cat([values[1:], bootstrap[None]], 0)
    inputs = rewards + discounts * (1.0 - lam) * next_values
    factors = discounts * lam
    out, acc = [], bootstrap
    for t in range(rewards.shape[0] - 1, -1, -1):
        acc = inputs[t] + factors[t] * acc
        out.append(acc)
    return torch.stack(out[::-1])


def trajectory_weights(discounts: Tensor) -> Tensor:
    """w_t = discounts_0 ... discounts_{t-1} (w_0 = 1), (H, N): the (discounted) probability that
    z_t is reached without a terminal before it; ``discounts_t`` is d_{t+1}, z_{t+1}'s discount."""
    return torch.cumprod(torch.cat([torch.ones_like(discounts[:1]), discounts[:-1]], 0), 0)


# ------------------------------------------------------------------------------------------------
# imagination
# ------------------------------------------------------------------------------------------------


def start_states(posts: RSSMState, batch: ChunkBatch) -> RSSMState:
    """Detached posteriors (N, ...) of the observations the policy acts from: real, after the
    hybrid controller's handover, and not terminal."""
    acts = batch.mask.bool() & batch.handover.bool() & (batch.discounts > 0)
    return detach_state(select_states(posts, acts))


class Imagination(NamedTuple):
    feats: Tensor
    """(H+1, N, F) features of z_0 .. z_H."""
    actions: Tensor
    """(H, N) long: index of a_t, the action taken from z_t."""


@torch.no_grad()
def imagine(
    rssm: RSSM,
    actor: nn.Module,
    start: RSSMState,
    horizon: int,
    action_features: Tensor,
    generator: torch.Generator | None = None,
) -> Imagination:
    """Roll the prior out from ``start`` (N, ...) with the actor's sampled actions, mapped to the world
    model's action input through ``action_features`` (num_actions, action_dim)."""
    state = start
    feats, actions = [features(state)], []
    for _ in range(horizon):
        a = gumbel_argmax(actor(feats[-1]), generator)
        state = rssm.img_step(state, action_features[a], generator=generator)
        feats.append(features(state))
        actions.append(a)
    return Imagination(torch.stack(feats), torch.stack(actions))


class Targets(NamedTuple):
    rewards: Tensor
    """(H, N) r_{t+1}."""
    discounts: Tensor
    """(H, N) d_{t+1}."""
    values: Tensor
    """(H+1, N) slow critic v(z_t)."""
    returns: Tensor
    """(H, N) R_t."""
    weights: Tensor
    """(H, N) w_t."""


@torch.no_grad()
def imagination_targets(
    world_model: WorldModel, slow_critic: nn.Module, imag: Imagination, lam: float
) -> Targets:
    """Rewards, discounts, slow values, lambda-returns and weights of a rollout (no gradients)."""
    nxt = imag.feats[1:]
    rewards, discounts = world_model.reward(nxt), world_model.discount(nxt)
    values = slow_critic(imag.feats)
    returns = lambda_returns(rewards, values[:-1], discounts, values[-1], lam)
    return Targets(rewards, discounts, values, returns, trajectory_weights(discounts))


# ------------------------------------------------------------------------------------------------
# losses
# ------------------------------------------------------------------------------------------------


def actor_loss(
    actor: nn.Module,
    feats: Tensor,
    actions: Tensor,
    returns: Tensor,
    baseline: Tensor,
    weights: Tensor,
    entropy_scale: float,
) -> tuple[Tensor, dict[str, Tensor]]:
    """REINFORCE with a baseline and an entropy bonus, weighted: feats (H, N, F) of z_0..z_{H-1},
    actions/returns/baseline/weights (H, N). Only the actor receives gradients."""
    log_probs = actor(feats.detach()).log_softmax(-1)
    log_pi = log_probs.gather(-1, actions[..., None]).squeeze(-1)
    entropy = -(log_probs.exp() * log_probs).sum(-1)
    advantage = (returns - baseline).detach()
    objective = log_pi * advantage + entropy_scale * entropy
    loss = -(weights.detach() * objective).mean()
    return loss, {"actor_entropy": entropy.detach().mean(), "advantage": advantage.mean()}


def critic_loss(critic: nn.Module, feats: Tensor, returns: Tensor, weights: Tensor) -> Tensor:
    """Weighted regression (a unit Gaussian's NLL without its constant) of V(z_t) onto sg(R_t)."""
    values = critic(feats.detach())
    return (weights.detach() * 0.5 * (values - returns.detach()).pow(2)).mean()


@torch.no_grad()
def update_slow_target(slow: nn.Module, critic: nn.Module, fraction: float) -> None:
    """slow <- slow + fraction (critic - slow); an exact copy at fraction 1."""
    for s, c in zip(slow.parameters(), critic.parameters(), strict=True):
        if fraction >= 1.0:
            s.copy_(c)
        else:
            s.lerp_(c, fraction)


def behaviour_losses(
    world_model: WorldModel,
    actor: nn.Module,
    critic: nn.Module,
    slow_critic: nn.Module,
    start: RSSMState,
    cfg: DreamerConfig,
    action_features: Tensor,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
    """(actor loss, critic loss, detached metrics) of one imagination rollout from ``start`` (N >= 1)."""
    imag = imagine(world_model.rssm, actor, start, cfg.horizon, action_features, generator)
    tg = imagination_targets(world_model, slow_critic, imag, cfg.lam)
    feats = imag.feats[:-1]
    a_loss, a_metrics = actor_loss(
        actor, feats, imag.actions, tg.returns, tg.values[:-1], tg.weights, cfg.actor_entropy
    )
    c_loss = critic_loss(critic, feats, tg.returns, tg.weights)
    metrics = {
        "actor_loss": a_loss.detach(),
        "critic_loss": c_loss.detach(),
        **a_metrics,
        "imag_return": tg.returns[0].mean(),
        "imag_reward": tg.rewards.mean(),
        "imag_discount": tg.discounts.mean(),
        "imag_value": tg.values.mean(),
    }
    return a_loss, c_loss, metrics
