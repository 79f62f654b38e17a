"""The algorithm contract: what the generic trainer, the learner service and the policy consumers
need of a learning algorithm, and nothing else (``registry`` names the algorithms that meet it).

An algorithm is three things: its config (frozen, one per run: ``AlgorithmConfig``, which also says
how it builds its learner, replay and batches), its learner (``Algorithm``: updates, published
tensors, checkpoint state) and its policy (``Spec``, which travels with the weights, and
``AlgorithmRuntime``, which consumers step through ``policy.PolicyRuntime``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, Self

if TYPE_CHECKING:
    import numpy as np
    import torch

    from proto.episode import Episode
    from proto.weights import WeightsBlob

OBSERVATIONS = ("voxel", "depth", "dsa")
"""What policies observe. `voxel`: the voxel orthographic projection (EquiObs, MEA); `depth`: the
rendered depth image (Equi-RSAC); `dsa`: the surgical task's own DSA image (GASv2;
``services.observation.dsa``)."""


class Algorithm(Protocol):
    """The learner's learning part: networks, optimisers and their update, on one torch device."""

    device: torch.device
    updates: int
    """Updates done (saved in ``state_dict``)."""

    def update(self, batch: Any) -> dict[str, float]:
        """One update; its statistics read as floats (a host synchronisation on a GPU)."""
        ...

    def update_tensors(self, batch: Any) -> Mapping[str, torch.Tensor | float]:
        """One update; its statistics as 0-d tensors left on the device."""
        ...

    def policy_tensors(self) -> dict[str, np.ndarray]:
        """What actors run, as CPU numpy arrays by name (a WeightsBlob's tensors)."""
        ...

    def state_dict(self) -> dict:
        """Everything a resumed learner needs (tensors and plain values: ``weights_only`` loads)."""
        ...

    def load_state_dict(self, d: dict) -> None: ...


class Sample(Protocol):
    """A batch as the replay hands it out (numpy), before it goes to the device."""

    @property
    def demo_share(self) -> float:
        """Share of the batch drawn from the demonstration set."""
        ...

    @property
    def reward_transitions(self) -> float:
        """Transitions with reward > 0 in the batch."""
        ...


class Replay(Protocol):
    """The replay kind an algorithm trains from (``SequenceReplay`` or one derived from it)."""

    num_episodes: int
    nbytes: int
    capacity_transitions: int
    state_dim: int

    def __len__(self) -> int: ...

    def insert_episode(self, ep: Episode) -> int:
        """Store ``ep``; ValueError (replay unchanged) when it is refused."""
        ...

    def live_episodes(self) -> tuple[np.ndarray, np.ndarray]:
        """(serials, transitions) of the stored episodes, in insertion order."""
        ...

    def state_dict(self, serials: np.ndarray | None = None) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class Spec(Protocol):
    """What a consumer needs to rebuild and feed a policy; travels as a blob's ``config_json``."""

    observation: str

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """(C, H, W) of the uint8 image codes the policy takes."""
        ...

    def to_json(self) -> str: ...


class AlgorithmRuntime(Protocol):
    """One algorithm's policy, stepped one observation at a time with its recurrent state."""

    spec: Any

    def load(self, blob: WeightsBlob) -> None:
        """Rebuild if the spec changed and load the tensors; ValueError (unchanged) if they do not fit."""
        ...

    def fresh(self, generator: torch.Generator) -> Self:
        """The same (shared, read-only) policy with its own state and ``generator``."""
        ...

    def reset(self) -> None: ...

    def executed(self, action: np.ndarray) -> None: ...

    def act(self, image_codes: np.ndarray) -> np.ndarray: ...


class AlgorithmConfig(Protocol):
    """An algorithm's frozen config: its hyperparameters, and how it builds what it trains with."""

    name: str
    """The registry name (``--algorithm``); WeightsBlob.algorithm of its weights."""
    observation: str
    """What its policy observes (``policy.OBSERVATIONS``)."""

    @property
    def group(self) -> str:
        """Symmetry group of its networks ("-" where they have none)."""
        ...

    def for_run(self, observation: str, group: str) -> Self:
        """This config for a run's variant: the policy's ``observation`` and the task's symmetry ``group``
        (used where the networks are equivariant). ValueError if it cannot observe ``observation``."""
        ...

    def build(self, seed: int, device: torch.device) -> Algorithm:
        """Its learner, with networks from torch's current generator (``seed`` for what has its own)."""
        ...

    def replay(self, capacity: int, seq_len: int, seed: int) -> Replay:
        """An empty replay of its kind."""
        ...

    def sample(
        self, replay: Any, batch_size: int, rng: np.random.Generator, demo_fraction: float,
        successes_as_demos: bool,
    ) -> Sample:  # fmt: skip
        """One batch of ``batch_size`` (episodes or windows) from ``replay``, numpy, on the host."""
        ...

    def to_batch(self, sample: Any, device: torch.device) -> Any:
        """``sample`` as the tensors its ``update`` takes, on ``device``."""
        ...

    def spec(self) -> Spec:
        """The spec its published weights carry."""
        ...


@dataclass(frozen=True)
class Registration:
    """What the registry holds for one algorithm name."""

    config: type
    """Its ``AlgorithmConfig`` type."""
    read_spec: Callable[[str], Spec]
    """Its spec from a blob's ``config_json`` (ValueError if it is not one)."""
    runtime: Callable[[bool, torch.Generator], AlgorithmRuntime]
    """A runtime of its policy: ``runtime(deterministic, generator)``, weights loaded by ``load``."""


__all__ = [
    "OBSERVATIONS",
    "Algorithm",
    "AlgorithmConfig",
    "AlgorithmRuntime",
    "Registration",
    "Replay",
    "Sample",
    "Spec",
]
