"""Recurrent SAC's losses (Equi-RSAC) over whole padded episodes, as pure functions.

The critic, actor, temperature (alpha) and behaviour-cloning losses over B episodes padded to L
transitions (``mask``), each sequence encoded once.

Design notes: docs/architecture-notes.md, services/algorithms/sac/losses.py."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
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
    real_images: Tensor | None = None  # (N, C, H, W) images[obs_mask], channels_last (CPU: gathered once)

    @property
    def prev_actions(self) -> Tensor:
        """(B, L+1, A): a_{t-1} beside observation t, zeros at t = 0."""
        a = self.actions
        return torch.cat([torch.zeros_like(a[:, :1]), a], dim=1)


def gathered(batch: Batch) -> dict[str, Tensor]:
    """``real_images=`` for a network's call where the batch has them (networks that do not take
    them, e.g. the tests' small ones, are then never passed the argument)."""
    return {} if batch.real_images is None else {"real_images": batch.real_images}


# ------------------------------------------------------------------------------------------------
# tanh-Gaussian policy distribution
# ------------------------------------------------------------------------------------------------

XY = slice(1, 3)
"""(dx, dy) in (jaw, dx, dy, dz, dtheta)."""
_R_MIN = 1e-6  # |u_xy| floor: the radial map's tanh(r) / r is 1 there, and r stays differentiable
_DISC = 1.0 - 2.0**-20  # the disc's radius: float32's tanh rounds to 1 from r ~ 9, and a copy of an
# action on the circle itself could round out of [-1, 1] when turned


def _tanh_log_det(u: Tensor) -> Tensor:
    """log(1 - tanh(u)^2) elementwise, in the stable form 2 (log 2 - u - softplus(-2u))."""
    return 2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))


def _radius(xy: Tensor) -> Tensor:
    return xy.pow(2).sum(-1).add(_R_MIN**2).sqrt()


def squash(u: Tensor, disc: bool = False) -> Tensor:
    """The action of a pre-squash value u (..., 5): tanh of each dimension, or with ``disc`` the pair
    (dx, dy) through the radial tanh c u tanh(|u|) / |u| instead, onto the open disc of radius c just
    below 1. Every rotation
    maps the disc onto itself, so a copy of a disc action turned by any angle is an action the policy
    could have taken (the box fits only quarter turns of actions near its corners)."""
    a = torch.tanh(u)
    if not disc:
        return a
    r = _radius(u[..., XY])
    xy = u[..., XY] * (_DISC * torch.tanh(r) / r)[..., None]
    return torch.cat([a[..., :1], xy, a[..., 3:]], -1)


def squash_log_det(u: Tensor, disc: bool = False) -> Tensor:
    """log |det da/du| of ``squash`` at u, summed over the action (...). The radial map's Jacobian
    has eigenvalues c tanh'(r) (along u_xy) and c tanh(r) / r (across it)."""
    per_dim = _tanh_log_det(u)
    if not disc:
        return per_dim.sum(-1)
    r = _radius(u[..., XY])
    radial = _tanh_log_det(r) + torch.log(torch.tanh(r) / r) + 2.0 * math.log(_DISC)
    return per_dim[..., :1].sum(-1) + radial + per_dim[..., 3:].sum(-1)


def unsquash(action: Tensor, disc: bool = False, bound: float = 0.999) -> Tensor:
    """The pre-squash u of a given action, the action first clamped inside the range (each
    dimension to +-``bound``; with ``disc`` the (dx, dy) norm to ``bound``), so recorded actions at
    the range's edge stay finite."""
    a = action.clamp(-bound, bound)
    u = torch.atanh(a)
    if not disc:
        return u
    xy = action[..., XY]
    rho = xy.pow(2).sum(-1).sqrt().clamp_min(_R_MIN)
    scale = torch.atanh(rho.clamp_max(bound) / _DISC) / rho  # clamps the norm and inverts
    return torch.cat([u[..., :1], xy * scale[..., None], u[..., 3:]], -1)


