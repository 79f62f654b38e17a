"""An actor climbing a fixed critic: the SAC actor loss alone, stepped by Adam, against a critic that
does not learn.

A released clone falls whether or not its critic goes on learning; holding the critic still tells
whether the critic's own slope around the clone's actions leads the actor into failures (the actor
gains value by the critic and loses success in the simulator) or the actor's step does not climb
the critic at all. The simulator's side is the caller's (``mea bench critic --climb``)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from services.algorithms.networks import disc_xy
from services.algorithms.sac.losses import Batch, actor_loss, masked_mean, min_q, policy_outputs, squash


@dataclass(frozen=True)
class ClimbPoint:
    """The critic's min-Q on the probe batch after ``updates`` actor updates, mean over its real
    transitions: of the policy's sampled actions (fixed noise), of its squashed mean actions, and of
    the recorded actions (fixed while the critic is)."""

    updates: int
    q_sample: float
    q_mean: float
    q_recorded: float


@torch.no_grad()
def climb_point(actor: nn.Module, critic: nn.Module, probe: Batch, noise: Tensor, updates: int) -> ClimbPoint:
    """``ClimbPoint`` of ``actor`` on ``probe`` with the policy's sampling noise ``noise`` (B, L+1, A)."""
    feats = critic.features_of(probe)[:, :-1]
    policy = policy_outputs(actor, probe, noise, disc=disc_xy(actor))
    mean = squash(policy.mean[:, :-1], disc_xy(actor))
    q = {k: float(masked_mean(min_q(critic.q(feats, a)), probe.mask))
         for k, a in (("s", policy.actions[:, :-1]), ("m", mean), ("r", probe.actions))}  # fmt: skip
    return ClimbPoint(updates, q["s"], q["m"], q["r"])


def climb(
    actor: nn.Module, critic: nn.Module, batches: Iterator[Batch], updates: int, every: int, lr: float,
    alpha: float, probe: Batch,
) -> Iterator[ClimbPoint]:  # fmt: skip
    """Step ``actor`` ``updates`` times by Adam at ``lr`` on the SAC actor loss (temperature ``alpha``)
    against ``critic``, which is never changed, one batch from ``batches`` per update; yield a
    ``ClimbPoint`` before the first update and after every ``every``-th and the last. The caller may
    play the actor in between: it is the same module."""
    params = [p for p in actor.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=lr)
    generator = torch.Generator().manual_seed(0)
    noise = torch.randn(*probe.images.shape[:2], probe.actions.shape[-1], generator=generator)
    disc = disc_xy(actor)
    yield climb_point(actor, critic, probe, noise, 0)
    for u in range(1, updates + 1):
        batch = next(batches)
        with torch.no_grad():
            feats = critic.features_of(batch)
        loss = actor_loss(critic, feats, batch, policy_outputs(actor, batch, disc=disc), alpha)
        grads = torch.autograd.grad(loss, params, allow_unused=True)  # the critic gets none
        for p, g in zip(params, grads, strict=True):
            p.grad = g
        opt.step()
        if u % every == 0 or u == updates:
            yield climb_point(actor, critic, probe, noise, u)


__all__ = ["ClimbPoint", "climb", "climb_point"]
