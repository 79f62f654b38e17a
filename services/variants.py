"""The variants the paper compares, defined once: what each one observes, how it augments, and which
network group each task uses. Every service's config is derived from these (``services.plan``)."""

from __future__ import annotations

from dataclasses import dataclass

from proto.episode import DSA_TASKS


@dataclass(frozen=True)
class Variant:
    """One of the paper's compared methods."""

    name: str
    observation: str
    """What the policy sees: ``voxel`` (the orthographic projection of the voxelised point clouds)
    or ``depth`` (the rendered depth image of Equi-RSAC)."""
    mea: bool
    """Whether MEA copies are made (on demos, or as the run's ``mea_on`` says); every SAC variant gets
    the isometric SO(2) copies (the discrete-action domain has none, Sec. VI)."""
    algorithm: str = "equi_rsac"
    """The learner: equi_rsac (general manipulation) or gasv2 (Surgical Grasp Any)."""

    @property
    def depth_image(self) -> bool:
        """Whether actors and the evaluator must render the depth image."""
        return self.observation == "depth"


VARIANTS = {
    "mea": Variant("mea", observation="voxel", mea=True),
    "equiobs": Variant("equiobs", observation="voxel", mea=False),
    "equirsac": Variant("equirsac", observation="depth", mea=False),
    "gasv2": Variant("gasv2", observation="dsa", mea=False, algorithm="gasv2"),
    "mea-gasv2": Variant("mea-gasv2", observation="dsa", mea=True, algorithm="gasv2"),
}
"""The paper's comparisons. General manipulation: EquiRSAC (depth image, isometric copies), EquiObs
(voxel projection, isometric copies), MEA (voxel projection, isometric and MEA copies). Surgical
grasping: GASv2 (DSA image, no copies) and MEA-GASv2 (the same with MEA copies, 200 per episode)."""

NETWORK_GROUP = {"block_pull": "c4", "block_pick": "d4", "drawer_open": "d4"}
"""Equi-RSAC's symmetry group per task: C4 for Block Pull, D4 for the others."""


def variant(name: str) -> Variant:
    try:
        return VARIANTS[name]
    except KeyError:
        raise ValueError(f"variant must be one of {tuple(VARIANTS)}, not {name!r}") from None


def check_task(name: str, task: str) -> None:
    """ValueError unless variant ``name`` runs on ``task``: the GASv2 variants on the tasks that render
    the DSA image (``DSA_TASKS``), the others on the general manipulation tasks."""
    v = variant(name)
    if (v.observation == "dsa") != (task in DSA_TASKS):
        fits = [n for n, w in VARIANTS.items() if (w.observation == "dsa") == (task in DSA_TASKS)]
        raise ValueError(f"variant {name!r} does not run on {task}; choose one of {fits}")


def network_group(task: str) -> str:
    """The equivariant networks' group for ``task`` (D4 for tasks not listed)."""
    return NETWORK_GROUP.get(task, "d4")