def tanh_gaussian_sample(
    mean: Tensor,
    log_std: Tensor,
    noise: Tensor | None = None,
    generator: torch.Generator | None = None,
    disc: bool = False,
) -> tuple[Tensor, Tensor]:
    """Reparameterised sample a = squash(mean + std * eps) and its log-density (summed over the last
    axis): log pi(a) = sum_k log N(u_k; mean_k, std_k) - log |det da/du| (``squash_log_det``)."""
    log_std = log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)
    if noise is None:
        noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
    std = log_std.exp()
    u = mean + std * noise
    log_normal = -0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
    if disc:
        return squash(u, disc), log_normal.sum(-1) - squash_log_det(u, disc)
    # the box's terms inline, as they were: tests/unit/test_update_hashes.py pins their bits
    log_jac = 2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))
    return torch.tanh(u), (log_normal - log_jac).sum(-1)


def tanh_gaussian_log_prob(
    mean: Tensor, log_std: Tensor, action: Tensor, bound: float = 0.999, disc: bool = False
) -> Tensor:
    """log pi(a) of a given action a = squash(u) under the tanh-Gaussian (summed over the last axis),
    a clamped inside the range first (``unsquash``)."""
    log_std = log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)
    a = action.clamp(-bound, bound)
    u = unsquash(action, disc, bound) if disc else torch.atanh(a)
    z = (u - mean) * torch.exp(-log_std)
    log_normal = -0.5 * z.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
    if disc:
        return log_normal.sum(-1) - squash_log_det(u, disc)
    return (log_normal - torch.log1p(-a.pow(2))).sum(-1)


def deterministic_action(mean: Tensor, disc: bool = False) -> Tensor:
    """Evaluation action: the squashed mean."""
    return squash(mean, disc)


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
    disc: bool = False  # the (dx, dy) range of ``squash``


def policy_outputs(
    actor: nn.Module,
    batch: Batch,
    noise: Tensor | None = None,
    embedding: Tensor | None = None,
    disc: bool = False,
) -> PolicyOutputs:
    """One actor pass: samples, log-probs, mean and log std at every observation; ``disc``: the
    actor's (dx, dy) range (``squash``)."""
    mean, log_std, _ = actor(
        batch.images, batch.prev_actions, embedding=embedding, obs_mask=batch.obs_mask, **gathered(batch)
    )
    actions, log_probs = tanh_gaussian_sample(mean, log_std, noise, disc=disc)
    return PolicyOutputs(actions, log_probs, mean, log_std, disc)


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


def min_q(qs: Sequence[Tensor]) -> Tensor:
    """The elementwise minimum over a critic's heads (``torch.min`` of the twin's two)."""
    return functools.reduce(torch.minimum, qs)


def subset_min_q(qs: Sequence[Tensor], subset: int | None) -> Tensor:
    """``min_q`` over ``subset`` heads drawn at random for the whole batch (REDQ, Chen et al. 2021),
    or over all of them (``subset`` None or >= their count: the twin's rule, SAC-N's for more). The
    draw reads torch's generator only where it chooses, with torch.rand, which a CUDA graph replays."""
    if subset is None or subset >= len(qs):
        return min_q(qs)
    stacked = torch.stack(tuple(qs))
    drawn = torch.rand(len(qs), device=stacked.device).argsort()[:subset]
    return stacked.index_select(0, drawn).amin(0)


def critic_targets(
    critic_target: nn.Module, batch: Batch, policy: PolicyOutputs, alpha: Tensor | float, gamma: float,
    n_step: int = 1, feats: Tensor | None = None, backup_entropy: bool = True, target_heads: int | None = None,
) -> Tensor:  # fmt: skip
    """y_t (B, L), without gradient. ``feats``: the target critic's features of the batch, if computed;
    ``backup_entropy`` False: V(s') is min Q alone, without the entropy bonus -alpha log pi;
    ``target_heads``: the min is over that many heads drawn at random (``subset_min_q``)."""
    with torch.no_grad():
        feats = critic_target.features_of(batch) if feats is None else feats
        soft_v = subset_min_q(critic_target.q(feats[:, 1:], policy.actions[:, 1:].detach()), target_heads)
        if backup_entropy:
            soft_v = soft_v - alpha * policy.log_probs[:, 1:].detach()
        return n_step_targets(batch.rewards, batch.terminated, batch.mask, soft_v, gamma, n_step)


def bounded_targets(targets: Tensor, batch: Batch, gamma: float) -> Tensor:
    """max(y_t, G_t): the target never below what the episode actually earned from step t."""
    return torch.maximum(targets, returns_to_go(batch.rewards, batch.mask, gamma))


