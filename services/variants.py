"""The variants the paper compares, defined once: what each one observes, how it augments, and which
network group each task uses. Every service's config is derived from these (``services.plan``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Variant:
    """One of the paper's compared methods."""

    name: str
    observation: str
    """What the policy sees: ``voxel`` (the orthographic projection of the voxelised point clouds)
    or ``depth`` (the rendered depth image of Equi-RSAC)."""
    mea: bool
    """Whether MEA copies are made (on demos, or as the run's ``mea_on`` says); every variant gets
    the isometric SO(2) copies."""

    @property
    def depth_image(self) -> bool:
        """Whether actors and the evaluator must render the depth image."""
        return self.observation == "depth"


VARIANTS = {
    "mea": Variant("mea", observation="voxel", mea=True),
    "equiobs": Variant("equiobs", observation="voxel", mea=False),
    "equirsac": Variant("equirsac", observation="depth", mea=False),
}
"""The paper's comparison: EquiRSAC (depth image, isometric copies), EquiObs (voxel projection,
isometric copies), MEA (voxel projection, isometric and MEA copies)."""

NETWORK_GROUP = {"block_pull": "c4", "block_pick": "d4", "drawer_open": "d4"}
"""Equi-RSAC's symmetry group per task: C4 for Block Pull, D4 for the others."""


def variant(name: str) -> Variant:
    try:
        return VARIANTS[name]
    except KeyError:
        raise ValueError(f"variant must be one of {tuple(VARIANTS)}, not {name!r}") from None


def network_group(task: str) -> str:
    """The equivariant networks' group for ``task`` (D4 for tasks not listed)."""
    return NETWORK_GROUP.get(task, "d4")
