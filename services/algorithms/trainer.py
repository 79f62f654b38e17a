"""The learner's training step and replay-gate arithmetic, for any algorithm (``algorithm``): its
replay, the rate limiter and its learner, nothing else.

Design notes: docs/architecture-notes.md, services/algorithms/trainer.py."""

from __future__ import annotations

from collections.abc import Mapping
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
import torch

from proto.control import ReplayGate
from services.algorithms.algorithm import Algorithm, AlgorithmConfig, Replay
from services.algorithms.rate_limiter import RateLimiter

if TYPE_CHECKING:
    from proto.episode import Episode


def allowed_steps(inserted: int, inserts_allowed: int, max_env_steps: int = 0) -> int:
    """Total env steps producers may have inserted before they wait: the ``inserted`` ones plus what
    the limiter still allows (``inserts_allowed``, never counted below 0), capped at the run's budget
    ``max_env_steps`` (0: none) but never below what is already in."""
    allowed = inserted + max(0, inserts_allowed)
    if max_env_steps:
        allowed = max(inserted, min(allowed, max_env_steps))
    return allowed


@dataclass(frozen=True)
class GateReading:
    """One consistent reading of the replay and the limiter, for the replay gate and its metrics."""

    inserted: int
    """Raw env steps inserted (the limiter's inserts)."""
    allowed: int
    """``allowed_steps``: env steps producers may have inserted in total before they wait."""
    samples_allowed: int
    """Updates the limiter allows now."""
    can_sample: bool
    """Whether the limiter allows an update now."""
    replay_transitions: int
    replay_episodes: int
    updates: int
    """Gradient updates done."""

    @property
    def inserts_allowed(self) -> int:
        """Env steps producers may still add before waiting."""
        return self.allowed - self.inserted

    def message(self, learner_id: str, run_id: str, policy_version: int, created_at: float) -> ReplayGate:
        """The ``ReplayGate`` that announces this reading."""
        return ReplayGate(
            learner_id=learner_id,
            run_id=run_id,
            inserted_steps=self.inserted,
            allowed_steps=self.allowed,
            updates=self.updates,
            policy_version=policy_version,
            replay_transitions=self.replay_transitions,
            created_at=created_at,
        )


class Schedule(Protocol):
    """What the trainer reads of the learner's settings, where they are (``LearnerConfig`` is one:
    nothing is copied, and each setting is checked once, there). Read only."""

    batch_size: int
    """Episodes (SAC) or windows (GASv2) per update."""
    demo_fraction: float
    """Share of every batch drawn from the demonstration set (0: uniform)."""
    successes_as_demos: bool
    """Episodes that succeeded join the demonstration set."""
    publish_every: int
    """New weights are due every this many updates."""
    max_env_steps: int
    """Env-step budget of the run: the gate never allows more (0: none)."""
    max_updates: int
    """The trainer is done after this many updates (0: never)."""
    metrics_every: int
    """Read the update statistics from the device every this many updates, as means over them
    (``MetricsWindow``); 1 reads each update's (the CPU: no device to wait for)."""


class MetricsWindow:
    """Update statistics summed where they are (0-d tensors stay on their device: adding them queues
    work, it does not wait for it) and read as means on demand, the one wait for the device."""

    def __init__(self) -> None:
        self._sums: dict[str, torch.Tensor | float] = {}
        self._counts: dict[str, int] = {}

    def add(self, info: Mapping[str, torch.Tensor | float]) -> None:
        for k, v in info.items():
            v = v.detach() if isinstance(v, torch.Tensor) else float(v)
            self._sums[k] = v if k not in self._sums else self._sums[k] + v
            self._counts[k] = self._counts.get(k, 0) + 1

    def read(self) -> dict[str, float]:
        """The mean of each statistic since the last read (those never added are absent); clears."""
        out = {k: float(total) / self._counts[k] for k, total in self._sums.items()}
        self._sums.clear()
        self._counts.clear()
        return out


class Trainer:
    """One learner's replay, limiter and algorithm, driven one insert, gate reading or update at a time.

    ``config`` says how batches are drawn and made (``AlgorithmConfig.sample``, ``to_batch``);
    ``agent`` is what it built to learn (``Algorithm``: ``update``, ``state_dict`` for the checkpoint,
    ``updates`` its count)."""

    def __init__(
        self,
        config: AlgorithmConfig,
        agent: Algorithm,
        replay: Replay,
        limiter: RateLimiter,
        rng: np.random.Generator,
        schedule: Schedule,
        guard: AbstractContextManager[object] | None = None,
    ) -> None:
        self.config, self.agent, self.replay, self.limiter, self.rng = config, agent, replay, limiter, rng
        self.schedule = schedule
        self.metrics_every = schedule.metrics_every
        self.guard = guard if guard is not None else nullcontext()
        self.window = MetricsWindow()

    def policy_tensors(self) -> dict[str, np.ndarray]:
        """The published part (a WeightsBlob's tensors), on the CPU."""
        return self.agent.policy_tensors()

    @property
    def env_steps(self) -> int:
        """Raw env steps inserted: the limiter's inserts (augmented copies are not counted)."""
        return self.limiter.inserts

    @property
    def updates(self) -> int:
        return self.agent.updates

    def insert(self, ep: Episode) -> None:
        """Store ``ep``; a raw episode's steps count as env steps for the limiter.

        Raises ``ValueError`` (the replay and the limiter unchanged) if the replay refuses it.
        """
        with self.guard:
            self.replay.insert_episode(ep)
            if ep.augmentation is None:
                self.limiter.inserted(ep.num_steps)

    def gate(self) -> GateReading:
        with self.guard:
            inserted = self.limiter.inserts
            return GateReading(
                inserted=inserted,
                allowed=allowed_steps(inserted, self.limiter.inserts_allowed(), self.schedule.max_env_steps),
                samples_allowed=self.limiter.samples_allowed(),
                can_sample=self.limiter.can_sample(),
                replay_transitions=len(self.replay),
                replay_episodes=self.replay.num_episodes,
                updates=self.agent.updates,
            )

    def step(self) -> dict[str, float] | None:
        """One update on a freshly drawn batch if the limiter allows it now (None otherwise): the
        update's losses and statistics, plus the batch's demonstration share and rewarded transitions.

        With ``metrics_every`` N > 1 the losses and statistics come every N-th update only (by the
        update count), as means over the updates since the last read (``MetricsWindow``); the other
        updates give the batch's two numbers alone."""
        s = self.schedule
        with self.guard:
            ready = self.replay.num_episodes > 0 and self.limiter.can_sample()
            sample = (
                self.config.sample(self.replay, s.batch_size, self.rng, s.demo_fraction, s.successes_as_demos)
                if ready
                else None
            )
        if sample is None:
            return None
        batch = self.config.to_batch(sample, self.agent.device)
        if self.metrics_every == 1:
            info = self.agent.update(batch)
        else:
            self.window.add(self.agent.update_tensors(batch))
            info = self.window.read() if self.agent.updates % self.metrics_every == 0 else {}
        info["batch_demo_share"] = sample.demo_share
        info["batch_reward_transitions"] = sample.reward_transitions
        with self.guard:
            self.limiter.sampled()
        return info

    def publish_due(self) -> bool:
        """Whether the update just done completes a ``publish_every`` period."""
        return self.agent.updates % self.schedule.publish_every == 0

    def done(self) -> bool:
        return self.schedule.max_updates > 0 and self.agent.updates >= self.schedule.max_updates
