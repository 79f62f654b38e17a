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

``RecurrentSAC`` wires the losses into one update (critic, actor, alpha, soft target update).
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
    n_step: int = 1,
) -> Tensor:  # fmt: skip
    """y_t (B, L), without gradient."""
    with torch.no_grad():
        feats = critic_target.features_of(batch)
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


def bc_loss(mean: Tensor, batch: Batch) -> Tensor:
    """Squared error between tanh(mean) ((B, L+1, 5), the policy's pre-tanh mean) and the recorded
    action, summed over action dims, averaged over the demonstration transitions of the batch (0 when
    it holds none)."""
    if batch.demo is None:
        return mean.new_zeros(())
    err = (torch.tanh(mean[:, :-1]) - batch.actions).pow(2).sum(-1)
    return masked_mean(err, batch.mask * batch.demo[:, None])


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


def _step(
    opt: torch.optim.Optimizer, loss: Tensor, params: list[Tensor], extra: tuple[Tensor | None, ...] = ()
) -> None:
    """Gradients of ``loss`` for ``params`` only (others untouched), plus ``extra`` gradients of the
    same parameters computed earlier, then one optimiser step."""
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    for i, (p, g) in enumerate(zip(params, grads, strict=True)):
        e = extra[i] if extra else None
        p.grad = e if g is None else (g if e is None else g + e)
    opt.step()


# ------------------------------------------------------------------------------------------------
# the update
# ------------------------------------------------------------------------------------------------


class RecurrentSAC:
    """Actor, twin critic with a soft-updated target copy, entropy temperature, their optimisers."""

    def __init__(self, actor: nn.Module, critic: nn.Module, settings: SacSettings) -> None:
        self.s = settings
        self.actor, self.critic = actor, critic
        self.critic_target = copy.deepcopy(critic).requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(settings.init_alpha), requires_grad=True)
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
        alpha, w = self.alpha, self.s.bc_weight
        feats = embedding = None
        if self.s.share_encoder:
            feats, _ = self.critic.features(batch.images, batch.prev_actions, obs_mask=batch.obs_mask)
            embedding = feats[..., -self.critic.cfg.image_embed :]
        policy = policy_outputs(
            self.actor, batch, embedding=None if embedding is None else embedding.detach()
        )
        targets = critic_targets(self.critic_target, batch, policy, alpha, self.s.gamma, self.s.n_step)
        if self.s.return_bound:
            targets = bounded_targets(targets, batch, self.s.gamma)
        q_loss, feats, info = critic_loss(self.critic, batch, targets, feats)
        critic_objective, b_loss, actor_bc_grads = q_loss, None, ()
        if w > 0 and embedding is None:
            b_loss = bc_loss(policy.mean, batch)
        elif w > 0:
            # shared encoder: the BC term trains it beside the critic (a sparse-reward critic alone
            # shapes it too slowly for the actor to tell situations apart); the SAC actor loss does not
            mean, _, _ = self.actor(batch.images, batch.prev_actions, embedding=embedding)
            b_loss = bc_loss(mean, batch)
            critic_objective = q_loss + w * b_loss
            actor_bc_grads = torch.autograd.grad(
                w * b_loss, self._actor_params, retain_graph=True, allow_unused=True
            )
        _step(self.critic_opt, critic_objective, self._critic_params)
        pi_loss = actor_loss(self.critic, feats, batch, policy, alpha)
        pi_objective = pi_loss + w * b_loss if b_loss is not None and not actor_bc_grads else pi_loss
        _step(self.actor_opt, pi_objective, self._actor_params, actor_bc_grads)
        log_probs = policy.log_probs[:, :-1]
        a_loss = alpha_loss(self.log_alpha, log_probs, batch.mask, self.s.target_entropy)
        if self.s.autotune_alpha:
            _step(self.alpha_opt, a_loss, [self.log_alpha])
        soft_update(self.critic_target, self.critic, self.s.tau)
        self.updates += 1
        extra = {} if b_loss is None else {"bc_loss": float(b_loss.detach())}
        return extra | {
            "critic_loss": float(q_loss.detach()),
            "actor_loss": float(pi_loss.detach()),
            "alpha_loss": float(a_loss.detach()),
            "alpha": float(self.alpha),
            "q1": float(info["q1"]),
            "q2": float(info["q2"]),
            "target_q": float(masked_mean(targets, batch.mask)),
            "entropy": float(-masked_mean(log_probs.detach(), batch.mask)),
        }

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
