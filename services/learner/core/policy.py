"""Policy runtime: the actor network rebuilt from broadcast weights, stepped one observation at a time.

Used by actors (stochastic, exploring) and the evaluator (deterministic: tanh of the mean). The
recurrent state and the previous action are carried across an episode and cleared by ``reset``.
Weights arrive as a ``WeightsBlob`` (tensors by name, no pickle) whose ``config_json`` names the
network configuration and the observation the policy expects, so a consumer needs nothing else.

Policy input: uint8 image codes (C, H, W) as stored in replay, scaled by the policy image format's
``INPUT_SCALE`` (1/255; see ``images_from_codes``); the learner trains on exactly the same mapping.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch

from proto.actions import ACTION_DIM
from proto.episode import DSA_TASKS
from proto.weights import WeightsBlob
from services.learner.core.gasv2.policy import GasV2Spec, LatentRuntime
from services.learner.core.networks import Actor, NetConfig, build_actor
from services.learner.core.sac import deterministic_action, tanh_gaussian_sample
from services.learner.core.tensors import fitting_state, images_from_codes

OBSERVATIONS = ("voxel", "depth", "dsa")
"""`voxel`: the voxel orthographic projection (EquiObs, MEA); `depth`: the rendered depth image
(Equi-RSAC); `dsa`: the surgical task's own DSA image (GASv2; ``services.observation.dsa``)."""


@dataclass(frozen=True)
class PolicySpec:
    """What a consumer needs to rebuild and feed the policy; travels as the blob's ``config_json``."""

    net: NetConfig
    observation: str = "voxel"

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


class ObservationUnavailableError(ValueError):
    """The weights' policy observes an image this consumer does not render."""


def check_observation(observation: str, depth_image: bool, consumer: str, task: str = "") -> None:
    """Refuse a policy whose observation this consumer cannot build: a ``depth`` policy needs the
    rendered depth image (a service started with ``--depth-image``); a ``dsa`` policy needs a task
    whose env renders the DSA image (``DSA_TASKS``), and those tasks render nothing else. One check for
    the actor and the evaluator; ``consumer`` names the service in the message ("an actor", "an
    evaluator"), ``task`` its task (empty: not checked)."""
    if observation == "depth" and not depth_image:
        raise ObservationUnavailableError(f"a depth-image policy needs {consumer} started with --depth-image")
    if task and (observation == "dsa") != (task in DSA_TASKS):
        raise ObservationUnavailableError(
            f"a {observation!r} policy cannot run on {task} (the DSA image is {', '.join(DSA_TASKS)}'s observation)"
        )


def blob_observation(blob: WeightsBlob) -> str:
    """What the blob's policy observes, from its spec (ValueError if the spec does not parse)."""
    if blob.algorithm == "gasv2":
        return GasV2Spec.from_json(blob.config_json).observation
    return PolicySpec.from_json(blob.config_json).observation


def actor_tensors(actor: torch.nn.Module) -> dict[str, np.ndarray]:
    """A policy's parameters and buffers as numpy arrays (what a WeightsBlob carries)."""
    return {k: v.detach().cpu().numpy().copy() for k, v in actor.state_dict().items()}


class PolicyRuntime:
    """The policy a consumer runs, whichever learner made it: recurrent SAC's actor (``equi_rsac``,
    ``rsac``) or GASv2's latent policy (``gasv2``, ``gasv2.policy.LatentRuntime``), rebuilt from each
    blob as its ``algorithm`` and ``config_json`` say."""

    def __init__(self, deterministic: bool = False, seed: int = 0) -> None:
        self.deterministic = deterministic
        self.generator = torch.Generator().manual_seed(seed)
        self.actor: Actor | None = None
        self.spec: PolicySpec | GasV2Spec | None = None
        self.version = -1
        self._latent: LatentRuntime | None = None
        self._state = None
        self._prev = torch.zeros(1, ACTION_DIM)

    def load(self, blob: WeightsBlob) -> None:
        """Rebuild (if the spec changed) and load the blob's tensors; raises ValueError if they do not
        fit (the running policy is then unchanged)."""
        if blob.algorithm == "gasv2":
            latent = self._latent or LatentRuntime(self.deterministic, self.generator)
            latent.load(blob)
            self._latent, self.actor, self.spec, self.version = latent, None, latent.spec, blob.version
            return
        spec = PolicySpec.from_json(blob.config_json)
        actor = self.actor if spec == self.spec and self.actor is not None else build_actor(spec.net)
        actor.load_state_dict(fitting_state(actor, blob.tensors, blob.version), strict=True)
        actor.eval()
        self.actor, self.spec, self.version, self._latent = actor, spec, blob.version, None

    @property
    def ready(self) -> bool:
        return self.actor is not None or self._latent is not None

    def reset(self) -> None:
        self._state = None
        self._prev = torch.zeros(1, ACTION_DIM)
        if self._latent is not None:
            self._latent.reset()

    def fresh(self, seed: int = 0) -> PolicyRuntime:
        """A runtime with these weights (the same modules, shared read-only) and its own recurrent
        state and generator: one per robot session of an inference server."""
        other = PolicyRuntime(self.deterministic, seed)
        other.actor, other.spec, other.version = self.actor, self.spec, self.version
        if self._latent is not None:
            other._latent = self._latent.fresh(other.generator)
        return other

    def executed(self, action: np.ndarray) -> None:
        """What was executed on the last step (it may differ from what ``act`` chose: Surgical Grasp
        Any's hybrid controller drives the approach; a robot's safety envelope clamps or holds). It is
        the previous action the next step sees, as in the episodes the learner trains on."""
        if self._latent is not None:
            self._latent.executed(action)
        else:
            self._prev = torch.from_numpy(np.asarray(action, np.float32).reshape(1, ACTION_DIM).copy())

    @torch.no_grad()
    def act(self, image_codes: np.ndarray) -> np.ndarray:
        """One action (5,) in [-1, 1] for uint8 image codes (C, H, W); carries the recurrent state."""
        if self._latent is not None:
            return self._latent.act(image_codes)
        if self.actor is None:
            raise RuntimeError("no weights loaded")
        x = images_from_codes(torch.from_numpy(np.ascontiguousarray(image_codes))[None])
        mean, log_std, self._state = self.actor.step(x, self._prev, self._state)
        if self.deterministic:
            a = deterministic_action(mean)
        else:
            a, _ = tanh_gaussian_sample(mean, log_std, generator=self.generator)
        self._prev = a
        return a[0].numpy().astype(np.float32)
