"""Recurrent SAC (``RecurrentSAC``): actor, twin critic with a soft-updated target copy and entropy
temperature, their optimisers, and one update over a ``Batch`` (``losses``) on one torch device.

Speed choices (each saves one pass of an image encoder over B x (L+1) images per update): the
actor's forward pass serves both the critic targets (a' at t+1, no gradient) and the actor loss (a~ at
t, reparameterised); the actor loss reads the critic's recurrent features from the critic step,
detached, through the critic's (just updated) Q heads. Gradients are taken with respect to each
loss's own parameters (``torch.autograd.grad``), so no loss moves another's parameters.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from services.algorithms.networks import disc_xy
from services.algorithms.sac.config import SacSettings
from services.algorithms.sac.graphed import GraphedUpdate
from services.algorithms.sac.losses import (
    CONSERVATIVE_ACTIONS,
    ActionValues,
    Batch,
    DemoCritique,
    PolicyOutputs,
    action_values,
    actor_loss,
    alpha_loss,
    bc_loss,
    bounded_targets,
    conservative_gap,
    critic_loss,
    critic_targets,
    critique_demos,
    crr_loss,
    crr_weights,
    gathered,
    masked_mean,
    policy_outputs,
    returns_to_go,
    soft_update,
)
from services.algorithms.tensors import actor_tensors

Grads = tuple[Tensor | None, ...]


@dataclass(frozen=True)
class _Forward:
    """One pass over a batch, read by every loss of the update (``RecurrentSAC._forward``)."""

    policy: PolicyOutputs
    """The policy's samples and log-probs at every observation (reparameterised)."""
    targets: Tensor
    """Critic targets y_t (B, L), no gradient."""
    critique: DemoCritique | None
    """The target critic's reading of the demonstrations (None without them)."""
    values: ActionValues | None
    """The target critic's values of the replayed and the policy's actions (None: neither the
    critique nor CRR reads them, a batch without demos under the SAC objective)."""
    feats: Tensor | None
    """The critic's features with gradients, from a shared encoder's pass (None: ``critic_loss`` runs it)."""
    embedding: Tensor | None
    """A shared encoder's live image embedding (None without one)."""


def _grads(loss: Tensor, params: list[Tensor], retain: bool = False) -> Grads:
    return torch.autograd.grad(loss, params, allow_unused=True, retain_graph=retain)


def _norm(grads: Grads) -> Tensor:
    norms = [g.norm() for g in grads if g is not None]
    return torch.linalg.vector_norm(torch.stack(norms)) if norms else torch.zeros(())


def _apply(opt: torch.optim.Optimizer, params: list[Tensor], *terms: Grads) -> None:
    """Sum each parameter's gradient over ``terms`` (gradients of ``params`` only, others untouched),
    then one optimiser step."""
    for i, p in enumerate(params):
        parts = [t[i] for t in terms if t and t[i] is not None]
        p.grad = None if not parts else parts[0] if len(parts) == 1 else torch.stack(parts).sum(0)
    opt.step()


def _step(opt: torch.optim.Optimizer, loss: Tensor, params: list[Tensor]) -> None:
    _apply(opt, params, _grads(loss, params))


# ------------------------------------------------------------------------------------------------
# the update
# ------------------------------------------------------------------------------------------------


