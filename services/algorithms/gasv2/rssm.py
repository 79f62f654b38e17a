"""DreamerV2's recurrent state-space model with categorical latents, and its balanced KL loss.

A model state is ``RSSMState(deter, logits, stoch)``; ``features(state)`` is what the heads, the
actor and the critic read.

Design notes: docs/architecture-notes.md, services/algorithms/gasv2/rssm.py."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from services.algorithms.gasv2.config import DreamerConfig


class RSSMState(NamedTuple):
    deter: Tensor
    """(..., deter) GRU state."""
    logits: Tensor
    """(..., stoch, classes) logits of the categorical latents."""
    stoch: Tensor
    """(..., stoch * classes) one-hot sample (straight-through gradients to ``logits``)."""


def features(state: RSSMState) -> Tensor:
    """(..., stoch * classes + deter): DreamerV2's ``get_feat``."""
    return torch.cat([state.stoch, state.deter], -1)


def stack_states(states: list[RSSMState], dim: int) -> RSSMState:
    return RSSMState(*(torch.stack(xs, dim) for xs in zip(*states, strict=True)))


def select_states(state: RSSMState, index: Tensor) -> RSSMState:
    """Rows of every field picked by a (boolean or integer) index over the leading dims."""
    return RSSMState(*(x[index] for x in state))


def detach_state(state: RSSMState) -> RSSMState:
    return RSSMState(*(x.detach() for x in state))


def masked_mean(x: Tensor, mask: Tensor) -> Tensor:
    """Mean of ``x`` over the entries where ``mask`` (same shape) is true; 0 for an empty mask."""
    m = mask.to(x.dtype)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def activation(name: str) -> nn.Module:
    return {"elu": nn.ELU, "relu": nn.ReLU, "silu": nn.SiLU, "tanh": nn.Tanh}[name]()


def init_weights(module: nn.Module) -> None:
    """Keras' defaults, as in DreamerV2: Glorot-uniform weights, zero biases (torch's default
    Kaiming-uniform(a=sqrt 5) starts the deep nets with much smaller activations)."""
    for m in module.modules():
        if isinstance(m, nn.Linear | nn.Conv2d | nn.ConvTranspose2d):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


