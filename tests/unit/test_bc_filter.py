"""The BC term's options as math: the Q filter keeps exactly the demonstration transitions the
critic rates above the policy's mean action, the decaying weight, the critique's rank gap, and the
update's reported gradient norms."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from services.algorithms.batch import to_batch
from services.algorithms.sac.agent import RecurrentSAC
from services.algorithms.sac.config import SacSettings
from services.algorithms.sac.losses import action_values, bc_loss, critique_demos
from tests.unit.test_sac_options import NET, nets, replay_with

pytestmark = pytest.mark.unit


class LinearQ(torch.nn.Module):
    """Q(f, a) = w . a (features ignored): a critic whose ranking is known."""

    def __init__(self, w: list[float]) -> None:
        super().__init__()
        self.w = torch.tensor(w)

    def q(self, feats: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        v = actions @ self.w
        return v, v + 1.0  # min is the first


def demo_batch():
    return to_batch(replay_with([4, 5, 3], demos=2).sample(3, np.random.default_rng(0), demo_fraction=0.5))


def test_filter_keeps_where_the_demo_action_scores_higher():
    batch = demo_batch()
    B, L, _ = batch.actions.shape
    critic = LinearQ([0.0, 1.0, 0.0, 0.0, 0.0])  # Q = dx
    mean = torch.zeros(B, L + 1, 5)  # tanh(0) = 0: the policy's dx is 0
    feats = torch.zeros(B, L + 1, 3)
    c = critique_demos(critic, feats, batch, action_values(critic, feats, batch, mean))
    expect = (batch.actions[..., 1] > 0).float()
    torch.testing.assert_close(c.keep, expect)
    demo = batch.mask * batch.demo[:, None]
    torch.testing.assert_close(c.accept, (expect * demo).sum() / demo.sum())
    # a quarter turn sends (dx, dy) to (-dy, dx): the gap is the mean of dx + dy on demo steps
    gap = ((batch.actions[..., 1] + batch.actions[..., 2]) * demo).sum() / demo.sum()
    torch.testing.assert_close(c.rank_gap, gap)
    # reversing the move negates dx: the gap is twice the mean dx on demo steps
    torch.testing.assert_close(c.reverse_gap, 2 * (batch.actions[..., 1] * demo).sum() / demo.sum())


def test_the_reverse_gap_ranks_a_vertical_move_that_the_quarter_turn_cannot():
    batch = demo_batch()
    B, L, _ = batch.actions.shape
    critic = LinearQ([0.0, 0.0, 0.0, -1.0, 0.0])  # Q = -dz: a critic that prefers descending
    feats = torch.zeros(B, L + 1, 3)
    descents = batch.actions.clone()
    descents[..., 1:3] = 0.0
    descents[..., 3] = -0.5
    down = dataclasses.replace(batch, actions=descents)
    c = critique_demos(critic, feats, down, action_values(critic, feats, down, torch.zeros(B, L + 1, 5)))
    assert float(c.rank_gap) == 0.0  # a quarter turn leaves a vertical move as it is
    torch.testing.assert_close(c.reverse_gap, torch.tensor(1.0))  # -(-0.5) - (-(0.5))


def test_filtered_bc_counts_only_kept_transitions_but_averages_over_all_demo_steps():
    batch = demo_batch()
    B, L, _ = batch.actions.shape
    mean = torch.full((B, L + 1, 5), 0.3)
    keep = torch.zeros(B, L)
    assert float(bc_loss(mean, batch, keep)) == 0.0
    full = bc_loss(mean, batch)
    torch.testing.assert_close(bc_loss(mean, batch, torch.ones(B, L)), full)
    half = torch.zeros(B, L)
    half[:, ::2] = 1.0
    assert 0.0 < float(bc_loss(mean, batch, half)) < float(full)


def test_bc_weight_decays_linearly_to_zero():
    s = SacSettings(bc_weight=2.0, bc_decay_updates=100)
    assert [s.bc_weight_at(u) for u in (0, 50, 100, 500)] == [2.0, 1.0, 0.0, 0.0]
    assert SacSettings(bc_weight=2.0).bc_weight_at(10**6) == 2.0
    with pytest.raises(ValueError, match="bc_decay_updates"):
        SacSettings(bc_decay_updates=-1)


@pytest.mark.parametrize("share", [False, True])
def test_update_reports_both_actor_gradient_norms_and_the_filter(share: bool):
    actor, critic, _ = nets(NET)
    sac = RecurrentSAC(actor, critic, SacSettings(bc_weight=1.0, bc_filter=True, share_encoder=share))
    info = sac.update(demo_batch())
    for k in (
        "bc_grad_norm",
        "actor_grad_norm",
        "bc_accept",
        "q_rank_gap",
        "q_reverse_gap",
        "q_demo_minus_pi",
        "bc_loss",
    ):
        assert np.isfinite(info[k]), k
    assert info["bc_grad_norm"] > 0 and info["actor_grad_norm"] > 0
    assert 0.0 <= info["bc_accept"] <= 1.0
    off = RecurrentSAC(*nets(NET)[:2], SacSettings()).update(demo_batch())
    assert "bc_loss" not in off and "bc_grad_norm" not in off
    assert np.isfinite(off["q_rank_gap"])  # the critique is reported without BC too


def test_a_filter_that_keeps_nothing_leaves_the_actor_to_the_sac_term():
    # with every demo transition filtered out, the update equals one with the BC weight at 0
    batch = demo_batch()
    torch.manual_seed(3)
    a1, c1, _ = nets(NET, seed=1)
    a0, c0, _ = nets(NET, seed=1)
    s_filtered = RecurrentSAC(a1, c1, SacSettings(bc_weight=1.0, bc_filter=True))
    s_off = RecurrentSAC(a0, c0, SacSettings(bc_weight=0.0))
    never = LinearQ([0.0] * 5)  # Q(a_demo) == Q(pi): never strictly above, nothing kept
    s_filtered.critic_target.q = never.q  # type: ignore[method-assign]
    s_off.critic_target.q = never.q  # type: ignore[method-assign]
    torch.manual_seed(7)
    s_filtered.update(batch)
    torch.manual_seed(7)
    s_off.update(batch)
    for p, q in zip(a1.parameters(), a0.parameters(), strict=True):
        torch.testing.assert_close(p, q)


def _params(m: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in m.parameters()]


def test_critic_warmup_holds_actor_and_temperature_then_releases_them():
    batch = demo_batch()
    actor, critic, _ = nets(NET, seed=2)
    sac = RecurrentSAC(actor, critic, SacSettings(actor_warmup_updates=2))
    a0, c0, alpha0 = _params(actor), _params(critic), float(sac.alpha)
    for _ in range(2):
        info = sac.update(batch)
    assert info["actor_grad_norm"] > 0  # measured, not applied
    assert all(torch.equal(p, q) for p, q in zip(_params(actor), a0, strict=True))
    assert float(sac.alpha) == alpha0
    assert not all(torch.equal(p, q) for p, q in zip(_params(critic), c0, strict=True))
    sac.update(batch)  # the third update moves both
    assert not all(torch.equal(p, q) for p, q in zip(_params(actor), a0, strict=True))
    assert float(sac.alpha) != alpha0
    with pytest.raises(ValueError, match="actor_warmup_updates"):
        SacSettings(actor_warmup_updates=-1)


def test_critic_warmup_keeps_the_bc_term_on_the_actor():
    batch = demo_batch()
    actor, critic, _ = nets(NET, seed=2)
    a0 = _params(actor)
    RecurrentSAC(actor, critic, SacSettings(bc_weight=1.0, actor_warmup_updates=5)).update(batch)
    assert not all(torch.equal(p, q) for p, q in zip(_params(actor), a0, strict=True))
