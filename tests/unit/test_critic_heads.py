"""More than two Q heads on the critic (``net.critic_heads``) and the target's min over a drawn subset
of them (``sac.target_heads``: REDQ's rule; all of them: the twin's and SAC-N's)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from services.algorithms.batch import to_batch
from services.algorithms.groups import get_group, transform_actions, transform_images
from services.algorithms.networks import NetConfig, build_critic
from services.algorithms.sac.agent import RecurrentSAC
from services.algorithms.sac.algorithm import SacConfig
from services.algorithms.sac.config import SacSettings
from services.algorithms.sac.losses import actor_loss, critic_loss, masked_mean, policy_outputs, subset_min_q
from tests.unit.test_sac_options import NET, SIZE, nets, replay_with

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("group", ["c4", "d4"])
@torch.no_grad()
def test_every_head_rates_an_action_invariantly_and_the_heads_differ(group):
    critic = build_critic(dataclasses.replace(NET, group=group, critic_heads=4))
    gen = torch.Generator().manual_seed(2)
    images = torch.rand(2, 4, 2, SIZE, SIZE, generator=gen)
    prev = torch.rand(2, 4, 5, generator=gen) * 2 - 1
    actions = torch.rand(2, 4, 5, generator=gen) * 2 - 1
    qs = critic.q(critic.features(images, prev)[0], actions)
    assert len(qs) == 4
    assert all(not torch.allclose(qs[0], q) for q in qs[1:])  # each head its own initial draw
    for g in get_group(group).elements:
        qs_g = critic.q(critic.features(transform_images(images, g), transform_actions(prev, g))[0],
                        transform_actions(actions, g))  # fmt: skip
        for q, q_g in zip(qs, qs_g, strict=True):
            torch.testing.assert_close(q_g, q, atol=1e-4, rtol=1e-5)


@pytest.mark.parametrize("critic_input", ["image", "state"])
def test_a_twin_keeps_its_parameter_names_and_first_draws_when_heads_are_added(critic_input):
    """The heads past the second are built last, so the twin's checkpoints load and a run with more
    heads starts from the twin's trunk and first two heads."""
    net = dataclasses.replace(NET, critic_input=critic_input, state_critic_hidden=(16,))
    torch.manual_seed(5)
    twin = build_critic(net).state_dict()
    torch.manual_seed(5)
    five = build_critic(dataclasses.replace(net, critic_heads=5)).state_dict()
    assert not any(k.startswith("more_q") for k in twin)
    assert {k.split(".")[1] for k in five if k.startswith("more_q")} == {"0", "1", "2"}
    for k, v in twin.items():
        torch.testing.assert_close(five[k], v, rtol=0, atol=0)


def test_the_target_min_is_over_a_drawn_subset_or_over_every_head():
    qs = [torch.full((2, 3), v) for v in (3.0, 1.0, 4.0, 2.0, 5.0)]
    state = torch.random.get_rng_state()
    assert torch.equal(subset_min_q(qs, None), torch.full((2, 3), 1.0))
    assert torch.equal(subset_min_q(qs, 5), torch.full((2, 3), 1.0))
    assert torch.equal(torch.random.get_rng_state(), state)  # no draw where all heads count: a twin's bits
    torch.manual_seed(0)
    singles = [subset_min_q(qs, 1) for _ in range(200)]
    pairs = [subset_min_q(qs, 2) for _ in range(2000)]
    for drawn in singles + pairs:  # one draw for the whole batch
        assert torch.equal(drawn, torch.full_like(drawn, float(drawn[0, 0])))
    assert {float(d[0, 0]) for d in singles} == {1.0, 2.0, 3.0, 4.0, 5.0}
    # the min of 2 of 5 values drawn without replacement is 1 with probability 4/10, 5 never
    lows = np.array([float(d[0, 0]) for d in pairs])
    assert 5.0 not in lows and set(lows) == {1.0, 2.0, 3.0, 4.0}
    assert np.mean(lows == 1.0) == pytest.approx(0.4, abs=0.04)
    assert np.mean(lows == 4.0) == pytest.approx(0.1, abs=0.03)


def test_every_head_is_regressed_onto_the_targets_and_the_loss_is_their_sum():
    batch = to_batch(replay_with([5, 4, 6], demos=1).sample(3, np.random.default_rng(1), trim=True))
    _, critic, _ = nets(dataclasses.replace(NET, critic_heads=3))
    targets = torch.rand(batch.actions.shape[:2], generator=torch.Generator().manual_seed(0))
    loss, feats, info = critic_loss(critic, batch, targets)
    qs = critic.q(feats[:, :-1], batch.actions)
    expected = sum(masked_mean((q - targets).pow(2), batch.mask) for q in qs)
    torch.testing.assert_close(loss, expected)
    torch.testing.assert_close(info["q2"], masked_mean(qs[1].detach(), batch.mask))
    loss.backward()
    for head in (critic.q1, critic.q2, *critic.more_q):
        assert all(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in head.parameters())


class HeadsCritic(torch.nn.Module):
    """Q_i = a . w + offset_i: every head's value known for any action, features ignored."""

    def __init__(self, offsets: tuple[float, ...]) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(torch.linspace(-1, 1, 5))
        self.offsets = offsets

    def q(self, feats: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(actions @ self.w + o for o in self.offsets)


def test_the_actor_climbs_the_lowest_head():
    batch = to_batch(replay_with([4, 6], demos=1).sample(2, np.random.default_rng(3), trim=True))
    actor = nets()[0]
    policy = policy_outputs(actor, batch)
    feats = torch.zeros(*batch.images.shape[:2], 1)
    loss = actor_loss(HeadsCritic((0.3, -0.2, 0.7)), feats, batch, policy, 0.1)
    q = policy.actions[:, :-1] @ torch.linspace(-1, 1, 5) - 0.2
    torch.testing.assert_close(loss, masked_mean(0.1 * policy.log_probs[:, :-1] - q, batch.mask))


def test_an_update_with_more_heads_moves_all_of_them():
    batch = to_batch(replay_with([5, 4], demos=1).sample(2, np.random.default_rng(1), trim=True))
    actor, critic, _ = nets(dataclasses.replace(NET, critic_heads=4))
    sac = RecurrentSAC(actor, critic, SacSettings(target_heads=2))
    before = [p.detach().clone() for p in critic.more_q.parameters()]
    torch.manual_seed(1)
    info = sac.update(batch)
    assert np.isfinite(info["critic_loss"]) and np.isfinite(info["actor_loss"])
    assert all(not torch.equal(a, p) for a, p in zip(before, critic.more_q.parameters(), strict=True))


def test_bad_head_counts_are_refused():
    with pytest.raises(ValueError, match="critic_heads must be >= 2"):
        NetConfig(critic_heads=1)
    with pytest.raises(ValueError, match="target_heads must be >= 1"):
        SacSettings(target_heads=0)
    with pytest.raises(ValueError, match="sac.target_heads 3 exceeds net.critic_heads 2"):
        SacConfig(sac=SacSettings(target_heads=3))
    SacConfig(net=dataclasses.replace(NET, critic_heads=3), sac=SacSettings(target_heads=3))
    assert (
        NetConfig.from_dict({k: v for k, v in NET.to_dict().items() if k != "critic_heads"}).critic_heads == 2
    )
