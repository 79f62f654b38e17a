"""Recurrent SAC's update replayed as a CUDA graph: the batch is copied into fixed buffers and the
whole update (forward passes, gradients, Adam steps, temperature, target critic) is one launch.

Why: a paper-preset update is ~1,100 kernels issued from Python, and on a GPU their host-side
dispatch, not the GPU, sets its time. A graph issues them once, at capture. It needs fixed shapes
(batches padded to seq_len, never trimmed) and no host reads inside the update (there are none:
statistics stay on the device); what the update decides on the host (the BC weight, whether the
actor's warm-up is over) selects one captured graph per value."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from services.algorithms.sac.losses import Batch

log = logging.getLogger(__name__)

MAX_GRAPHS = 4
"""Graphs kept at most: one per (batch shapes, BC weight, warm-up over); more means a setting that
changes every update (a BC decay), which replays nothing twice: the update stays eager then."""


class GraphedUpdate:
    """``update(batch)`` (one update, uncounted; ``count_update`` counts one) as CUDA graph replays after
    ``warmup`` eager updates (Adam's state and the libraries' workspaces must exist before a
    capture). ``key(batch)`` names what the update reads on the host besides the batch's shapes."""

    def __init__(
        self,
        update: Callable[[Batch], dict[str, Any]],
        key: Callable[[], tuple],
        parameters: list[Tensor],
        device: torch.device,
        count_update: Callable[[], None],
        warmup: int = 3,
    ) -> None:
        if device.type != "cuda":
            raise ValueError(f"CUDA graphs need a CUDA device, not {device}")
        self._update, self._key, self._params, self._count = update, key, parameters, count_update
        self._eager_left = warmup
        self._side = torch.cuda.Stream(device)
        self._graphs: dict[tuple, tuple[Batch, torch.cuda.CUDAGraph, dict[str, Any]]] = {}
        self.enabled = True
        self.captures = 0

    def __call__(self, batch: Batch) -> dict[str, Any]:
        if not self.enabled:
            return self._eager(batch)
        if self._eager_left > 0:
            self._eager_left -= 1
            return self._on_side_stream(batch)
        key = (_shapes(batch), self._key())
        entry = self._graphs.get(key)
        if entry is None:
            if len(self._graphs) >= MAX_GRAPHS:
                return self._give_up(batch, f"more than {MAX_GRAPHS} distinct updates to capture")
            try:
                entry = self._capture(batch)
            except RuntimeError as exc:  # a capture the update does not allow: stay eager, say why
                return self._give_up(batch, str(exc).splitlines()[0][:300])
            self._graphs[key] = entry
        static, graph, outputs = entry
        _copy_into(static, batch)
        graph.replay()
        self._count()
        # the outputs live in the graph's memory: the next replay overwrites them
        return {k: v.clone() if isinstance(v, Tensor) else v for k, v in outputs.items()}

    def _on_side_stream(self, batch: Batch) -> dict[str, Any]:
        # warm-up off the default stream, as capture needs (torch.cuda.graphs' recipe)
        self._side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(self._side):
            out = self._eager(batch)
        torch.cuda.current_stream().wait_stream(self._side)
        return out

    def _eager(self, batch: Batch) -> dict[str, Any]:
        out = self._update(batch)
        self._count()
        return out

    def _capture(self, batch: Batch) -> tuple[Batch, torch.cuda.CUDAGraph, dict[str, Any]]:
        static = _clone(batch)
        graph = torch.cuda.CUDAGraph()
        for p in self._params:
            p.grad = None  # gradients are allocated inside the graph's memory
        torch.cuda.synchronize()
        # thread_local: the learner's batch thread may queue copies meanwhile; only this thread's
        # calls must be capturable
        with torch.cuda.graph(graph, capture_error_mode="thread_local"):
            outputs = self._update(static)  # records; nothing is computed, no update is counted
        self.captures += 1
        return static, graph, outputs

    def _give_up(self, batch: Batch, why: str) -> dict[str, Any]:
        log.warning("CUDA graphs off for this learner; updates run eagerly", extra={"reason": why})
        self.enabled = False
        self._graphs.clear()
        for p in self._params:
            p.grad = None
        return self._eager(batch)


def _shapes(batch: Batch) -> tuple:
    values = (getattr(batch, f.name) for f in dataclasses.fields(batch))
    return tuple(None if v is None else (tuple(v.shape), v.dtype) for v in values)


def _clone(batch: Batch) -> Batch:
    return dataclasses.replace(
        batch,
        **{
            f.name: getattr(batch, f.name).clone()
            for f in dataclasses.fields(batch)
            if getattr(batch, f.name) is not None
        },
    )


def _copy_into(static: Batch, batch: Batch) -> None:
    for f in dataclasses.fields(batch):
        src = getattr(batch, f.name)
        if src is not None:
            getattr(static, f.name).copy_(src, non_blocking=True)
