"""Replay samples (numpy, uint8 codes) to the SAC batch (torch, float network inputs)."""

from __future__ import annotations

import torch

from services.learner.core.replay_batch import SequenceBatch
from services.learner.core.sac import Batch
from services.learner.core.tensors import images_from_codes


def to_batch(sample: SequenceBatch, device: torch.device | str = "cpu") -> Batch:
    """Images are rebuilt from the varying channels plus the tiled constant ones, scaled by 1/255,
    exactly as the policy runtime scales the actor's live observations."""
    images = images_from_codes(torch.from_numpy(sample.images_uint8()).to(device))
    return Batch(
        images=images,
        actions=torch.from_numpy(sample.actions).to(device),
        rewards=torch.from_numpy(sample.rewards).to(device),
        terminated=torch.from_numpy(sample.terminated).to(device, torch.float32),
        mask=torch.from_numpy(sample.mask).to(device, torch.float32),
        demo=torch.from_numpy(sample.from_demo_set).to(device, torch.float32),
        obs_mask=torch.from_numpy(sample.obs_mask).to(device),
        state=torch.from_numpy(sample.state).to(device) if sample.state.shape[-1] else None,
    )
