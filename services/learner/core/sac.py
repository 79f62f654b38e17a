"""Recurrent SAC (Equi-RSAC's algorithm) as pure loss functions over whole padded episodes.

Shapes: B episodes padded to L transitions. ``images`` has L+1 observations per episode (the next
observation of step t is observation t+1: every sequence is encoded once and the targets reuse it),
``actions``/``rewards``/``terminated``/``mask`` have L rows; ``mask`` is 1 on real transitions and 0
on padding. The recurrent nets read observation t together with the previous action a_{t-1}
(zeros at t = 0), as in Equi-RSAC (pomdp-baselines' ``prev_actions``).

    critic:  y_t = r_t + gamma (1 - term_t) [min_i Q'_i(h'_{t+1}, a'_{t+1}) - alpha log pi(a'_{t+1} | h_{t+1})]
             L_Q = sum_i sum_t mask_t (Q_i(h_t, a_t) - y_t)^2 / sum_t mask_t        a' ~ pi (no gradient)
    actor:   L_pi = sum_t mask_t [alpha log pi(a~_t | h_t) - min_i Q_i(h_t, a~_t)] / sum_t mask_t,  a~ ~ pi (reparameterised)
    alpha:   L_alpha = -log_alpha * sum_t mask_t (log pi(a~_t) + target_entropy) / sum_t mask_t

A truncated episode bootstraps from its last observation (stored); only ``terminated`` stops it.
``n_step`` > 1 replaces y_t by the n-step return (``n_step_targets``); ``return_bound`` raises y_t
to the episode's observed discounted return-to-go G_t where that is higher (``bounded_targets``).

Speed choices (each saves one pass of an image encoder over B x (L+1) images per update):
* the actor's forward pass serves both the critic targets (a' at t+1, no gradient) and the actor
  loss (a~ at t, reparameterised);
* the actor loss reads the critic's recurrent features from the critic step, detached, through the
  critic's (just updated) Q heads; gradients are taken only with respect to the loss's own
  parameters (``torch.autograd.grad``), so no loss can move another's parameters.

Options (``SacSettings``, all off in the paper's recipe): ``bc_weight`` adds
    L_bc = sum_t mask_t demo_b |tanh(mean_t) - a_t|^2 / sum_t mask_t demo_b
to the actor loss (TD3+BC-style cloning of the demonstrations and their augmented copies), and
``share_encoder`` lets the actor read the critic's image embedding (SAC-AE / DrQ), so an update runs
the encoder once with gradients and once without (target critic). The SAC actor loss sees the
embedding detached; the BC term, when on, trains the shared encoder together with the critic loss.

``RecurrentSAC`` wires the losses into one update (critic, actor, alpha, soft target update) on
one torch device; ``update`` returns its statistics as floats, ``update_tensors`` leaves them on
the device (reading one is a host synchronisation, which a GPU learner does every N updates).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


@dataclass(frozen=True)
class Batch:
    """A training batch as tensors (see the module docstring for shapes)."""

    images: Tensor  # (B, L+1, C, H, W) float32
    actions: Tensor  # (B, L, A) float32 in [-1, 1]
    rewards: Tensor  # (B, L)
    terminated: Tensor  # (B, L) float, 1 where the task ended (no bootstrap)
    mask: Tensor  # (B, L) float, 1 on real transitions
    demo: Tensor | None = None  # (B,) float, 1 for demonstrations (and their copies); for the BC term
    obs_mask: Tensor | None = None  # (B, L+1) bool, real observations; padded ones skip the encoders
    state: Tensor | None = None  # (B, L+1, S) privileged state per observation, for a state critic

    @property
    def prev_actions(self) -> Tensor:
        """(B, L+1, A): a_{t-1} beside observation t, zeros at t = 0."""
        a = self.actions
        return torch.cat([torch.zeros_like(a[:, :1]), a], dim=1)


@dataclass(frozen=True)
class SacSettings:
    gamma: float = 0.9
    """Discount (Equi-RSAC: 0.9)."""
    tau: float = 0.005
    """Soft-update rate of the target critic."""
    lr: float = 3e-4
    """Adam learning rate of actor and critic."""
    alpha_lr: float = 1e-3
    """Adam learning rate of log alpha."""
    init_alpha: float = 0.1
    """Initial entropy temperature."""
    target_entropy: float = -5.0
    """Target entropy (-action_dim)."""
    autotune_alpha: bool = True
    """Tune alpha to reach the target entropy; else keep init_alpha."""
    bc_weight: float = 0.0
    """Weight of a behaviour-cloning term in the actor loss: squared error between the policy's mean
    action and the recorded action on demonstration transitions (0: off, the paper)."""
    n_step: int = 1
    """Critic targets from n-step returns (1: the one-step target of Equi-RSAC); see ``n_step_targets``."""
    return_bound: bool = False
    """Critic targets no lower than the episode's observed discounted return-to-go (self-imitation /
    optimality-tightening lower bound; valid for non-negative rewards): demonstrations and successes
    carry their value back at once, instead of one bootstrap hop per target-network lag."""
    share_encoder: bool = False
    """The actor reads the critic's image encoder on detached features (SAC-AE / DrQ): one encoder
    pass with gradients per update instead of two; the actor's loss never moves the encoder."""
    bc_filter: bool = False
    """Clone a demonstration action only where the target critic rates it above the policy's own
    mean action (Q filter, Nair et al. 2018): where the critic knows better, RL overrules the clone."""
    bc_decay_updates: int = 0
    """Decay bc_weight linearly to 0 over this many updates (0: constant)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {self.gamma}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"tau must be in (0, 1], got {self.tau}")
        if self.lr <= 0 or self.alpha_lr <= 0 or self.init_alpha <= 0:
            raise ValueError("lr, alpha_lr and init_alpha must be positive")
        if self.bc_weight < 0:
            raise ValueError(f"bc_weight must be >= 0, got {self.bc_weight}")
        if self.n_step < 1:
            raise ValueError(f"n_step must be >= 1, got {self.n_step}")
        if self.bc_decay_updates < 0:
            raise ValueError(f"bc_decay_updates must be >= 0, got {self.bc_decay_updates}")

    def bc_weight_at(self, updates: int) -> float:
        """The BC weight after ``updates`` updates (``bc_decay_updates``' linear decay)."""
        if self.bc_decay_updates == 0:
            return self.bc_weight
        return self.bc_weight * max(0.0, 1.0 - updates / self.bc_decay_updates)


# ------------------------------------------------------------------------------------------------
# tanh-Gaussian policy distribution
# ------------------------------------------------------------------------------------------------


def tanh_gaussian_sample(
    mean: Tensor, log_std: Tensor, noise: Tensor | None = None, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Reparameterised sample a = tanh(mean + std * eps) and its log-density (summed over the last axis).

    log pi(a) = sum_k [log N(u_k; mean_k, std_k) - log(1 - tanh(u_k)^2)], with the Jacobian term in the
    stable form 2 (log 2 - u - softplus(-2u))."""
    log_std = log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)
    if noise is None:
        noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
    std = log_std.exp()
    u = mean + std * noise
    log_normal = -0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
    log_jac = 2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))
    return torch.tanh(u), (log_normal - log_jac).sum(-1)


def deterministic_action(mean: Tensor) -> Tensor:
    """Evaluation action: tanh of the mean."""
    return torch.tanh(mean)


def masked_mean(x: Tensor, mask: Tensor) -> Tensor:
    return (x * mask).sum() / mask.sum().clamp_min(1.0)


# ------------------------------------------------------------------------------------------------
# losses
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PolicyOutputs:
    """One actor pass over the batch: sampled actions and log-probs at every observation (L+1)."""

    actions: Tensor  # (B, L+1, A)
    log_probs: Tensor  # (B, L+1)
    mean: Tensor
    log_std: Tensor


def policy_outputs(
    actor: nn.Module, batch: Batch, noise: Tensor | None = None, embedding: Tensor | None = None
) -> PolicyOutputs:
    mean, log_std, _ = actor(batch.images, batch.prev_actions, embedding=embedding, obs_mask=batch.obs_mask)
    actions, log_probs = tanh_gaussian_sample(mean, log_std, noise)
    return PolicyOutputs(actions, log_probs, mean, log_std)


def n_step_targets(
    rewards: Tensor, terminated: Tensor, mask: Tensor, soft_v: Tensor, gamma: float, n: int
) -> Tensor:
    """y_t = sum_{k<m} gamma^k r_{t+k} + gamma^m (1 - term_{t+m-1}) V(s_{t+m}), m = min(n, T - t).

    All (B, L); ``soft_v[:, t]`` is V(s_{t+1}) and ``mask`` is a prefix of ones (T real steps). The
    window stops at the episode's end: a terminal step stops the bootstrap, a truncated one
    bootstraps from the last stored observation. Intermediate steps' entropy bonuses are left out
    (as in n-step SAC/D4PG variants); n = 1 is the one-step target exactly."""
    if n == 1:
        return rewards + gamma * (1.0 - terminated) * soft_v
    B, L = rewards.shape
    pad = rewards.new_zeros(B, n - 1)
    win = lambda x: torch.cat([x, pad], 1).unfold(1, n, 1)  # (B, L, n): x_{t..t+n-1}  # noqa: E731
    m_win = win(mask)
    discounts = gamma ** torch.arange(n, dtype=rewards.dtype, device=rewards.device)
    returns = (win(rewards) * m_win * discounts).sum(-1)
    steps = m_win.sum(-1).clamp_min(1.0)  # m
    last = (torch.arange(L, device=rewards.device) + steps.long() - 1).clamp_max(L - 1)  # t + m - 1
    boot = (1.0 - terminated.gather(1, last)) * soft_v.gather(1, last)
    return returns + gamma**steps * boot


def returns_to_go(rewards: Tensor, mask: Tensor, gamma: float) -> Tensor:
    """G_t = sum_{k >= t} gamma^(k - t) mask_k r_k, (B, L): the observed discounted return of each
    step, i.e. the n-step target with a window as long as the batch and nothing to bootstrap from."""
    zeros = torch.zeros_like(rewards)
    return n_step_targets(rewards * mask, zeros, mask, zeros, gamma, rewards.shape[1])


def critic_targets(
    critic_target: nn.Module, batch: Batch, policy: PolicyOutputs, alpha: Tensor | float, gamma: float,
    n_step: int = 1, feats: Tensor | None = None,
) -> Tensor:  # fmt: skip
    """y_t (B, L), without gradient. ``feats``: the target critic's features of the batch, if computed."""
    with torch.no_grad():
        feats = critic_target.features_of(batch) if feats is None else feats
        q1, q2 = critic_target.q(feats[:, 1:], policy.actions[:, 1:].detach())
        soft_v = torch.min(q1, q2) - alpha * policy.log_probs[:, 1:].detach()
        return n_step_targets(batch.rewards, batch.terminated, batch.mask, soft_v, gamma, n_step)


def bounded_targets(targets: Tensor, batch: Batch, gamma: float) -> Tensor:
    """max(y_t, G_t): the target never below what the episode actually earned from step t."""
    return torch.maximum(targets, returns_to_go(batch.rewards, batch.mask, gamma))


def critic_loss(
    critic: nn.Module, batch: Batch, targets: Tensor, feats: Tensor | None = None
) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
    """Twin-Q regression onto ``targets``. Returns (loss, features of all L+1 steps, info).
    ``feats``: the critic's features of this batch if already computed (with gradients)."""
    if feats is None:
        feats = critic.features_of(batch)
    q1, q2 = critic.q(feats[:, :-1], batch.actions)
    loss = masked_mean((q1 - targets).pow(2), batch.mask) + masked_mean((q2 - targets).pow(2), batch.mask)
    info = {"q1": masked_mean(q1.detach(), batch.mask), "q2": masked_mean(q2.detach(), batch.mask)}
    return loss, feats, info


def actor_loss(
    critic: nn.Module, critic_features: Tensor, batch: Batch, policy: PolicyOutputs, alpha: Tensor | float
) -> Tensor:
    """alpha log pi - min Q at the policy's own actions, on real transitions."""
    q1, q2 = critic.q(critic_features[:, :-1].detach(), policy.actions[:, :-1])
    return masked_mean(alpha * policy.log_probs[:, :-1] - torch.min(q1, q2), batch.mask)


def bc_loss(mean: Tensor, batch: Batch, keep: Tensor | None = None) -> Tensor:
    """Squared error between tanh(mean) ((B, L+1, 5), the policy's pre-tanh mean) and the recorded
    action, summed over action dims, averaged over the demonstration transitions of the batch (0 when
    it holds none). ``keep`` (B, L): 1 where a demonstration transition is cloned (``bc_filter``);
    the average stays over all of them, so a filtered-out transition weighs 0, not more on the rest."""
    if batch.demo is None:
        return mean.new_zeros(())
    err = (torch.tanh(mean[:, :-1]) - batch.actions).pow(2).sum(-1)
    demo = batch.mask * batch.demo[:, None]
    kept = err if keep is None else err * keep
    return (kept * demo).sum() / demo.sum().clamp_min(1.0)


@dataclass(frozen=True)
class DemoCritique:
    """What the critic says on the batch's demonstration transitions (no gradient).

    ``keep`` is the Q filter: 1 where min Q(h, a_demo) > min Q(h, tanh(mean)). ``rank_gap`` is the
    mean of Q(h, a_demo) - Q(h, g a_demo), g a quarter turn of (dx, dy): how well the critic tells
    the demonstrated move from the same move turned away (0: it cannot rank them)."""

    keep: Tensor  # (B, L)
    accept: Tensor  # () share of demonstration transitions kept
    rank_gap: Tensor  # ()
    pi_gap: Tensor  # () mean Q(h, a_demo) - Q(h, tanh(mean))


def critique_demos(critic: nn.Module, feats: Tensor, batch: Batch, mean: Tensor) -> DemoCritique | None:
    """``DemoCritique`` of the batch from critic features ``feats`` (B, L+1, F); None without demos."""
    if batch.demo is None:
        return None
    demo = batch.mask * batch.demo[:, None]
    with torch.no_grad():
        f = feats[:, :-1].detach()
        q_demo = torch.min(*critic.q(f, batch.actions))
        q_pi = torch.min(*critic.q(f, torch.tanh(mean[:, :-1].detach())))
        a = batch.actions
        turned = torch.stack([a[..., 0], -a[..., 2], a[..., 1], a[..., 3], a[..., 4]], -1)
        q_turned = torch.min(*critic.q(f, turned))
        keep = (q_demo > q_pi).to(q_demo.dtype)
        return DemoCritique(keep, masked_mean(keep, demo), masked_mean(q_demo - q_turned, demo),
                            masked_mean(q_demo - q_pi, demo))  # fmt: skip


def alpha_loss(log_alpha: Tensor, log_probs: Tensor, mask: Tensor, target_entropy: float) -> Tensor:
    return -log_alpha * masked_mean(log_probs.detach() + target_entropy, mask)


def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- (1 - tau) target + tau source, parameters and floating buffers."""
    with torch.no_grad():
        for t, s in zip(target.parameters(), source.parameters(), strict=True):
            t.lerp_(s, tau)
        for t, s in zip(target.buffers(), source.buffers(), strict=True):
            if t.is_floating_point():
                t.lerp_(s, tau)
            else:
                t.copy_(s)


Grads = tuple[Tensor | None, ...]


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
        self, actor: nn.Module, critic: nn.Module, settings: SacSettings, device: torch.device | str = "cpu"
    ) -> None:
        self.s = settings
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
        self.actor_opt = torch.optim.Adam(self._actor_params, lr=settings.lr)
        self.critic_opt = torch.optim.Adam(self._critic_params, lr=settings.lr)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=settings.alpha_lr)
        self.updates = 0

    @property
    def alpha(self) -> Tensor:
        return self.log_alpha.detach().exp()

    def update(self, batch: Batch) -> dict[str, float]:
        """``update_tensors``, its statistics read as floats."""
        return {k: float(v) for k, v in self.update_tensors(batch).items()}

    def update_tensors(self, batch: Batch) -> dict[str, Tensor | float]:
        """One update: critic, actor (SAC term, plus the BC term where on), alpha, target critic;
        its statistics as 0-d tensors on the device (``bc_weight`` a float), never read here.

        The BC term's gradient is taken apart from the SAC actor term's, so both norms are reported
        (which of them steers the actor). With a shared encoder the BC term also trains the encoder,
        beside the critic loss (a sparse-reward critic alone shapes it too slowly)."""
        s, alpha = self.s, self.alpha
        w = s.bc_weight_at(self.updates)
        feats = embedding = None
        if s.share_encoder:
            feats, _ = self.critic.features(batch.images, batch.prev_actions, obs_mask=batch.obs_mask)
            embedding = feats[..., -self.critic.cfg.image_embed :]
        policy = policy_outputs(
            self.actor, batch, embedding=None if embedding is None else embedding.detach()
        )
        with torch.no_grad():
            target_feats = self.critic_target.features_of(batch)
        targets = critic_targets(self.critic_target, batch, policy, alpha, s.gamma, s.n_step, target_feats)
        if s.return_bound:
            targets = bounded_targets(targets, batch, s.gamma)
        critique = critique_demos(self.critic_target, target_feats, batch, policy.mean)

        # losses
        q_loss, feats, info = critic_loss(self.critic, batch, targets, feats)
        b_loss = bc_mean = None
        if w > 0:
            # with a shared encoder the BC term needs the actor pass on the live (undetached) embedding
            bc_mean = policy.mean if embedding is None else self.actor(batch.images, batch.prev_actions,
                                                                        embedding=embedding)[0]  # fmt: skip
            keep = critique.keep if (s.bc_filter and critique is not None) else None
            b_loss = bc_loss(bc_mean, batch, keep)

        # critic (and the shared encoder: the BC term's share of it)
        critic_objective = q_loss if (b_loss is None or embedding is None) else q_loss + w * b_loss
        bc_actor_grads: Grads = ()
        if b_loss is not None:
            bc_actor_grads = _grads(w * b_loss, self._actor_params, retain=True)
        _step(self.critic_opt, critic_objective, self._critic_params)

        # actor: SAC term through the just-updated Q heads, plus the BC gradient
        pi_loss = actor_loss(self.critic, feats, batch, policy, alpha)
        pi_grads = _grads(pi_loss, self._actor_params)
        _apply(self.actor_opt, self._actor_params, pi_grads, bc_actor_grads)

        # temperature and target critic
        log_probs = policy.log_probs[:, :-1]
        a_loss = alpha_loss(self.log_alpha, log_probs, batch.mask, s.target_entropy)
        if s.autotune_alpha:
            _step(self.alpha_opt, a_loss, [self.log_alpha])
        soft_update(self.critic_target, self.critic, s.tau)
        self.updates += 1

        out: dict[str, Tensor | float] = {
            "critic_loss": q_loss.detach(),
            "actor_loss": pi_loss.detach(),
            "alpha_loss": a_loss.detach(),
            "alpha": self.alpha,
            "q1": info["q1"],
            "q2": info["q2"],
            "target_q": masked_mean(targets, batch.mask),
            "entropy": -masked_mean(log_probs.detach(), batch.mask),
            "actor_grad_norm": _norm(pi_grads),
        }
        if critique is not None:
            out |= {
                "bc_accept": critique.accept,
                "q_rank_gap": critique.rank_gap,
                "q_demo_minus_pi": critique.pi_gap,
            }
        if b_loss is not None:
            out |= {"bc_loss": b_loss.detach(), "bc_weight": w, "bc_grad_norm": _norm(bc_actor_grads)}
        return out

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
