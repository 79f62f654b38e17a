"""What a recurrent SAC critic says along stored episodes, step by step: the value of the recorded
action beside the same move turned a quarter, the move reversed, uniform random actions and the
policy's own mean action, counted from the episode's start or back from its end.

The learner's running diagnostics average such gaps over whole batches; along an episode they tell
where the critic ranks the recorded action (the last steps before a success) and where the actor
has found an action it rates higher than a demonstration's (``policy_mean`` above ``recorded``)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from services.algorithms.networks import disc_xy
from services.algorithms.sac.losses import (
    Batch,
    action_values,
    gathered,
    min_q,
    quarter_turned,
    reversed_move,
)

COLUMNS = ("recorded", "turned", "reversed", "random", "policy_mean")
"""The actions rated at each step (min over the Q heads): the recorded one; its (dx, dy) turned a
quarter; its move reversed (dx, dy, dz, dtheta negated, jaw kept); uniform random actions in the
box (the mean over ``random_actions`` draws); the policy's squashed mean."""

TARGET_COLUMNS = ("live", "target")
"""Optional columns beside ``COLUMNS``: the live critic's min-Q of the recorded action (the profiled
critic is usually the target copy, which trails it by its soft update), and the learner's TD target
for that transition, what the live critic is regressed onto (``target - live``: how far it lags)."""

Targets = Callable[[Batch], Tensor]
"""The learner's critic targets of a batch, (B, L) (``RecurrentSAC.td_targets``)."""


@dataclass(frozen=True)
class StepProfile:
    """Per step index (``steps[i]``: t from the start, or k back from the end, 1 = the last
    transition), the transitions seen and the mean of each column and of the reward."""

    steps: tuple[int, ...]
    from_end: bool
    counts: np.ndarray  # (K,) int
    values: dict[str, np.ndarray]  # column -> (K,), NaN where no transition
    rewards: np.ndarray  # (K,)


@torch.no_grad()
def column_values(
    actor: nn.Module,
    critic: nn.Module,
    batch: Batch,
    random_actions: int,
    generator: torch.Generator,
    live: nn.Module | None = None,
    targets: Targets | None = None,
) -> dict[str, Tensor]:
    """Each column's min-Q at every transition of ``batch``: column -> (B, L). The recorded and
    policy-mean columns are the learner's own ``action_values`` (its Q filter and critique); with
    ``live`` and ``targets``, the ``TARGET_COLUMNS`` too."""
    feats = critic.features_of(batch)
    mean = actor(batch.images, batch.prev_actions, obs_mask=batch.obs_mask, **gathered(batch))[0]
    values = action_values(critic, feats, batch, mean, disc_xy(actor))
    a = batch.actions

    def q(actions: Tensor) -> Tensor:
        return min_q(critic.q(feats[:, :-1], actions))

    draws = [
        q(torch.rand(a.shape, generator=generator, dtype=a.dtype) * 2 - 1) for _ in range(random_actions)
    ]
    out = {
        "recorded": values.replayed,
        "turned": q(quarter_turned(a)),
        "reversed": q(reversed_move(a)),
        "random": torch.stack(draws).mean(0),
        "policy_mean": values.policy,
    }
    if live is not None:
        out["live"] = min_q(live.q(live.features_of(batch)[:, :-1], a))
    if targets is not None:
        out["target"] = targets(batch)
    return out


def step_profile(
    actor: nn.Module,
    critic: nn.Module,
    batches: Iterable[Batch],
    *,
    steps: int,
    from_end: bool,
    random_actions: int = 8,
    seed: int = 0,
    live: nn.Module | None = None,
    targets: Targets | None = None,
) -> StepProfile:
    """``column_values`` of every batch, averaged per step index over the first ``steps`` indices
    (from the start, or back from each episode's end with ``from_end``); ``values`` holds
    ``COLUMNS`` and, with ``live`` or ``targets``, their ``TARGET_COLUMNS``."""
    if steps < 1 or random_actions < 1:
        raise ValueError(f"steps and random_actions must be >= 1, got {steps} and {random_actions}")
    generator = torch.Generator().manual_seed(seed)
    counts = np.zeros(steps, np.int64)
    columns = (
        *COLUMNS,
        *(["live"] if live is not None else []),
        *(["target"] if targets is not None else []),
    )
    sums = {c: np.zeros(steps) for c in columns}
    reward_sums = np.zeros(steps)
    for batch in batches:
        values = {
            c: v.cpu().numpy()
            for c, v in column_values(actor, critic, batch, random_actions, generator, live, targets).items()
        }
        rewards = batch.rewards.cpu().numpy()
        lengths = batch.mask.sum(1).cpu().numpy().astype(int)
        for e, length in enumerate(lengths):
            idx = np.arange(min(steps, length))
            t = length - 1 - idx if from_end else idx  # k = idx + 1 steps back: transition length - k
            counts[idx] += 1
            reward_sums[idx] += rewards[e, t]
            for c in columns:
                sums[c][idx] += values[c][e, t]
    with np.errstate(invalid="ignore", divide="ignore"):
        means = {c: np.where(counts > 0, sums[c] / counts, np.nan) for c in columns}
        rewards_mean = np.where(counts > 0, reward_sums / counts, np.nan)
    labels = tuple(range(1, steps + 1)) if from_end else tuple(range(steps))
    return StepProfile(labels, from_end, counts, means, rewards_mean)


__all__ = ["COLUMNS", "TARGET_COLUMNS", "StepProfile", "Targets", "column_values", "step_profile"]
