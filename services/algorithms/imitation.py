"""Behaviour cloning of the recurrent actor on the demonstrations in a replay (`mea bench imitation`).

The loss is the learner's own BC term (``sac.bc_loss``: squared error between tanh(mean) and the
recorded action over whole episodes from step 0 with a zero LSTM state), and batches come through
the learner's sampling and tensor path (``SequenceReplay.sample`` + ``to_batch``), so what a clone
reaches measures what the learner's BC term can teach the network from those demos. Pure: no
transport, files or simulator.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from services.algorithms.batch import to_batch
from services.algorithms.networks import disc_xy
from services.algorithms.replay import SequenceReplay
from services.algorithms.sac.losses import Batch, bc_loss, gathered


@dataclass(frozen=True)
class CloneSettings:
    """How batches are drawn and the actor is stepped (the learner preset's fields of the same names)."""

    batch_size: int = 16
    """Whole episodes per update."""
    lr: float = 3e-4
    """Adam learning rate (the learner's actor rate)."""
    demo_fraction: float = 0.0
    """Share of every batch from the demonstration set (``SequenceReplay.sample``)."""
    successes_as_demos: bool = False
    """Successful episodes join the demonstration set."""
    trim: bool = True
    """Pad each batch to its longest episode."""

    def __post_init__(self) -> None:
        if self.batch_size < 1 or self.lr <= 0:
            raise ValueError("batch_size must be >= 1 and lr > 0")


def clone_loss(actor: nn.Module, batch: Batch) -> torch.Tensor:
    """The BC loss of ``actor`` on ``batch``'s demonstration transitions (``sac.bc_loss``)."""
    mean, _, _ = actor(batch.images, batch.prev_actions, obs_mask=batch.obs_mask, **gathered(batch))
    return bc_loss(mean, batch, disc=disc_xy(actor))


class Cloner:
    """An actor, its Adam optimiser and the batches it draws from ``replay``."""

    def __init__(
        self, actor: nn.Module, replay: SequenceReplay, rng: np.random.Generator, settings: CloneSettings
    ) -> None:
        self.actor, self.replay, self.rng, self.s = actor, replay, rng, settings
        self.opt = torch.optim.Adam([p for p in actor.parameters() if p.requires_grad], lr=settings.lr)
        self.updates = 0

    def batch(self) -> Batch:
        """A batch drawn as the learner draws one (same sampler, same tensors)."""
        s = self.s
        sample = self.replay.sample(s.batch_size, self.rng, demo_fraction=s.demo_fraction,
                                    successes_as_demos=s.successes_as_demos, trim=s.trim)  # fmt: skip
        return to_batch(sample)

    def update(self) -> float:
        """One gradient step on a fresh batch; its loss before the step."""
        self.actor.train()
        loss = clone_loss(self.actor, self.batch())
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.updates += 1
        return float(loss.detach())

    def run(
        self, updates: int, every: int = 0, on_progress: Callable[[int, float], None] | None = None
    ) -> list[float]:
        """``updates`` steps; every ``every`` of them (0: never) ``on_progress(updates, mean loss since
        the last call)``. Returns every step's loss."""
        losses: list[float] = []
        for k in range(updates):
            losses.append(self.update())
            if on_progress is not None and every and (k + 1) % every == 0:
                on_progress(self.updates, float(np.mean(losses[-every:])))
        return losses


@torch.no_grad()
def held_loss(actor: nn.Module, batch: Batch) -> float:
    """The BC loss on a fixed ``batch`` (drawn once, e.g. with its own seeded generator), in eval mode:
    the fit tracked without sampling noise between readings."""
    was = actor.training
    actor.eval()
    try:
        return float(clone_loss(actor, batch))
    finally:
        actor.train(was)


__all__ = ["CloneSettings", "Cloner", "clone_loss", "held_loss"]
