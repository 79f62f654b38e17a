"""Small recurrent actor/critic with the learner's network interface, for testing the SAC math fast.

Same contract as ``services.algorithms.networks``: images (B, T, C, H, W) and previous actions
(B, T, A) in; the actor returns (mean, log_std, state); the critic returns per-step features and
twin Q values from them. Causal (a GRU), so padding after an episode cannot leak backwards.
``check_lerp_update`` checks a target-network update (soft or slow target) on small layers.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

A = 5


class _Trunk(nn.Module):
    def __init__(self, image_numel: int, hidden: int) -> None:
        super().__init__()
        self.embed = nn.Linear(image_numel, hidden)
        self.rnn = nn.GRU(hidden + A, hidden, batch_first=True)

    def forward(
        self,
        images: Tensor,
        prev_actions: Tensor,
        state: Tensor | None = None,
        embedding: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        e = torch.tanh(self.embed(images.flatten(2))) if embedding is None else embedding
        h, state = self.rnn(torch.cat([e, prev_actions], -1), state)
        return torch.cat([h, e], -1), state


class TinyActor(nn.Module):
    def __init__(self, image_numel: int, hidden: int = 16) -> None:
        super().__init__()
        self.trunk = _Trunk(image_numel, hidden)
        self.head = nn.Linear(2 * hidden, 2 * A)

    def forward(
        self, images: Tensor, prev_actions: Tensor, state: Tensor | None = None, embedding=None, obs_mask=None
    ):
        """``obs_mask`` is accepted and ignored: this trunk is cheap on padding, which cannot leak back."""
        f, state = self.trunk(images, prev_actions, state, embedding)
        mean, log_std = self.head(f).chunk(2, -1)
        return mean, log_std.clamp(-20.0, 2.0), state


class TinyCritic(nn.Module):
    def __init__(self, image_numel: int, hidden: int = 16) -> None:
        super().__init__()
        self.trunk = _Trunk(image_numel, hidden)
        self.q1 = nn.Sequential(nn.Linear(2 * hidden + A, hidden), nn.ReLU(), nn.Linear(hidden, 1))
        self.q2 = nn.Sequential(nn.Linear(2 * hidden + A, hidden), nn.ReLU(), nn.Linear(hidden, 1))

    def features(self, images: Tensor, prev_actions: Tensor, state: Tensor | None = None, obs_mask=None):
        return self.trunk(images, prev_actions, state)

    def features_of(self, batch) -> Tensor:
        return self.features(batch.images, batch.prev_actions)[0]

    def q(self, features: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        x = torch.cat([features, actions], -1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)


def check_lerp_update(update, fraction: float, seed: int) -> tuple[nn.Module, nn.Module]:
    """``update(target, source, fraction)`` on two small linear layers must move every parameter of
    the target ``fraction`` of its way to the source's; returns (target, source) after it."""
    torch.manual_seed(seed)
    source, target = nn.Linear(3, 2), nn.Linear(3, 2)
    before = copy.deepcopy(target)
    update(target, source, fraction)
    for t, b, s in zip(target.parameters(), before.parameters(), source.parameters(), strict=True):
        assert torch.allclose(t, b + fraction * (s - b)), (t, b, s)
    return target, source