class RecurrentSAC:
    """Actor, twin critic with a soft-updated target copy, entropy temperature, their optimisers, all
    on ``device`` (the networks are moved there; batches must be there too)."""

    def __init__(
        self,
        actor: nn.Module,
        critic: nn.Module,
        settings: SacSettings,
        device: torch.device | str = "cpu",
        cuda_graphs: bool = False,
    ) -> None:
        self.s = settings
        self.disc = disc_xy(actor)
        self.device = torch.device(device)
        self.actor, self.critic = actor.to(self.device), critic.to(self.device)
        self.critic_target = copy.deepcopy(critic).requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(settings.init_alpha), device=self.device, requires_grad=True)
        if settings.share_encoder and not hasattr(critic, "encoder"):
            raise ValueError("share_encoder needs a critic with an image encoder (not the state critic)")
        if settings.share_encoder:
            actor.encoder = critic.encoder  # trained by the critic's loss only
        shared = {id(p) for p in critic.parameters()}
        self._actor_params = [p for p in actor.parameters() if p.requires_grad and id(p) not in shared]
        self._critic_params = [p for p in critic.parameters() if p.requires_grad]
        # torch's default Adam on every device (multi-tensor on CUDA). Not the fused kernel: it
        # refuses a gradient whose strides differ from its parameter's (einsum hands the mean
        # head's irrep a transposed one), which the H200 check of 2026-11-29 hit on every update.
        opt = {"capturable": True} if cuda_graphs else {}  # Adam's step count read inside the graph
        self.actor_opt = torch.optim.Adam(self._actor_params, lr=settings.actor_rate, **opt)
        self.critic_opt = torch.optim.Adam(self._critic_params, lr=settings.lr, **opt)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=settings.alpha_lr, **opt)
        self.updates = 0
        self._graphed = (
            GraphedUpdate(
                self._update,
                self._host_settings,
                [*self._actor_params, *self._critic_params, self.log_alpha],
                self.device,
                self._count_update,
            )
            if cuda_graphs
            else None
        )

    @property
    def alpha(self) -> Tensor:
        return self.log_alpha.detach().exp()

    @torch.no_grad()
    def td_targets(self, batch: Batch) -> Tensor:
        """y (B, L): the targets an update would regress the critic onto for ``batch`` now (the
        policy's sampled next actions, the current alpha, the return bound where on). Read only."""
        return self._forward(batch, self.alpha).targets

    def policy_tensors(self) -> dict[str, np.ndarray]:
        """What actors run, on the CPU: the actor's parameters and buffers."""
        return actor_tensors(self.actor)

    def update(self, batch: Batch) -> dict[str, float]:
        """``update_tensors``, its statistics read as floats."""
        return {k: float(v) for k, v in self.update_tensors(batch).items()}

    def update_tensors(self, batch: Batch) -> dict[str, Tensor | float]:
        """``_update`` once, counted: eagerly, or as a CUDA graph replay (``cuda_graphs``)."""
        if self._graphed is not None:
            return self._graphed(batch)
        out = self._update(batch)
        self._count_update()
        return out

    def _count_update(self) -> None:
        self.updates += 1

    def _host_settings(self) -> tuple[float, bool]:
        """What an update reads on the host besides its batch: the BC weight and whether the actor's
        warm-up is over (a CUDA graph is captured per value)."""
        return self.s.bc_weight_at(self.updates), self.updates >= self.s.actor_warmup_updates

    def _update(self, batch: Batch) -> dict[str, Tensor | float]:
        """One update in the paper's order: the losses on one pass over the batch (``_forward``), then
        the critic step, the actor step (through the just-updated Q heads), the temperature step and
        the target critic; its statistics as 0-d tensors on the device (``bc_weight`` a float), never
        read here (a host synchronisation, which a GPU learner does every N updates).

        The BC term's gradient on the actor is taken apart from the SAC term's, so both norms are
        reported (which of them steers the actor). With a shared encoder the BC term also trains the
        encoder, beside the critic loss (a sparse-reward critic alone shapes it too slowly)."""
        s, alpha = self.s, self.alpha
        w, warm = self._host_settings()
        fwd = self._forward(batch, alpha)

        # losses: J_Q, and J_bc (where on) with its gradient on the actor, taken while the graph it
        # shares with J_Q through a shared encoder is whole
        q_loss, feats, q_info = critic_loss(self.critic, batch, fwd.targets, fwd.feats)
        cql = None  # the TD loss alone is reported as critic_loss
        c_loss = q_loss
        if s.conservative_weight > 0:
            floor = returns_to_go(batch.rewards, batch.mask, s.gamma) if s.conservative_calibrated else None
            cql = conservative_gap(
                self.critic, feats, batch, fwd.policy.actions[:, :-1], CONSERVATIVE_ACTIONS, floor
            )
            c_loss = q_loss + s.conservative_weight * cql
        b_loss = self._bc_loss(batch, fwd) if w > 0 else None
        bc_grads: Grads = () if b_loss is None else _grads(w * b_loss, self._actor_params, retain=True)

        # critic step: J_Q, plus w J_bc where the BC term reaches a shared encoder
        trains_encoder = b_loss is not None and fwd.embedding is not None
        _step(self.critic_opt, c_loss + w * b_loss if trains_encoder else c_loss, self._critic_params)

        # actor step: J_pi through the just-updated Q heads, plus the BC gradient; during a critic
        # warm-up the BC gradient alone (J_pi's gradient still measured)
        crr = s.actor_objective == "crr"
        if crr:
            assert fwd.values is not None  # _forward computes them for crr
            weights = crr_weights(fwd.values, s.crr_beta)
            pi_loss = crr_loss(fwd.policy, batch, weights)
        else:
            pi_loss = actor_loss(self.critic, feats, batch, fwd.policy, alpha)
        pi_grads = _grads(pi_loss, self._actor_params)
        if warm or bc_grads:
            _apply(self.actor_opt, self._actor_params, pi_grads if warm else (), bc_grads)

        # temperature step, then the target critic
        log_probs = fwd.policy.log_probs[:, :-1]
        a_loss = alpha_loss(self.log_alpha, log_probs, batch.mask, s.target_entropy, s.alpha_loss)
        if s.autotune_alpha and warm and not crr:  # crr's actor has no entropy term to tune
            _step(self.alpha_opt, a_loss, [self.log_alpha])
        soft_update(self.critic_target, self.critic, s.tau)

        out: dict[str, Tensor | float] = {
            "critic_loss": q_loss.detach(),
            "actor_loss": pi_loss.detach(),
            "alpha_loss": a_loss.detach(),
            "alpha": self.alpha,
            "q1": q_info["q1"],
            "q2": q_info["q2"],
            "target_q": masked_mean(fwd.targets, batch.mask),
            "entropy": -masked_mean(log_probs.detach(), batch.mask),
            "actor_grad_norm": _norm(pi_grads),
        }
        if crr:
            out["crr_keep"] = masked_mean(weights, batch.mask)
        if cql is not None:
            out["conservative_gap"] = cql.detach()
        if fwd.critique is not None:
            c = fwd.critique
            out |= {
                "bc_accept": c.accept,
                "q_rank_gap": c.rank_gap,
                "q_reverse_gap": c.reverse_gap,
                "q_demo_minus_pi": c.pi_gap,
            }
        if b_loss is not None:
            out |= {"bc_loss": b_loss.detach(), "bc_weight": w, "bc_grad_norm": _norm(bc_grads)}
        return out

    def _forward(self, batch: Batch, alpha: Tensor) -> _Forward:
        """The pass over the batch every loss reads: a shared encoder's features (with gradients),
        the policy's samples at every observation, the critic targets and the target critic's
        reading of the demonstrations (no gradient)."""
        s = self.s
        feats = embedding = None
        if s.share_encoder:
            feats, _ = self.critic.features(
                batch.images, batch.prev_actions, obs_mask=batch.obs_mask, **gathered(batch)
            )
            embedding = feats[..., -self.critic.cfg.image_embed :]
        # the SAC actor term sees the shared embedding detached: only the critic (and BC) move it
        policy = policy_outputs(
            self.actor, batch, embedding=None if embedding is None else embedding.detach(), disc=self.disc
        )
        with torch.no_grad():
            target_feats = self.critic_target.features_of(batch)
        targets = critic_targets(self.critic_target, batch, policy, alpha, s.gamma, s.n_step, target_feats,
                                 s.backup_entropy, s.target_heads)  # fmt: skip
        if s.return_bound:
            targets = bounded_targets(targets, batch, s.gamma)
        values = None
        if batch.demo is not None or s.actor_objective == "crr":
            values = action_values(self.critic_target, target_feats, batch, policy.mean, self.disc)
        critique = None if values is None else critique_demos(self.critic_target, target_feats, batch, values)
        return _Forward(policy, targets, critique, values, feats, embedding)

    def _bc_loss(self, batch: Batch, fwd: _Forward) -> Tensor:
        """J_bc on the demonstration transitions (those the Q filter keeps, with ``bc_filter``); with a
        shared encoder through the live embedding, so that it trains the encoder too."""
        mean = (
            fwd.policy.mean
            if fwd.embedding is None
            else self.actor(batch.images, batch.prev_actions, embedding=fwd.embedding)[0]
        )
        keep = fwd.critique.keep if (self.s.bc_filter and fwd.critique is not None) else None
        return bc_loss(mean, batch, keep, self.disc)

    # checkpoints -------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            "updates": self.updates,
        }

    def load_state_dict(self, d: dict) -> None:
        self.actor.load_state_dict(d["actor"])
        self.critic.load_state_dict(d["critic"])
        self.critic_target.load_state_dict(d["critic_target"])
        with torch.no_grad():
            self.log_alpha.copy_(d["log_alpha"])
        self.actor_opt.load_state_dict(d["actor_opt"])
        self.critic_opt.load_state_dict(d["critic_opt"])
        self.alpha_opt.load_state_dict(d["alpha_opt"])
        self.updates = int(d["updates"])
        self._keep_own_optimiser()

    def _keep_own_optimiser(self) -> None:
        """A loaded optimiser state carries its writer's implementation flags; this learner keeps its
        own (a CUDA graph's Adam keeps its step count on the device, an eager one need not; a state
        written by a fused Adam must not bring the fused kernel back)."""
        for opt in (self.actor_opt, self.critic_opt, self.alpha_opt):
            for group in opt.param_groups:
                for flag in ("capturable", "fused", "foreach"):
                    group[flag] = opt.defaults.get(flag)
            if opt.defaults.get("capturable"):
                for state in opt.state.values():
                    if "step" in state:
                        state["step"] = state["step"].to(self.device, torch.float32)
