"""The crr actor objective as math: the tanh-Gaussian log-density of given actions, the binary and
exponential weights from a critic whose ranking is known, and an update that moves the policy
towards the kept actions only."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from services.algorithms.sac.agent import RecurrentSAC
from services.algorithms.sac.config import SacSettings
from services.algorithms.sac.losses import (
    CRR_MAX_WEIGHT,
    PolicyOutputs,
    action_values,
    crr_loss,
    crr_weights,
    tanh_gaussian_log_prob,
    tanh_gaussian_sample,
)
from tests.unit.test_bc_filter import LinearQ, demo_batch
from tests.unit.test_sac_options import NET, nets

pytestmark = pytest.mark.unit


def test_log_prob_of_given_actions_matches_the_sampler():
    g = torch.Generator().manual_seed(0)
    mean, log_std = torch.randn(4, 3, 5, generator=g), torch.randn(4, 3, 5, generator=g) * 0.3
    a, lp = tanh_gaussian_sample(mean, log_std, generator=g)
    torch.testing.assert_close(
        tanh_gaussian_log_prob(mean, log_std, a, bound=1.0 - 1e-7), lp, atol=1e-4, rtol=1e-4
    )


def test_log_prob_at_the_box_edge_is_finite():
    lp = tanh_gaussian_log_prob(torch.zeros(2, 5), torch.zeros(2, 5), torch.ones(2, 5))
    assert torch.isfinite(lp).all()


def test_weights_binary_and_exponential_follow_the_advantage():
    batch = demo_batch()
    B, L, _ = batch.actions.shape
    critic = LinearQ([0.0, 1.0, 0.0, 0.0, 0.0])  # Q = dx; the policy's dx is tanh(0) = 0
    mean, feats = torch.zeros(B, L + 1, 5), torch.zeros(B, L + 1, 3)
    adv = batch.actions[..., 1]
    values = action_values(critic, feats, batch, mean)
    torch.testing.assert_close(crr_weights(values, 0.0), (adv > 0).float())
    torch.testing.assert_close(crr_weights(values, 0.5), torch.exp(adv / 0.5))
    big = LinearQ([0.0, 100.0, 0.0, 0.0, 0.0])
    assert float(crr_weights(action_values(big, feats, batch, mean), 0.5).max()) == CRR_MAX_WEIGHT


def test_crr_loss_counts_only_weighted_actions():
    batch = demo_batch()
    B, L, _ = batch.actions.shape
    mean = torch.zeros(B, L + 1, 5, requires_grad=True)
    policy = PolicyOutputs(torch.zeros(B, L + 1, 5), torch.zeros(B, L + 1), mean, torch.zeros(B, L + 1, 5))
    assert float(crr_loss(policy, batch, torch.zeros(B, L)).detach()) == 0.0
    keep = torch.zeros(B, L)
    keep[0, 0] = 1.0
    crr_loss(policy, batch, keep).backward()
    grad = mean.grad.abs().sum(-1)
    assert grad[0, 0] > 0 and float(grad.sum() - grad[0, 0]) == 0.0
    # the gradient step moves the mean towards the kept action (in pre-tanh space)
    target = torch.atanh(batch.actions[0, 0].clamp(-0.999, 0.999))
    assert float((-mean.grad[0, 0] * target).sum()) > 0


def test_a_crr_update_moves_the_actor_and_leaves_the_temperature():
    actor, critic, _ = nets(NET, seed=4)
    sac = RecurrentSAC(actor, critic, SacSettings(actor_objective="crr"))
    before = [p.detach().clone() for p in actor.parameters()]
    info = sac.update(demo_batch())
    assert 0.0 <= info["crr_keep"] <= 1.0 and np.isfinite(info["actor_loss"])
    assert float(sac.alpha) == pytest.approx(math.exp(math.log(SacSettings().init_alpha)))
    assert not all(torch.equal(p, q) for p, q in zip(actor.parameters(), before, strict=True))
    with pytest.raises(ValueError, match="actor_objective"):
        SacSettings(actor_objective="awr")
    with pytest.raises(ValueError, match="crr_beta"):
        SacSettings(crr_beta=-1.0)