def critic_loss(
    critic: nn.Module, batch: Batch, targets: Tensor, feats: Tensor | None = None
) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
    """Every Q head's regression onto ``targets``, summed. Returns (loss, features of all L+1 steps,
    info: the first two heads' mean Q). ``feats``: the critic's features of this batch if already
    computed (with gradients)."""
    if feats is None:
        feats = critic.features_of(batch)
    qs = critic.q(feats[:, :-1], batch.actions)
    loss = functools.reduce(torch.add, (masked_mean((q - targets).pow(2), batch.mask) for q in qs))
    info = {"q1": masked_mean(qs[0].detach(), batch.mask), "q2": masked_mean(qs[1].detach(), batch.mask)}
    return loss, feats, info


CONSERVATIVE_ACTIONS = 4
"""Uniform random actions per transition in the conservative term, beside the policy's sample."""


def conservative_gap(
    critic: nn.Module, feats: Tensor, batch: Batch, policy_actions: Tensor, random_actions: int,
    floor: Tensor | None = None,
) -> Tensor:  # fmt: skip
    """CQL's term (Kumar et al. 2020), summed over the Q heads: the masked mean of logsumexp over
    ``random_actions`` uniform actions and the policy's sampled one, less log of their count, minus
    Q of the replayed action. Descending it lowers the values of actions no episode tried relative
    to the one tried, so an actor cannot climb the critic into them. Without CQL's importance
    weights (the sampled set is small, and a Q in [0, 1] keeps the softmax close to uniform).
    ``feats``: the critic's features (L+1 steps, with gradients); ``policy_actions`` (B, L, A).
    ``floor`` (B, L): Cal-QL's calibration (Nakamoto et al. 2023), the policy's sampled action's Q
    taken as at least this (the replayed episode's return-to-go), so the term never pushes the
    policy's values below what the data's own actions earned from there."""
    h = feats[:, :-1]
    a = batch.actions
    draws = [torch.rand_like(a) * 2 - 1 for _ in range(random_actions)]
    tried = critic.q(h, a)
    policy_q = critic.q(h, policy_actions.detach())
    if floor is not None:
        policy_q = tuple(torch.maximum(q, floor) for q in policy_q)
    others = [*(critic.q(h, x) for x in draws), policy_q]
    log_n = math.log(random_actions + 1)
    gap = sum(
        torch.logsumexp(torch.stack([o[i] for o in others]), 0) - log_n - tried[i] for i in range(len(tried))
    )
    return masked_mean(gap, batch.mask)


def actor_loss(
    critic: nn.Module, critic_features: Tensor, batch: Batch, policy: PolicyOutputs, alpha: Tensor | float
) -> Tensor:
    """alpha log pi - min Q over every head at the policy's own actions, on real transitions."""
    q = min_q(critic.q(critic_features[:, :-1].detach(), policy.actions[:, :-1]))
    return masked_mean(alpha * policy.log_probs[:, :-1] - q, batch.mask)


CRR_MAX_WEIGHT = 20.0
"""Cap of exp(A / beta): one transition never outweighs the batch (Wang et al. 2020 cap at 20)."""


@dataclass(frozen=True)
class ActionValues:
    """A critic's min-Q of each replayed action and of the policy's mean action at the same step,
    (B, L), no gradient: read by the Q filter and the critique (``critique_demos``) and by CRR."""

    replayed: Tensor  # min Q(h_t, a_t)
    policy: Tensor  # min Q(h_t, squash(mean_t))

    @property
    def advantage(self) -> Tensor:
        return self.replayed - self.policy


def action_values(
    critic: nn.Module, feats: Tensor, batch: Batch, mean: Tensor, disc: bool = False
) -> ActionValues:
    """``ActionValues`` from critic features ``feats`` (B, L+1, F) and the policy's pre-squash ``mean``."""
    with torch.no_grad():
        f = feats[:, :-1].detach()
        replayed = min_q(critic.q(f, batch.actions))
        return ActionValues(replayed, min_q(critic.q(f, squash(mean[:, :-1].detach(), disc))))


def crr_weights(values: ActionValues, beta: float) -> Tensor:
    """(B, L) weight of each replayed action, no gradient: with A its advantage over the policy's mean
    action, 1[A > 0] (``beta`` 0) or min(exp(A / beta), ``CRR_MAX_WEIGHT``)."""
    adv = values.advantage
    if beta == 0.0:
        return (adv > 0).to(adv.dtype)
    return torch.exp(adv / beta).clamp_max(CRR_MAX_WEIGHT)


