"""``--init-actor PATH``: a fresh learner's actor starts from weights on disk (a clone written by
`mea bench imitation`, or a weights file / run dir a learner or evaluator wrote).

The file is checked (digest, seal with its run's key, fit to the learner's actor) before it loads.

Design notes: docs/architecture-notes.md, services/learner/init_actor.py."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import torch

from proto.seal import is_sealed
from proto.weights import WeightsBlob
from services.algorithms.networks import build_actor
from services.algorithms.registry import lookup
from services.algorithms.sac.algorithm import SacConfig
from services.algorithms.sac.policy import PolicySpec
from services.algorithms.tensors import fitting_state
from services.common import run_key, weights_file

if TYPE_CHECKING:
    from services.algorithms.trainer import Trainer
    from services.learner.config import AlgorithmSettings

KEY_SEARCH_DEPTH = 4
"""Directories searched for the writer's ``run.key``: the file's own and the three above it."""


def _writer_key(path: Path) -> bytes | None:
    """The key of the run that sealed ``path`` (None for an unsealed file)."""
    with path.open("rb") as f:
        head = f.read(64)
    if not is_sealed(head):
        return None
    for d in list(path.resolve().parents)[:KEY_SEARCH_DEPTH]:
        if (d / run_key.FILE_NAME).is_file():
            return run_key.load(d / run_key.FILE_NAME)
    raise weights_file.WeightsFileError(
        f"{path}: the file is sealed and no {run_key.FILE_NAME} of the run that wrote it is beside it"
    )


def read(path: Path, version: int | None = None) -> tuple[Path, WeightsBlob]:
    """The weights file ``path`` names (a file, or in a run dir / weights folder the one of ``version``,
    None: the newest) and its blob, checked (seal with its run's key, digest); ValueError
    (``WeightsFileError``, ``RunKeyError``) naming the problem."""
    if not Path(path).exists():
        raise weights_file.WeightsFileError(f"{path}: no such file or directory")
    try:
        file = weights_file.resolve(Path(path), version)
        return file, weights_file.read(file, _writer_key(file))
    except OSError as exc:
        raise weights_file.WeightsFileError(f"{path}: cannot read it ({exc.strerror or exc})") from None


def supports(algorithm: str) -> bool:
    """Whether ``algorithm``'s learner starts from an actor's weights (the recurrent SAC ones)."""
    return lookup(algorithm).config is SacConfig


def check_fits(blob: WeightsBlob, algo: AlgorithmSettings) -> dict[str, torch.Tensor]:
    """``blob``'s tensors as the state dict of ``algo``'s actor (a learner's ``algorithm``); ValueError
    unless the blob is a policy of that algorithm and observation whose tensors fit that actor name
    for name and shape for shape."""
    if not isinstance(algo, SacConfig):
        raise ValueError("only the Equi-RSAC learners (equi_rsac, rsac) start from an actor's weights")
    if blob.algorithm != algo.name:
        raise ValueError(f"the weights are a {blob.algorithm} policy, the learner trains {algo.name}")
    spec = PolicySpec.from_json(blob.config_json)
    if spec.observation != algo.observation:
        raise ValueError(
            f"the weights' policy observes {spec.observation!r}, the learner's observes {algo.observation!r}"
        )
    try:
        return fitting_state(build_actor(algo.net), blob.tensors, blob.version)
    except ValueError as exc:
        raise ValueError(
            f"{exc}; the weights' network is group {spec.net.group}, image_embed {spec.net.image_embed}, "
            f"lstm_hidden {spec.net.lstm_hidden}, the learner's group {algo.net.group}, image_embed "
            f"{algo.net.image_embed}, lstm_hidden {algo.net.lstm_hidden} (a clone of the run's --task and "
            "--learner-preset fits)"
        ) from None


def load_into(trainer: Trainer, state: dict[str, torch.Tensor]) -> None:
    """Start ``trainer``'s actor from ``state`` (``check_fits``); a critic encoder the actor shares
    gets it too, and the target critic is made equal to the critic."""
    sac = trainer.agent
    sac.actor.load_state_dict(state, strict=True)
    if getattr(sac.actor, "encoder", None) is getattr(sac.critic, "encoder", object()):
        sac.critic_target.load_state_dict(sac.critic.state_dict())


__all__ = ["check_fits", "load_into", "read", "supports"]
