"""Replay samples (numpy, uint8 codes) to the SAC batch (torch, float network inputs) on a device.

On CUDA every array goes through pinned (page-locked) host memory and is copied without waiting
(``non_blocking``): the copies queue behind the running update instead of stalling the host. Images
travel as uint8 codes (a quarter of float32's bytes) and become floats on the device."""

from __future__ import annotations

import numpy as np
import torch

from services.algorithms.replay_batch import SequenceBatch
from services.algorithms.sac.losses import Batch
from services.algorithms.tensors import images_from_codes


def to_device(array: np.ndarray, device: torch.device, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``array`` as a tensor on ``device`` (as ``dtype``, converted there): on the CPU it shares the
    array's memory where no conversion is needed; on CUDA it is staged in pinned memory and copied
    asynchronously (the caching host allocator keeps the staging buffer until the copy is done)."""
    t = torch.from_numpy(array)
    if device.type == "cuda":
        t = t.pin_memory().to(device, non_blocking=True)
    return t.to(device, dtype)


def to_batch(sample: SequenceBatch, device: torch.device | str = "cpu") -> Batch:
    """Images are rebuilt from the varying channels plus the tiled constant ones, scaled by 1/255,
    exactly as the policy runtime scales the actor's live observations. On the CPU the real
    observations' images are also gathered once, as uint8 codes and in the encoders' channels_last
    layout (``Batch.real_images``): each encoder pass otherwise copied the float batch twice."""
    dev = torch.device(device)
    codes = sample.images_uint8()
    real_images = None
    if dev.type == "cpu":
        real = torch.from_numpy(codes[sample.obs_mask]).contiguous(memory_format=torch.channels_last)
        real_images = images_from_codes(real)
    return Batch(
        images=images_from_codes(to_device(codes, dev)),
        actions=to_device(sample.actions, dev),
        rewards=to_device(sample.rewards, dev),
        terminated=to_device(sample.terminated, dev, torch.float32),
        mask=to_device(sample.mask, dev, torch.float32),
        demo=to_device(sample.from_demo_set, dev, torch.float32),
        obs_mask=to_device(sample.obs_mask, dev),
        state=to_device(sample.state, dev) if sample.state.shape[-1] else None,
        real_images=real_images,
    )
