"""Policy runtime: the policy of any learner rebuilt from broadcast weights, stepped one observation
at a time (``PolicyRuntime``), for actors (stochastic, exploring), the evaluator (deterministic) and
the inference server. Weights arrive as a ``WeightsBlob`` (tensors by name, no pickle) whose
``algorithm`` names the runtime (``registry``) and whose ``config_json`` the network and the
observation, so a consumer needs nothing else.

Policy input: uint8 image codes (C, H, W) as stored in replay, scaled by the policy image format's
``INPUT_SCALE`` (1/255; see ``images_from_codes``); the learner trains on exactly the same mapping.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from proto.episode import DSA_TASKS
from proto.weights import WeightsBlob
from services.algorithms.algorithm import OBSERVATIONS, AlgorithmRuntime, Spec
from services.algorithms.registry import lookup
from services.algorithms.sac.policy import PolicySpec
from services.algorithms.tensors import actor_tensors, images_from_codes


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
    return lookup(blob.algorithm).read_spec(blob.config_json).observation


class PolicyRuntime:
    """The policy a consumer runs, whichever learner made it: the runtime the registry names for each
    blob's ``algorithm`` (recurrent SAC's actor, GASv2's latent policy), rebuilt as its ``config_json``
    says and kept across versions of the same algorithm (with its recurrent state)."""

    def __init__(self, deterministic: bool = False, seed: int = 0) -> None:
        self.deterministic = deterministic
        self.generator = torch.Generator().manual_seed(seed)
        self.runtime: AlgorithmRuntime | None = None
        self.version = -1

    @property
    def spec(self) -> Spec | None:
        """The loaded policy's spec (its algorithm's: ``PolicySpec``, ``GasV2Spec``); None before."""
        return None if self.runtime is None else self.runtime.spec

    def load(self, blob: WeightsBlob) -> None:
        """Rebuild (if the algorithm or spec changed) and load the blob's tensors; raises ValueError if
        they do not fit (the running policy is then unchanged)."""
        make = lookup(blob.algorithm).runtime
        runtime = self.runtime
        if runtime is None or type(runtime) is not make:
            runtime = make(self.deterministic, self.generator)
        runtime.load(blob)
        self.runtime, self.version = runtime, blob.version

    @property
    def ready(self) -> bool:
        return self.runtime is not None

    def reset(self) -> None:
        if self.runtime is not None:
            self.runtime.reset()

    def fresh(self, seed: int = 0) -> PolicyRuntime:
        """A runtime with these weights (the same modules, shared read-only) and its own recurrent
        state and generator: one per robot session of an inference server."""
        other = PolicyRuntime(self.deterministic, seed)
        other.version = self.version
        if self.runtime is not None:
            other.runtime = self.runtime.fresh(other.generator)
        return other

    def executed(self, action: np.ndarray) -> None:
        """What was executed on the last step (it may differ from what ``act`` chose: Surgical Grasp
        Any's hybrid controller drives the approach; a robot's safety envelope clamps or holds). It is
        the previous action the next step sees, as in the episodes the learner trains on."""
        if self.runtime is not None:
            self.runtime.executed(action)

    def act(self, image_codes: np.ndarray) -> np.ndarray:
        """One action (5,) in [-1, 1] for uint8 image codes (C, H, W); carries the recurrent state."""
        if self.runtime is None:
            raise RuntimeError("no weights loaded")
        return self.runtime.act(image_codes)

    def follow(self, source: PolicyRuntime) -> None:
        """Act with ``source``'s weights (the same modules, shared read-only), keeping this runtime's
        generator, and its recurrent state while the weights' spec stays the same (a new spec starts
        it afresh). For the envs of one actor: ``source`` loads each version once for all of them."""
        if source.runtime is None:
            raise RuntimeError("no weights loaded")
        if self.runtime is None or type(self.runtime) is not type(source.runtime) or self.spec != source.spec:
            self.runtime = source.runtime.fresh(self.generator)
        self.version = source.version

    @staticmethod
    def act_batch(policies: Sequence[PolicyRuntime], image_codes: Sequence[np.ndarray]) -> list[np.ndarray]:
        """``act`` for several runtimes that follow the same weights, in one batched forward pass where
        their algorithm's runtime has one (``act_many``: each keeps its own recurrent state and draws
        its noise from its own generator, so each acts as it would alone, to float rounding); one at
        a time otherwise."""
        runtimes = [p.runtime for p in policies]
        if any(r is None for r in runtimes):
            raise RuntimeError("no weights loaded")
        many = getattr(type(runtimes[0]), "act_many", None)
        if len(runtimes) > 1 and many is not None and all(type(r) is type(runtimes[0]) for r in runtimes):
            return many(runtimes, image_codes)
        return [p.act(c) for p, c in zip(policies, image_codes, strict=True)]


__all__ = [
    "OBSERVATIONS",
    "ObservationUnavailableError",
    "PolicyRuntime",
    "PolicySpec",
    "actor_tensors",
    "blob_observation",
    "check_observation",
    "images_from_codes",
]
