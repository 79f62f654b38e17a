"""The world model's training batch: ``B`` windows of ``L`` consecutive observations, in DreamerV2's
step convention (what arrives *with* observation t: the action that led to it and its reward).

Design notes: docs/architecture-notes.md, services/algorithms/gasv2/chunks.py."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class ChunkBatch:
    images: Tensor
    """float32 (B, L, 3, H, W) in [0, 1]: uint8 DSA codes x 1/255 (``tensors.images_from_codes``)."""
    actions: Tensor
    """float32 (B, L, 5): feature of the action into observation t (0 where ``is_first``)."""
    rewards: Tensor
    """float32 (B, L): reward of the action into observation t (0 where ``is_first``)."""
    discounts: Tensor
    """float32 (B, L): 0 where observation t is terminal, else 1."""
    is_first: Tensor
    """bool (B, L): observation t is its episode's first."""
    handover: Tensor
    """bool (B, L): controller_state is 0 at observation t (the policy acts from it)."""
    mask: Tensor
    """bool (B, L): observation t is real (not padding)."""
    demo: Tensor
    """float32 (B,): 1 for windows drawn from the demonstration set."""

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.rewards.shape[0]), int(self.rewards.shape[1])

    def to(self, device: torch.device | str) -> ChunkBatch:
        return ChunkBatch(**{k: v.to(device) for k, v in self.__dict__.items()})
