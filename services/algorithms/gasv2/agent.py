"""GASv2's learner: the world model, actor, critic and slow critic with their optimisers, one
``update`` per ``ChunkBatch``; and ``LatentPolicy``, the part actors run (encoder, RSSM, actor).

An update is DreamerV2's: one world-model step on the batch, then one actor and one critic step
in imagination from the batch's detached posteriors (``behaviour.start_states``), then the slow
critic's update every ``slow_target_every`` updates. Optimisers are DreamerV2's: Adam (eps
``opt_eps``), gradient clipping by global norm, and weight decay that multiplies every weight by
(1 - ``weight_decay``) per step, which is AdamW with weight_decay = weight_decay / lr.

All sampling (latents, imagined actions) draws from the agent's own ``torch.Generator``, which the
checkpoint carries: a restored agent's next update is bit-identical to the original's.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable

import numpy as np
import torch
from torch import Tensor, nn

from services.algorithms.gasv2.action_features import DISCRETE_FEATURES
from services.algorithms.gasv2.behaviour import (
    LatentActor,
    LatentCritic,
    behaviour_losses,
    start_states,
    update_slow_target,
)
from services.algorithms.gasv2.chunks import ChunkBatch
from services.algorithms.gasv2.config import DreamerConfig
from services.algorithms.gasv2.rssm import RSSM, RSSMState, features
from services.algorithms.gasv2.world_model import Encoder, WorldModel
from services.algorithms.tensors import actor_tensors

BEHAVIOUR_METRICS = ("actor_loss", "critic_loss", "actor_entropy", "advantage", "imag_return", "imag_reward",
                     "imag_discount", "imag_value", "actor_grad_norm", "critic_grad_norm")  # fmt: skip


class LatentPolicy(nn.Module):
    """What actors run: the encoder and RSSM posterior to track a latent state, and the actor."""

    def __init__(self, encoder: Encoder, rssm: RSSM, actor: LatentActor) -> None:
        super().__init__()
        self.encoder, self.rssm, self.actor = encoder, rssm, actor

    def initial_state(self, batch: int) -> RSSMState:
        return self.rssm.initial(batch)

    def step(
        self,
        state: RSSMState,
        prev_action_feature: Tensor,
        image: Tensor,
        is_first: Tensor,
        sample: bool = True,
        generator: torch.Generator | None = None,
    ) -> tuple[Tensor, RSSMState]:
        """(action logits (B, num_actions), posterior state) after observing ``image`` (B, C, H, W) in
        [0, 1], reached by the action with feature ``prev_action_feature`` (B, action_dim; ignored
        where ``is_first`` (B,))."""
        embed = self.encoder(image)
        post, _ = self.rssm.obs_step(state, prev_action_feature, embed, is_first, sample, generator)
        return self.actor(features(post)), post


def build_policy(cfg: DreamerConfig, seed: int = 0) -> LatentPolicy:
    """A standalone policy with the same state_dict layout as ``GasV2Agent(cfg).policy``."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        encoder = Encoder(cfg)
        return LatentPolicy(encoder, RSSM(cfg, encoder.embed_dim), LatentActor(cfg))


def _optimizer(params: Iterable[nn.Parameter], lr: float, cfg: DreamerConfig) -> torch.optim.AdamW:
    return torch.optim.AdamW(params, lr=lr, eps=cfg.opt_eps, weight_decay=cfg.weight_decay / lr)


def _step(opt: torch.optim.Optimizer, loss: Tensor, params: list[nn.Parameter], clip: float) -> Tensor:
    opt.zero_grad(set_to_none=True)
    loss.backward()
    norm = nn.utils.clip_grad_norm_(params, clip)
    opt.step()
    return norm.detach()


class GasV2Agent:
    def __init__(self, cfg: DreamerConfig, seed: int = 0, device: str | torch.device = "cpu") -> None:
        self.cfg = cfg
        self.device = torch.device(device)
        with torch.random.fork_rng(devices=[]):  # seeded init without touching the caller's RNG
            torch.manual_seed(seed)
            self.world_model = WorldModel(cfg).to(self.device)
            self.actor = LatentActor(cfg).to(self.device)
            self.critic = LatentCritic(cfg).to(self.device)
        self.slow_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.policy = LatentPolicy(self.world_model.encoder, self.world_model.rssm, self.actor)
        self._params = {
            name: list(m.parameters())
            for name, m in (("model", self.world_model), ("actor", self.actor), ("critic", self.critic))
        }
        self.model_opt = _optimizer(self._params["model"], cfg.model_lr, cfg)
        self.actor_opt = _optimizer(self._params["actor"], cfg.actor_lr, cfg)
        self.critic_opt = _optimizer(self._params["critic"], cfg.critic_lr, cfg)
        self.generator = torch.Generator(device=self.device).manual_seed(seed)
        self.action_features = torch.as_tensor(DISCRETE_FEATURES, device=self.device)
        self.updates = 0

    def policy_tensors(self) -> dict[str, np.ndarray]:
        """What actors run, on the CPU: the latent policy (encoder, RSSM, actor), not the decoder,
        heads or critic."""
        return actor_tensors(self.policy)

    def update(self, batch: ChunkBatch) -> dict[str, float]:
        """``update_tensors``, its statistics read as floats."""
        return {k: float(v) for k, v in self.update_tensors(batch).items()}

    def update_tensors(self, batch: ChunkBatch) -> dict[str, Tensor | float]:
        """One world-model step, then one actor and one critic step in imagination; its statistics as
        0-d tensors on the device (counts as floats), never read here."""
        cfg, batch = self.cfg, batch.to(self.device)
        model_loss, posts, metrics = self.world_model.loss(batch, self.generator)
        metrics["model_grad_norm"] = _step(self.model_opt, model_loss, self._params["model"], cfg.grad_clip)
        start = start_states(posts, batch)
        n = start.deter.shape[0]
        if n > 0:
            a_loss, c_loss, b_metrics = behaviour_losses(
                self.world_model, self.actor, self.critic, self.slow_critic, start, cfg, self.action_features,
                self.generator,
            )  # fmt: skip
            b_metrics["actor_grad_norm"] = _step(self.actor_opt, a_loss, self._params["actor"], cfg.grad_clip)
            b_metrics["critic_grad_norm"] = _step(
                self.critic_opt, c_loss, self._params["critic"], cfg.grad_clip
            )
            metrics.update(b_metrics)
        else:  # nothing to imagine from: report zeros, leave actor and critic as they are
            metrics.update({k: torch.zeros((), device=self.device) for k in BEHAVIOUR_METRICS})
        self.updates += 1
        if self.updates % cfg.slow_target_every == 0:
            update_slow_target(self.slow_critic, self.critic, cfg.slow_target_fraction)
        return {**metrics, "imag_starts": float(n), "updates": float(self.updates)}

    # checkpoints -------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Every network, the optimisers, the sampling generator and the update count; tensors,
        numbers, strings, lists and dicts only (``torch.load(weights_only=True)`` reads it)."""
        return {
            "world_model": self.world_model.state_dict(),
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "slow_critic": self.slow_critic.state_dict(),
            "model_opt": self.model_opt.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "generator": self.generator.get_state(),
            "updates": self.updates,
            "config": self.cfg.to_dict(),
        }

    def load_state_dict(self, d: dict) -> None:
        for name in ("world_model", "actor", "critic", "slow_critic", "model_opt", "actor_opt", "critic_opt"):
            getattr(self, name).load_state_dict(d[name])
        self.generator.set_state(d["generator"])
        self.updates = int(d["updates"])
