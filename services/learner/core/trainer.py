"""The learner's training step and replay-gate arithmetic: replay, rate limiter and SAC, nothing else.

No transport, metrics or threads: the service (``services.learner.main``) calls these methods from
its ingest thread (``insert``, ``gate``) and its training loop (``step``), and publishes or records
what they return. The one concession to its threads is ``guard``: a context manager (the service's
lock) held around every touch of the replay and the limiter, never around a gradient update, so an
update never holds up ingest.

Rate limiting (``rate_limiter.SampleToInsertRatio``)
    Inserts are counted in raw env steps (augmented copies are not new experience) and samples in
    updates. The learner trains only while updates <= samples_per_insert x env steps + slack, so a
    slow actor fleet never makes it over-train the same data, and it waits until ``min_steps`` env
    steps are in. The other side is the replay gate: the learner announces how many env steps it
    will take in total before producers should wait (``allowed_steps``), and actors hold back new
    episodes while that allowance is used up, so fast actors do not run ahead of the learner's update
    budget. Everything inserted is still accepted: the gate asks, it never drops.

Devices
    The agent may train on a GPU; the replay stays in host memory and each batch is copied to the
    agent's device (``batch.to_batch``). Reading an update's statistics there waits for the device
    (a host synchronisation), so with ``metrics_every`` N > 1 they stay on it (``MetricsWindow``) and
    are read as means every N updates.
"""

from __future__ import annotations

from collections.abc import Mapping
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from proto.control import ReplayGate
from services.learner.core.batch import to_batch
from services.learner.core.policy import actor_tensors
from services.learner.core.privileged import episode_critic_state
from services.learner.core.rate_limiter import RateLimiter
from services.learner.core.replay import SequenceReplay
from services.learner.core.sac import RecurrentSAC

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


@dataclass(frozen=True)
class TrainerSettings:
    """How batches are drawn and when the trainer publishes or stops (``LearnerConfig``'s fields)."""

    batch_size: int
    """Whole episodes per update."""
    trim_batches: bool
    """Pad each batch to its longest episode instead of seq_len."""
    publish_every: int
    """New weights are due every this many updates."""
    demo_fraction: float = 0.0
    """Share of every batch drawn from the demonstration set (0: uniform)."""
    successes_as_demos: bool = False
    """Episodes that succeeded (``Episode.succeeded``) join the demonstration set."""
    max_env_steps: int = 0
    """Env-step budget of the run: the gate never allows more (0: none)."""
    max_updates: int = 0
    """The trainer is done after this many updates (0: never)."""
    metrics_every: int = 1
    """Read the update statistics from the agent's device every this many updates, as means over
    them (``MetricsWindow``); 1 reads each update's (the CPU default: no device to wait for)."""


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
    """One learner's replay, limiter and SAC, driven one insert, gate reading or update at a time."""

    def __init__(
        self,
        agent: RecurrentSAC,
        replay: SequenceReplay,
        limiter: RateLimiter,
        rng: np.random.Generator,
        settings: TrainerSettings,
        guard: AbstractContextManager[object] | None = None,
    ) -> None:
        # what learns: its ``update`` trains, its ``state_dict`` is the checkpoint's learner part and
        # ``updates`` its count (subclasses hold another algorithm's agent here)
        self.agent, self.replay, self.limiter, self.rng, self.settings = agent, replay, limiter, rng, settings
        self.guard = guard if guard is not None else nullcontext()
        self.window = MetricsWindow()

    @property
    def sac(self) -> RecurrentSAC:
        return self.agent

    def policy_tensors(self) -> dict[str, np.ndarray]:
        """The published part (a WeightsBlob's tensors): the actor's parameters and buffers."""
        return actor_tensors(self.agent.actor)

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
        state = episode_critic_state(ep) if self.replay.state_dim else None
        with self.guard:
            self.replay.insert(ep, state)
            if ep.augmentation is None:
                self.limiter.inserted(ep.num_steps)

    def gate(self) -> GateReading:
        with self.guard:
            inserted = self.limiter.inserts
            return GateReading(
                inserted=inserted,
                allowed=allowed_steps(inserted, self.limiter.inserts_allowed(), self.settings.max_env_steps),
                samples_allowed=self.limiter.samples_allowed(),
                can_sample=self.limiter.can_sample(),
                replay_transitions=len(self.replay),
                replay_episodes=self.replay.num_episodes,
                updates=self.agent.updates,
            )

    def step(self) -> dict[str, float] | None:
        """One SAC update on a freshly drawn batch if the limiter allows it now (None otherwise): the
        update's losses and statistics, plus the batch's demonstration share and rewarded transitions.

        With ``metrics_every`` N > 1 the losses and statistics come every N-th update only (by the
        update count), as means over the updates since the last read (``MetricsWindow``); the other
        updates give the batch's two numbers alone."""
        s = self.settings
        with self.guard:
            ready = self.replay.num_episodes > 0 and self.limiter.can_sample()
            sample = (
                self.replay.sample(
                    s.batch_size,
                    self.rng,
                    demo_fraction=s.demo_fraction,
                    successes_as_demos=s.successes_as_demos,
                    trim=s.trim_batches,
                )
                if ready
                else None
            )
        if sample is None:
            return None
        batch = to_batch(sample, self.agent.device)
        if s.metrics_every == 1:
            info = self.agent.update(batch)
        else:
            self.window.add(self.agent.update_tensors(batch))
            info = self.window.read() if self.agent.updates % s.metrics_every == 0 else {}
        info["batch_demo_share"] = float(sample.from_demo_set.mean())
        info["batch_reward_transitions"] = float((sample.rewards > 0).sum())
        with self.guard:
            self.limiter.sampled()
        return info

    def publish_due(self) -> bool:
        """Whether the update just done completes a ``publish_every`` period."""
        return self.agent.updates % self.settings.publish_every == 0

    def done(self) -> bool:
        return self.settings.max_updates > 0 and self.agent.updates >= self.settings.max_updates
