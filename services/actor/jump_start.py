"""Jump-start episodes (JSRL, Uchendu et al. 2022): a learned episode that first replays one of the
run's own demonstrations up to a drawn step, then hands over to the policy.

Why: a demonstration's later states are states the policy does not reach from the reset by itself,
so no episode of its own ever checks its critic's value there (`mea bench critic --handover`
measured critics 0.3-0.7 above what their policy then achieved). Starting some episodes from those
states lets the policy's own successes and failures correct the critic where the demonstrations
lead. Only the run's demonstrations are replayed: the same expert on the same seeds makes them
again, action for action, so no expert knowledge enters beyond what the run already recorded."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from services.actor.config import ActorConfig
from services.actor.rollout import RolloutActor
from services.tasks import ManipulationEnv


@dataclass(frozen=True)
class Demo:
    """A demonstration to jump-start from: the seed its env was reset with and its actions."""

    seed: int
    actions: np.ndarray  # (T, action_dim)


@dataclass(frozen=True)
class JumpStart:
    """Which demonstration, and how many of its steps to replay before the policy acts."""

    demo: Demo
    replayed: int


LEFT_BINS = ((1, 2), (3, 4), (5, 8), (9, 12), (13, None))
"""Bins of the demonstration steps left at the handover, for the actor's charts: the last steps
(the pull or the lift itself) apart from the approach."""


def left_bin(left: int) -> str:
    """The chart suffix of ``left`` demonstration steps left at the handover: ``1-2`` .. ``13+``."""
    for lo, hi in LEFT_BINS:
        if left >= lo and (hi is None or left <= hi):
            return f"{lo}+" if hi is None else f"{lo}-{hi}"
    raise ValueError(f"a jump start leaves the demonstration 1 or more steps, not {left}")


def first_sitting(cfg: ActorConfig) -> ActorConfig:
    """The config under which actor 0 recorded the run's demonstrations: index 0, its first
    incarnation, one env, the first sitting's seed base (``jump_start_seed_base``)."""
    return dataclasses.replace(
        cfg, index=0, incarnation=0, envs=1, seed_base=cfg.jump_start_seed_base, demos=cfg.jump_start_demos
    )


def regenerate(cfg: ActorConfig, env: ManipulationEnv, instance: str) -> list[Demo]:
    """The run's demonstrations made again on ``env`` as actor 0 made them in the first sitting
    (``first_sitting``): the same expert episodes in the same order, failures skipped, within the
    same number of attempts. Nothing is published."""
    actor = RolloutActor(first_sitting(cfg), instance, env)
    n = actor.cfg.demos
    attempts = actor.demonstrations(n, n * actor.cfg.max_demo_attempts)
    return [Demo(int(b.meta["seed"]), np.stack(b.actions)) for b in attempts if b.success]


def draw(rng: np.random.Generator, demos: list[Demo], share: float) -> JumpStart | None:
    """With probability ``share``, a jump start: a demonstration drawn uniformly and a handover step
    drawn uniformly from 1 .. T-1 (at least one replayed step and one step left to the policy;
    JSRL's random switching, which needs no success threshold per stage). None: a plain episode."""
    usable = [d for d in demos if len(d.actions) >= 2]
    if not usable or rng.random() >= share:
        return None
    demo = usable[int(rng.integers(len(usable)))]
    return JumpStart(demo, int(rng.integers(1, len(demo.actions))))


__all__ = ["LEFT_BINS", "Demo", "JumpStart", "draw", "first_sitting", "left_bin", "regenerate"]
