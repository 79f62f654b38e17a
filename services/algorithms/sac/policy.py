"""Recurrent SAC's policy as consumers run it: the spec its weights carry (``PolicySpec``) and the
actor rebuilt from them, stepped one observation at a time (``ActorRuntime``): stochastic for
actors, the squashed mean for the evaluator. The LSTM state and the previous action are carried
across an episode and cleared by ``reset``."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from proto.actions import ACTION_DIM
from proto.weights import WeightsBlob
from services.algorithms.algorithm import OBSERVATIONS
from services.algorithms.networks import Actor, NetConfig, build_actor, disc_xy
from services.algorithms.sac.losses import deterministic_action, tanh_gaussian_sample
from services.algorithms.tensors import images_from_codes, rebuilt


@dataclass(frozen=True)
class PolicySpec:
    """What a consumer needs to rebuild and feed the policy; travels as the blob's ``config_json``."""

    net: NetConfig
    observation: str = "voxel"

    @property
    def image_shape(self) -> tuple[int, int, int]:
        return (self.net.in_channels, self.net.image_size, self.net.image_size)

    def to_json(self) -> str:
        return json.dumps({"net": self.net.to_dict(), "observation": self.observation}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> PolicySpec:
        try:
            d = json.loads(text)
            spec = cls(net=NetConfig.from_dict(d["net"]), observation=d.get("observation", "voxel"))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"weights config_json is not a policy spec: {exc}") from exc
        if spec.observation not in OBSERVATIONS:
            raise ValueError(f"observation must be one of {OBSERVATIONS}, not {spec.observation!r}")
        return spec


class ActorRuntime:
    """Recurrent SAC's actor, rebuilt from each blob (only when its spec changes) and stepped."""

    def __init__(self, deterministic: bool, generator: torch.Generator) -> None:
        self.deterministic, self.generator = deterministic, generator
        self.actor: Actor | None = None
        self.spec: PolicySpec | None = None
        self.reset()

    def load(self, blob: WeightsBlob) -> None:
        spec = PolicySpec.from_json(blob.config_json)
        self.actor, self.spec = (
            rebuilt(self.actor, spec == self.spec, lambda: build_actor(spec.net), blob),
            spec,
        )

    @classmethod
    def of(cls, actor: Actor, spec: PolicySpec, deterministic: bool = True) -> ActorRuntime:
        """A runtime over an actor already built (a learner checkpoint's), shared read-only."""
        runtime = cls(deterministic, torch.Generator().manual_seed(0))
        runtime.actor, runtime.spec = actor, spec
        return runtime

    def fresh(self, generator: torch.Generator) -> ActorRuntime:
        other = ActorRuntime(self.deterministic, generator)
        other.actor, other.spec = self.actor, self.spec
        return other

    def reset(self) -> None:
        self._state = None
        self._prev = torch.zeros(1, ACTION_DIM)

    def executed(self, action: np.ndarray) -> None:
        self._prev = torch.from_numpy(np.asarray(action, np.float32).reshape(1, ACTION_DIM).copy())

    @staticmethod
    @torch.no_grad()
    def act_many(runtimes: Sequence[ActorRuntime], image_codes: Sequence[np.ndarray]) -> list[np.ndarray]:
        """``act`` of several runtimes of the same actor module as one batch: their states and previous
        actions stacked (a fresh episode's state as the zeros the LSTM starts from), each sample's
        noise drawn from its own runtime's generator in the order ``act`` draws it."""
        actor = runtimes[0].actor
        if actor is None or any(r.actor is not actor for r in runtimes):
            raise ValueError("act_many needs runtimes of one loaded actor")
        x = images_from_codes(torch.from_numpy(np.stack([np.ascontiguousarray(c) for c in image_codes])))
        prev = torch.cat([r._prev for r in runtimes])
        states = [r._state for r in runtimes]
        state = None
        if any(st is not None for st in states):
            h0, c0 = next(st for st in states if st is not None)
            h = torch.cat([torch.zeros_like(h0) if st is None else st[0] for st in states])
            c = torch.cat([torch.zeros_like(c0) if st is None else st[1] for st in states])
            state = (h, c)
        mean, log_std, (h1, c1) = actor.step(x, prev, state)
        actions = []
        disc = disc_xy(actor)
        for k, r in enumerate(runtimes):
            r._state = (h1[k : k + 1], c1[k : k + 1])
            if r.deterministic:
                a = deterministic_action(mean[k : k + 1], disc)
            else:
                a, _ = tanh_gaussian_sample(
                    mean[k : k + 1], log_std[k : k + 1], generator=r.generator, disc=disc
                )
            r._prev = a
            actions.append(a[0].numpy().astype(np.float32))
        return actions

    @torch.no_grad()
    def act(self, image_codes: np.ndarray) -> np.ndarray:
        if self.actor is None:
            raise RuntimeError("no weights loaded")
        return self.act_many([self], [image_codes])[0]  # a batch of one: the same operations
