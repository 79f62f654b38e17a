"""The options of `mea audit`, for both audits: the general tasks' (``mea_tools.audit.general``) and
Surgical Grasp Any's (``mea_tools.audit.surgical``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from services.augmenter.core.audit_metrics import AuditTolerance
from services.augmenter.core.mea import MeaSettings
from services.augmenter.core.mea_discrete import MeaDiscreteSettings
from services.tasks import TASK_CLASSES


@dataclass(frozen=True)
class AuditConfig:
    """Record expert demonstrations, make their isometric, MEA and MEA∘isometric copies as the
    augmenter does, replay every demonstration and copy through physics, and report how many
    transitions the simulator reproduces, per kind (after measuring the noise floor)."""

    task: str = "block_pull"
    """Task: block_pull, block_pick, drawer_open or surgical_grasp_any."""
    episodes: int = 10
    """Successful expert demonstrations to augment (alternating probe/direct, as the actor)."""
    copies: int | None = None
    """MEA copies per demonstration; default: the task's (6, or 200)."""
    isometric: int = 4
    """Isometric copies per demonstration (each with its own angle, as the augmenter's)."""
    mea_isometric: bool = True
    """Also audit the MEA copies turned by their shared angle (G_t x G, what the augmenter stores)."""
    seed: int = 0
    """First demonstration seed, and the base seed of the group draws (as the augmenter's)."""
    json: bool = False
    """Print exactly one JSON object on stdout."""
    max_attempts: int = 4
    """Expert attempts per requested demonstration before giving up (only successes are kept)."""
    views: int = 6
    """Teleported views per demonstration for the noise floor."""
    gripper_chamfer_mm: float | None = None
    """Tolerance: gripper Chamfer distance (mm); default: the task's (1.25x its noise floor)."""
    object_chamfer_mm: float | None = None
    """Tolerance: object Chamfer distance (mm); default: the task's."""
    gripper_surface_mm: float | None = None
    """Tolerance: gripper points to the simulated surface (mm); default: the task's."""
    object_surface_mm: float | None = None
    """Tolerance: object points to the simulated surface (mm); default: the task's."""
    jaw: float | None = None
    """Tolerance: jaw opening difference (0..1); default: the task's."""
    mea: MeaSettings = field(default_factory=MeaSettings)
    """MEA settings audited (phases, group ranges, feasibility guards)."""
    mea_discrete: MeaDiscreteSettings = field(default_factory=MeaDiscreteSettings)
    """Discrete MEA settings audited for surgical_grasp_any (h_p, copies, C4 rate, workspace); its
    tolerances are ``services.augmenter.audit_surgical.SurgicalTolerance``'s."""

    def __post_init__(self) -> None:
        if self.task not in TASK_CLASSES:
            raise ValueError(f"--task must be one of {', '.join(sorted(TASK_CLASSES))}, not {self.task!r}")
        if (
            self.episodes < 1
            or self.max_attempts < 1
            or min(self.copies or 0, self.isometric, self.views) < 0
        ):
            raise ValueError("episodes and max_attempts must be >= 1; copies, isometric and views >= 0")

    @property
    def mea_copies(self) -> int:
        """MEA copies per demonstration of a general task (``copies``, default 6)."""
        return 6 if self.copies is None else self.copies

    def tolerance(self, rotated: bool = False) -> AuditTolerance:
        """The task's tolerance (``rotated``: for turned copies), with the values given here."""
        base = AuditTolerance.for_task(self.task, rotated)
        given = {f.name: getattr(self, f.name) for f in dataclasses.fields(AuditTolerance)}
        return dataclasses.replace(base, **{k: v for k, v in given.items() if v is not None})
