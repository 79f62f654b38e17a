"""GASv2's training step behind the learner service's trainer interface (``core.trainer.Trainer``:
insert, gate, step, publish_due, done; the same limiter and replay gate): episodes go into the
window replay (``chunk_replay.ChunkReplay``), each update draws ``batch_size`` windows of
``chunk_length`` observations and runs one world-model + imagination update (``agent.GasV2Agent``).
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import TYPE_CHECKING

import numpy as np

from services.learner.core.gasv2.agent import GasV2Agent
from services.learner.core.gasv2.chunk_replay import ChunkReplay, to_chunk_batch
from services.learner.core.policy import actor_tensors
from services.learner.core.rate_limiter import RateLimiter
from services.learner.core.trainer import Trainer, TrainerSettings

if TYPE_CHECKING:
    from proto.episode import Episode


class GasV2Trainer(Trainer):
    """A ``Trainer`` whose agent is GASv2 and whose replay hands out windows."""

    agent: GasV2Agent  # type: ignore[assignment]

    def __init__(
        self,
        agent: GasV2Agent,
        replay: ChunkReplay,
        limiter: RateLimiter,
        rng: np.random.Generator,
        settings: TrainerSettings,
        chunk_length: int,
        guard: AbstractContextManager[object] | None = None,
    ) -> None:
        super().__init__(agent, replay, limiter, rng, settings, guard)  # type: ignore[arg-type]
        self.chunk_length = chunk_length

    def policy_tensors(self) -> dict[str, np.ndarray]:
        """The published part: the latent policy (encoder, RSSM, actor), not the decoder, heads or critic."""
        return actor_tensors(self.agent.policy)

    def insert(self, ep: Episode) -> None:
        """Store ``ep``; ValueError (replay and limiter unchanged) if the window replay refuses it."""
        with self.guard:
            self.replay.insert_episode(ep)  # type: ignore[attr-defined]
            if ep.augmentation is None:
                self.limiter.inserted(ep.num_steps)

    def step(self) -> dict[str, float] | None:
        s = self.settings
        with self.guard:
            ready = self.replay.num_episodes > 0 and self.limiter.can_sample()
            sample = (
                self.replay.sample_chunks(  # type: ignore[attr-defined]
                    s.batch_size,
                    self.chunk_length,
                    self.rng,
                    demo_fraction=s.demo_fraction,
                    successes_as_demos=s.successes_as_demos,
                )
                if ready
                else None
            )
        if sample is None:
            return None
        info = self.agent.update(to_chunk_batch(sample, self.agent.device))
        info["batch_demo_share"] = float(np.mean(sample.demo))
        info["batch_reward_transitions"] = float((sample.rewards > 0).sum())
        with self.guard:
            self.limiter.sampled()
        return info
