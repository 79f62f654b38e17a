"""Recurrent SAC as the learner runs it (``SacConfig``, an ``algorithm.AlgorithmConfig``): its
networks, hyperparameters and observation, and how it builds its learner (``agent.RecurrentSAC``), its
replay of whole episodes (``replay.SequenceReplay``) and its batches (``batch.to_batch``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
import torch
import tyro

from services.algorithms.batch import to_batch
from services.algorithms.networks import PRESETS as NET_PRESETS
from services.algorithms.networks import NetConfig, build_actor, build_critic
from services.algorithms.privileged import STATE_DIM
from services.algorithms.replay import SequenceReplay
from services.algorithms.replay_batch import SequenceBatch
from services.algorithms.sac.agent import RecurrentSAC
from services.algorithms.sac.config import SacSettings
from services.algorithms.sac.losses import Batch
from services.algorithms.sac.policy import PolicySpec

GROUPS = {"equi_rsac": ("c4", "d4"), "rsac": ("none",)}
"""The two SAC learners by name and their networks' symmetry groups: Equi-RSAC's C4 or D4 layers,
the plain twin's ordinary ones (``rsac`` sets ``net.group`` none itself)."""
OBSERVATIONS = ("voxel", "depth")


@dataclass(frozen=True)
class SacConfig:
    """Recurrent SAC: its networks, hyperparameters and what its policy observes."""

    name: Annotated[str, tyro.conf.arg(name="algorithm")] = "equi_rsac"
    """equi_rsac, rsac (non-equivariant) or gasv2."""
    net: NetConfig = field(default_factory=lambda: NET_PRESETS["paper"])
    """Network widths and symmetry group."""
    sac: SacSettings = SacSettings()
    """SAC hyperparameters."""
    observation: str = "voxel"
    """Policy images: voxel (EquiObs/MEA) or depth."""
    trim_batches: bool = True
    """Pad batches to their longest episode."""
    cuda_graphs: bool = False
    """Each update as a CUDA graph replay (CUDA only)."""

    def __post_init__(self) -> None:
        if self.name not in GROUPS:
            raise ValueError(f"--algorithm {self.name!r} starts from a gasv2 preset (--preset gasv2, gasv2-cpu-small "
                             "or gasv2-smoke): it observes dsa, the surgical DSA image, in windows of its own; "
                             f"these presets train {' or '.join(GROUPS)}")  # fmt: skip
        if GROUPS[self.name] == ("none",) and self.net.group != "none":  # the twin: same widths, plain layers
            object.__setattr__(self, "net", dataclasses.replace(self.net, group="none"))
        if self.net.group not in GROUPS[self.name]:
            raise ValueError(f"{self.name} needs --net.group {' or '.join(GROUPS[self.name])} (the plain twin is "
                             "--algorithm rsac)")  # fmt: skip
        if self.observation not in OBSERVATIONS:
            raise ValueError(f"observation must be one of {OBSERVATIONS} (dsa, the surgical DSA image, is the "
                             f"gasv2 learner's only), not {self.observation!r}")  # fmt: skip
        if self.net.critic_input == "state" and self.sac.share_encoder:
            raise ValueError("sac.share_encoder needs the image critic (net.critic_input image)")
        if (self.sac.target_heads or 0) > self.net.critic_heads:
            raise ValueError(f"sac.target_heads {self.sac.target_heads} exceeds net.critic_heads "
                             f"{self.net.critic_heads}: the target's min draws from the critic's heads")  # fmt: skip

    @property
    def group(self) -> str:
        return self.net.group

    def for_run(self, observation: str, group: str) -> SacConfig:
        return dataclasses.replace(
            self, net=dataclasses.replace(self.net, group=group), observation=observation
        )

    def build(self, seed: int, device: torch.device) -> RecurrentSAC:
        """Actor and critic from torch's current generator (the trainer seeds it; ``seed`` unused)."""
        return RecurrentSAC(build_actor(self.net), build_critic(self.net), self.sac, device, self.cuda_graphs)

    def replay(self, capacity: int, seq_len: int, seed: int) -> SequenceReplay:
        """Whole episodes of policy images, with the privileged state per step for a state critic."""
        state_dim = STATE_DIM if self.net.critic_input == "state" else 0
        return SequenceReplay(capacity, image_size=self.net.image_size, seq_len=seq_len,
                              channels=self.net.in_channels, seed=seed, state_dim=state_dim)  # fmt: skip

    @property
    def trims_batches(self) -> bool:
        """Whether batches are padded to their longest episode (``trim_batches``); never with
        ``cuda_graphs``: a CUDA graph replays one shape, so batches are padded to seq_len."""
        return self.trim_batches and not self.cuda_graphs

    def sample(
        self, replay: SequenceReplay, batch_size: int, rng: np.random.Generator, demo_fraction: float,
        successes_as_demos: bool,
    ) -> SequenceBatch:  # fmt: skip
        """``batch_size`` whole episodes, padded as ``trims_batches`` says."""
        return replay.sample(batch_size, rng, demo_fraction=demo_fraction, successes_as_demos=successes_as_demos,
                             trim=self.trims_batches)  # fmt: skip

    def to_batch(self, sample: SequenceBatch, device: torch.device) -> Batch:
        return to_batch(sample, device)

    def spec(self) -> PolicySpec:
        return PolicySpec(self.net, self.observation)