def gumbel_argmax(logits: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Index of a sample from Categorical(logits) over the last axis (Gumbel-max)."""
    u = torch.rand(logits.shape, generator=generator, dtype=logits.dtype, device=logits.device)
    tiny = torch.finfo(logits.dtype).tiny
    return (logits.detach() - torch.log(-torch.log(u.clamp_min(tiny)))).argmax(-1)


def sample_one_hot(logits: Tensor, sample: bool = True, generator: torch.Generator | None = None) -> Tensor:
    """One-hot sample (or mode) of the last axis with straight-through gradients (DreamerV2's
    ``OneHotDist.sample``): the value is the one-hot, the gradient that of the probabilities."""
    index = gumbel_argmax(logits, generator) if sample else logits.detach().argmax(-1)
    one_hot = F.one_hot(index, logits.shape[-1]).to(logits.dtype)
    probs = logits.softmax(-1)
    return one_hot + (probs - probs.detach())  # exactly the one-hot in value


class GRUCell(nn.Module):
    """DreamerV2's GRU: one dense layer for the three gates, layer norm over all of them, and an
    update-gate bias of -1 (keeps the state by default early in training)."""

    def __init__(self, inp: int, size: int, norm: bool = True, update_bias: float = -1.0) -> None:
        super().__init__()
        self.layer = nn.Linear(inp + size, 3 * size)
        self.norm = nn.LayerNorm(3 * size, eps=1e-3) if norm else nn.Identity()  # Keras' epsilon
        self.update_bias = update_bias

    def forward(self, x: Tensor, h: Tensor) -> Tensor:
        parts = self.norm(self.layer(torch.cat([x, h], -1)))
        reset, cand, update = parts.chunk(3, -1)
        cand = torch.tanh(torch.sigmoid(reset) * cand)
        update = torch.sigmoid(update + self.update_bias)
        return update * cand + (1.0 - update) * h


class RSSM(nn.Module):
    def __init__(self, cfg: DreamerConfig, embed_dim: int) -> None:
        super().__init__()
        self.cfg = cfg
        S, H = cfg.stoch_dim, cfg.hidden
        self.img_in = nn.Sequential(nn.Linear(S + cfg.action_dim, H), activation(cfg.act))
        self.cell = GRUCell(H, cfg.deter, norm=cfg.gru_norm)
        self.img_out = nn.Sequential(nn.Linear(cfg.deter, H), activation(cfg.act), nn.Linear(H, S))
        self.obs_out = nn.Sequential(
            nn.Linear(cfg.deter + embed_dim, H), activation(cfg.act), nn.Linear(H, S)
        )
        init_weights(self)

    def initial(self, batch: int) -> RSSMState:
        """All-zero state (DreamerV2's ``initial``); ``is_first`` resets to it."""
        p = self.img_in[0].weight
        c = self.cfg
        z = lambda *shape: torch.zeros(*shape, dtype=p.dtype, device=p.device)  # noqa: E731
        return RSSMState(z(batch, c.deter), z(batch, c.stoch, c.classes), z(batch, c.stoch_dim))

    def _logits(self, x: Tensor) -> Tensor:
        return x.unflatten(-1, (self.cfg.stoch, self.cfg.classes))

    def img_step(
        self, state: RSSMState, action: Tensor, sample: bool = True, generator: torch.Generator | None = None
    ) -> RSSMState:
        """The prior one step on: (B, ...) state, (B, action_dim) action into the next observation."""
        x = self.img_in(torch.cat([state.stoch, action], -1))
        deter = self.cell(x, state.deter)
        logits = self._logits(self.img_out(deter))
        return RSSMState(deter, logits, sample_one_hot(logits, sample, generator).flatten(-2))

    def obs_step(
        self,
        state: RSSMState,
        action: Tensor,
        embed: Tensor,
        is_first: Tensor,
        sample: bool = True,
        generator: torch.Generator | None = None,
    ) -> tuple[RSSMState, RSSMState]:
        """(posterior, prior) of the next observation; state and action are zeroed where ``is_first``."""
        keep = (~is_first.bool()).to(action.dtype)
        state = RSSMState(
            state.deter * keep[:, None], state.logits * keep[:, None, None], state.stoch * keep[:, None]
        )
        prior = self.img_step(state, action * keep[:, None], sample, generator)
        logits = self._logits(self.obs_out(torch.cat([prior.deter, embed], -1)))
        post = RSSMState(prior.deter, logits, sample_one_hot(logits, sample, generator).flatten(-2))
        return post, prior

    def observe(
        self,
        embeds: Tensor,
        actions: Tensor,
        is_first: Tensor,
        state: RSSMState | None = None,
        sample: bool = True,
        generator: torch.Generator | None = None,
    ) -> tuple[RSSMState, RSSMState]:
        """(posts, priors), each field (B, L, ...), of embeds (B, L, E), actions (B, L, A), is_first (B, L)."""
        B, L = embeds.shape[:2]
        state = self.initial(B) if state is None else state
        posts, priors = [], []
        for t in range(L):
            state, prior = self.obs_step(
                state, actions[:, t], embeds[:, t], is_first[:, t], sample, generator
            )
            posts.append(state)
            priors.append(prior)
        return stack_states(posts, 1), stack_states(priors, 1)

    def imagine(
        self, actions: Tensor, state: RSSMState, sample: bool = True, generator: torch.Generator | None = None
    ) -> RSSMState:
        """Priors (B, H, ...) of an open-loop action sequence (B, H, A) from ``state``."""
        priors = []
        for t in range(actions.shape[1]):
            state = self.img_step(state, actions[:, t], sample, generator)
            priors.append(state)
        return stack_states(priors, 1)


def categorical_kl(p_logits: Tensor, q_logits: Tensor) -> Tensor:
    """KL(p || q) of independent categoricals (..., stoch, classes), summed over the latents: (...)."""
    log_p, log_q = p_logits.log_softmax(-1), q_logits.log_softmax(-1)
    return (log_p.exp() * (log_p - log_q)).sum((-2, -1))


def kl_loss(
    post_logits: Tensor,
    prior_logits: Tensor,
    balance: float,
    free: float,
    free_avg: bool,
    mask: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """DreamerV2's balanced KL: ``balance`` KL(sg(post) || prior) + (1 - balance) KL(post || sg(prior)).

    Both terms have the value KL(post || prior); the split only routes the gradient, so that the
    prior moves toward the posterior faster than the posterior is regularised toward the prior.
    Free nats as DreamerV2: ``free_avg`` clamps each term's (masked) mean at ``free`` from below
    (no gradient while the mean is under it), otherwise each step's KL is clamped before the mean.
    Returns (scalar loss, per-step KL(post || prior) (...), detached)."""
    if mask is None:
        mask = torch.ones(post_logits.shape[:-2], dtype=torch.bool, device=post_logits.device)
    to_post = categorical_kl(post_logits, prior_logits.detach())  # trains the posterior
    to_prior = categorical_kl(post_logits.detach(), prior_logits)  # trains the prior
    if free_avg:
        loss_post = masked_mean(to_post, mask).clamp_min(free)
        loss_prior = masked_mean(to_prior, mask).clamp_min(free)
    else:
        loss_post = masked_mean(to_post.clamp_min(free), mask)
        loss_prior = masked_mean(to_prior.clamp_min(free), mask)
    return balance * loss_prior + (1.0 - balance) * loss_post, to_post.detach()
