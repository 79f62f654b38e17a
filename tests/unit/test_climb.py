"""An actor climbing a fixed critic (``services.algorithms.sac.climb``): the critic never changes,
the actor does, and its value by the critic rises on the batch it climbs."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from services.algorithms.batch import to_batch
from services.algorithms.sac.climb import climb
from tests.unit.test_sac_options import nets, replay_with

pytestmark = pytest.mark.unit


def test_the_actor_climbs_a_critic_that_does_not_move():
    batch = to_batch(replay_with([6, 5, 7], demos=1).sample(3, np.random.default_rng(2), trim=True))
    actor, critic, _ = nets(seed=4)
    critic_before = {k: v.clone() for k, v in critic.state_dict().items()}
    actor_before = [p.detach().clone() for p in actor.parameters()]
    points = list(climb(actor, critic, itertools.repeat(batch), updates=25, every=10, lr=1e-2, alpha=0.0,
                        probe=batch))  # fmt: skip
    assert [p.updates for p in points] == [0, 10, 20, 25]
    for k, v in critic.state_dict().items():
        assert torch.equal(v, critic_before[k]), k
    assert all(p.grad is None for p in critic.parameters())
    assert any(not torch.equal(a, p) for a, p in zip(actor_before, actor.parameters(), strict=True))
    assert len({p.q_recorded for p in points}) == 1  # the recorded actions' value: the critic is fixed
    # climbing the batch it is probed on, the policy's sampled actions gain value by the critic
    assert points[-1].q_sample > points[0].q_sample + 1e-3, points


def test_a_climb_with_no_updates_is_the_starting_point_alone():
    batch = to_batch(replay_with([4, 3]).sample(2, np.random.default_rng(0), trim=True))
    actor, critic, _ = nets()
    points = list(climb(actor, critic, itertools.repeat(batch), 0, 5, 1e-3, 0.1, batch))
    assert [p.updates for p in points] == [0]
