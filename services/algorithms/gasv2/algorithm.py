"""GASv2 as the learner runs it (``GasV2Config``, an ``algorithm.AlgorithmConfig``): DreamerV2's
hyperparameters and the window length, and how it builds its learner (``agent.GasV2Agent``), its
replay of surgical episodes sampled as windows (``chunk_replay.ChunkReplay``) and its batches."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
import torch
import tyro

from services.algorithms.gasv2.agent import GasV2Agent
from services.algorithms.gasv2.chunk_replay import ChunkReplay, ChunkSample, to_chunk_batch
from services.algorithms.gasv2.chunks import ChunkBatch
from services.algorithms.gasv2.config import PRESETS as DREAMER_PRESETS
from services.algorithms.gasv2.config import DreamerConfig
from services.algorithms.gasv2.policy import OBSERVATION, GasV2Spec

NAME = "gasv2"


@dataclass(frozen=True)
class GasV2Config:
    """GASv2 (Surgical Grasp Any): a DreamerV2 world model with an imagination actor."""

    name: Annotated[str, tyro.conf.arg(name="algorithm")] = NAME
    """gasv2 (equi_rsac and rsac: other presets)."""
    dreamer: DreamerConfig = field(default_factory=lambda: DREAMER_PRESETS["paper"])
    """GASv2's world model, actor and critic."""
    chunk_length: int = 6
    """Observations per training window (GASv2: 6)."""
    observation: str = OBSERVATION
    """Policy images: dsa (the surgical task's only one)."""

    def __post_init__(self) -> None:
        if self.name != NAME:
            raise ValueError(f"--algorithm {self.name!r} starts from an Equi-RSAC preset (--preset paper, "
                             f"cpu-small, ...); the gasv2 presets train {NAME}")  # fmt: skip
        if self.observation != OBSERVATION:
            raise ValueError(f"a gasv2 learner observes {OBSERVATION}, the surgical DSA image, not "
                             f"{self.observation!r}")  # fmt: skip
        if self.chunk_length < 1:
            raise ValueError("chunk_length must be >= 1")

    @property
    def group(self) -> str:
        return "-"

    def for_run(self, observation: str, group: str) -> GasV2Config:
        """Unchanged (its networks have no symmetry group); ValueError unless ``observation`` is dsa."""
        return dataclasses.replace(self, observation=observation)

    def build(self, seed: int, device: torch.device) -> GasV2Agent:
        return GasV2Agent(self.dreamer, seed=seed, device=device)

    def replay(self, capacity: int, seq_len: int, seed: int) -> ChunkReplay:
        return ChunkReplay(capacity, seq_len=seq_len, seed=seed)

    def sample(
        self, replay: ChunkReplay, batch_size: int, rng: np.random.Generator, demo_fraction: float,
        successes_as_demos: bool,
    ) -> ChunkSample:  # fmt: skip
        """``batch_size`` windows of ``chunk_length`` observations."""
        return replay.sample_chunks(batch_size, self.chunk_length, rng, demo_fraction=demo_fraction,
                                    successes_as_demos=successes_as_demos)  # fmt: skip

    def to_batch(self, sample: ChunkSample, device: torch.device) -> ChunkBatch:
        return to_chunk_batch(sample, device)

    def spec(self) -> GasV2Spec:
        return GasV2Spec(self.dreamer)