def crr_loss(policy: PolicyOutputs, batch: Batch, weights: Tensor) -> Tensor:
    """-sum_t mask_t w_t log pi(a_t | h_t) / sum_t mask_t: the policy moves only towards replayed actions,
    as far as the critic rates them (never along the critic's gradient into actions it has not seen)."""
    log_probs = tanh_gaussian_log_prob(
        policy.mean[:, :-1], policy.log_std[:, :-1], batch.actions, disc=policy.disc
    )
    return -masked_mean(weights * log_probs, batch.mask)


def bc_loss(mean: Tensor, batch: Batch, keep: Tensor | None = None, disc: bool = False) -> Tensor:
    """Squared error between squash(mean) ((B, L+1, 5), the policy's pre-squash mean) and the recorded
    action, summed over action dims, averaged over the demonstration transitions of the batch (0 when
    it holds none). ``keep`` (B, L): 1 where a demonstration transition is cloned (``bc_filter``);
    the average stays over all of them, so a filtered-out transition weighs 0, not more on the rest."""
    if batch.demo is None:
        return mean.new_zeros(())
    err = (squash(mean[:, :-1], disc) - batch.actions).pow(2).sum(-1)
    demo = batch.mask * batch.demo[:, None]
    kept = err if keep is None else err * keep
    return (kept * demo).sum() / demo.sum().clamp_min(1.0)


@dataclass(frozen=True)
class DemoCritique:
    """What the critic says on the batch's demonstration transitions (no gradient).

    ``keep`` is the Q filter: 1 where min Q(h, a_demo) > min Q(h, squash(mean)). ``rank_gap`` is the
    mean of Q(h, a_demo) - Q(h, g a_demo), g a quarter turn of (dx, dy): how well the critic tells
    the demonstrated move from the same move turned away (0: it cannot rank them). A vertical move
    turns into itself, so on descents and lifts it reads 0 whatever the critic knows:
    ``reverse_gap``, Q(h, a_demo) - Q(h, the move reversed: dx, dy, dz, dtheta negated, jaw kept),
    ranks those too."""

    keep: Tensor  # (B, L)
    accept: Tensor  # () share of demonstration transitions kept
    rank_gap: Tensor  # ()
    reverse_gap: Tensor  # ()
    pi_gap: Tensor  # () mean Q(h, a_demo) - Q(h, squash(mean))


def quarter_turned(a: Tensor) -> Tensor:
    """Actions (..., 5) with (dx, dy) turned a quarter, to (-dy, dx)."""
    return torch.stack([a[..., 0], -a[..., 2], a[..., 1], a[..., 3], a[..., 4]], -1)


def reversed_move(a: Tensor) -> Tensor:
    """Actions (..., 5) moving the other way: dx, dy, dz and dtheta negated, the jaw kept."""
    return torch.cat([a[..., :1], -a[..., 1:]], -1)


def critique_demos(
    critic: nn.Module, feats: Tensor, batch: Batch, values: ActionValues
) -> DemoCritique | None:
    """``DemoCritique`` of the batch from critic features ``feats`` (B, L+1, F) and the same critic's
    ``values`` of them (``action_values``); None without demos."""
    if batch.demo is None:
        return None
    demo = batch.mask * batch.demo[:, None]
    with torch.no_grad():
        a = batch.actions
        q_turned = min_q(critic.q(feats[:, :-1].detach(), quarter_turned(a)))
        q_reversed = min_q(critic.q(feats[:, :-1].detach(), reversed_move(a)))
        keep = (values.advantage > 0).to(values.replayed.dtype)
        return DemoCritique(keep, masked_mean(keep, demo), masked_mean(values.replayed - q_turned, demo),
                            masked_mean(values.replayed - q_reversed, demo),
                            masked_mean(values.advantage, demo))  # fmt: skip


def alpha_loss(
    log_alpha: Tensor, log_probs: Tensor, mask: Tensor, target_entropy: float, form: str
) -> Tensor:
    """-c (log pi + target entropy), c = log alpha (``form`` "log_alpha") or alpha ("alpha")."""
    c = log_alpha.exp() if form == "alpha" else log_alpha
    return -c * masked_mean(log_probs.detach() + target_entropy, mask)


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
