"""From what travels (uint8 image codes, a weights blob's numpy tensors) to what networks take, for
every algorithm's consumers and learners alike."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numpy as np
import torch

from proto.weights import WeightsBlob
from services.observation.image_format import INPUT_SCALE


def images_from_codes(codes: torch.Tensor) -> torch.Tensor:
    """uint8 codes (..., C, H, W) -> float32 network input in [0, 1]: ``image_format.decode`` done by
    torch (on the codes' device), bit for bit."""
    return codes.to(torch.float32).mul_(INPUT_SCALE)


def fitting_state(
    module: torch.nn.Module, tensors: dict[str, np.ndarray], version: int
) -> dict[str, torch.Tensor]:
    """``tensors`` as a torch state dict if every name and shape fits ``module`` (ValueError naming a
    few that differ otherwise): checked before loading, since ``load_state_dict`` copies the tensors
    that fit before it raises on those that do not, which would leave a running policy half-overwritten."""
    state = {k: torch.from_numpy(np.array(v)) for k, v in tensors.items()}
    expected = {k: tuple(v.shape) for k, v in module.state_dict().items()}
    got = {k: tuple(v.shape) for k, v in state.items()}
    if got != expected:
        wrong = sorted(k for k in expected.keys() | got.keys() if expected.get(k) != got.get(k))
        raise ValueError(
            f"weights v{version} do not fit the network: {len(wrong)} tensors differ (e.g. {wrong[:3]})"
        )
    return state


def actor_tensors(actor: torch.nn.Module) -> dict[str, np.ndarray]:
    """A policy's parameters and buffers as numpy arrays on the CPU (what a WeightsBlob carries)."""
    return {k: v.detach().cpu().numpy().copy() for k, v in actor.state_dict().items()}


M = TypeVar("M", bound=torch.nn.Module)


def rebuilt(module: M | None, same_spec: bool, build: Callable[[], M], blob: WeightsBlob) -> M:
    """A consumer's policy network for ``blob``: ``module`` where its spec is the blob's (``same_spec``),
    else a new ``build()``, with the blob's tensors loaded (checked first: ``fitting_state``), in
    eval mode. ValueError, ``module`` untouched, if they do not fit."""
    net = module if same_spec and module is not None else build()
    net.load_state_dict(fitting_state(net, blob.tensors, blob.version), strict=True)
    return net.eval()
