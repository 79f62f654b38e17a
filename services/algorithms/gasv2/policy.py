"""GASv2's policy runtime: the published ``LatentPolicy`` (encoder, RSSM, actor) stepped one
observation at a time, with its recurrent latent state carried across an episode.

The consumer reports every executed action (``executed``: the controller's too), which the world
model's posterior needs. Stochastic (actors) or deterministic (the evaluator).

Design notes: docs/architecture-notes.md, services/algorithms/gasv2/policy.py."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch

from proto.actions import ACTION_DIM, JAW
from proto.discrete_actions import to_vector
from proto.weights import WeightsBlob
from services.algorithms.gasv2.action_features import FEATURE_DIM, features
from services.algorithms.gasv2.agent import LatentPolicy, build_policy
from services.algorithms.gasv2.config import DreamerConfig
from services.algorithms.tensors import images_from_codes, rebuilt

OBSERVATION = "dsa"
"""GASv2 observes the env's DSA image (Surgical Grasp Any: 3 x 64 x 64 uint8)."""


@dataclass(frozen=True)
class GasV2Spec:
    """What a consumer needs to rebuild and feed the policy; travels as the blob's ``config_json``."""

    dreamer: DreamerConfig
    observation: str = OBSERVATION

    @property
    def image_shape(self) -> tuple[int, int, int]:
        return (self.dreamer.channels, self.dreamer.image_size, self.dreamer.image_size)

    def to_json(self) -> str:
        return json.dumps(
            {"dreamer": self.dreamer.to_dict(), "observation": self.observation}, sort_keys=True
        )

    @classmethod
    def from_json(cls, text: str) -> GasV2Spec:
        try:
            d = json.loads(text)
            spec = cls(
                dreamer=DreamerConfig.from_dict(d["dreamer"]), observation=d.get("observation", OBSERVATION)
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"weights config_json is not a GASv2 policy spec: {exc}") from exc
        if spec.observation != OBSERVATION:
            raise ValueError(f"a GASv2 policy observes {OBSERVATION!r}, not {spec.observation!r}")
        return spec


class LatentRuntime:
    """One GASv2 policy, stepped one observation at a time (see the module docstring)."""

    def __init__(self, deterministic: bool, generator: torch.Generator) -> None:
        self.deterministic, self.generator = deterministic, generator
        self.policy: LatentPolicy | None = None
        self.spec: GasV2Spec | None = None
        self.logits: torch.Tensor | None = None
        self.reset()

    def load(self, blob: WeightsBlob) -> None:
        spec = GasV2Spec.from_json(blob.config_json)
        self.policy = rebuilt(self.policy, spec == self.spec, lambda: build_policy(spec.dreamer), blob)
        self.spec = spec

    def fresh(self, generator: torch.Generator) -> LatentRuntime:
        """The same policy (shared, read-only) with its own state and generator."""
        other = LatentRuntime(self.deterministic, generator)
        other.policy, other.spec = self.policy, self.spec
        return other

    def reset(self) -> None:
        self._state = None
        self._prev_feature = torch.zeros(1, FEATURE_DIM)
        self._jaw_open = True  # the jaw command before the next step: open at an episode's start
        self._pending: np.ndarray | None = None  # the last step's action, until the next act()
        self._first = True

    def executed(self, action: np.ndarray) -> None:
        """The action the env executed on the last step (its ``info['executed_action']``): replaces
        the one this runtime chose as the action that led to the next observation."""
        self._pending = np.asarray(action, np.float32).reshape(ACTION_DIM)

    def _advance(self) -> None:
        """Make the last step's action the world model's input for the next observation."""
        if self._pending is None:
            return
        a = self._pending[None]
        self._prev_feature = torch.from_numpy(features(a, jaw_open_at_start=self._jaw_open))
        self._jaw_open, self._pending = bool(a[0, JAW] >= 0.0), None

    @torch.no_grad()
    def act(self, image_codes: np.ndarray) -> np.ndarray:
        """The 5-vector of the chosen discrete action for uint8 DSA codes (3, 64, 64)."""
        if self.policy is None:
            raise RuntimeError("no weights loaded")
        self._advance()
        if self._state is None:
            self._state = self.policy.initial_state(1)
        x = images_from_codes(torch.from_numpy(np.ascontiguousarray(image_codes))[None])
        first = torch.tensor([self._first])
        logits, self._state = self.policy.step(
            self._state, self._prev_feature, x, first, generator=self.generator
        )
        self._first = False
        self.logits = logits[0]  # the last step's action logits (for tests and diagnostics)
        if self.deterministic:
            index = int(logits.argmax(-1))
        else:
            index = int(torch.multinomial(torch.softmax(logits, -1), 1, generator=self.generator))
        self._pending = to_vector(index, self._jaw_open)  # executed unless the env reports otherwise
        return self._pending.copy()
