"""The evaluator's settings (`mea evaluator` flags): task, evaluation sizes, cadence, held-out seeds."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from proto.seeds import EVAL_SEED_BASE
from services.common.config import ServiceConfig
from services.evaluator.core.schedule import Schedule
from services.tasks import TASK_CLASSES, EnvSettings
from services.tasks.camera import CameraSettings


@dataclasses.dataclass(frozen=True)
class EvaluatorConfig:
    """Evaluate broadcast weights with the deterministic policy on held-out seeds; report and record."""

    task: str = "block_pull"
    """Task: block_pull, block_pick or drawer_open."""
    episodes: int = 10
    """Evaluation episodes per version."""
    every_env_steps: int = 250
    """Evaluate the newest version every this many learner env steps."""
    seed_base: int = EVAL_SEED_BASE
    """First held-out seed (every evaluation runs the same seeds)."""
    run_dir: Path | None = None
    """Run directory for RUN_DIR/eval/history.jsonl (none: not recorded)."""
    final_env_steps: int = 0
    """The run's env-step budget, evaluated off the cadence (0: none)."""
    final_episodes: int = 0
    """Episodes of an evaluation at the budget (0: --episodes)."""
    points_per_segment: int = 256
    """Points per segment in each observation (as the actors')."""
    gripper_start: str = "random"
    """Gripper pose at reset: random or fixed (the public Equi-RSAC start)."""
    depth_image: bool = False
    """Render the depth image, which `depth` policies (the equirsac variant) observe."""
    max_evaluations: int = 0
    """Stop after this many evaluations (0: until stopped)."""
    first_gate_wait: float = 2.0
    """Seconds to wait for a replay gate before the first evaluation."""
    keep_weights: int = 100
    """Keep the weights of the newest this many evaluated versions."""
    torch_threads: int = 1
    """torch intra-op threads for the policy (0: torch's default)."""
    tensorboard_dir: Path | None = None
    """Write eval/* scalars and videos here (TensorBoard); none: off."""
    videos: int = 2
    """Episodes filmed per filmed evaluation (MP4); 0: none."""
    video_every: int = 5
    """Film every this many-th evaluation."""
    video_size: int = 256
    """Pixels per side of each picture in a video frame."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""

    def __post_init__(self) -> None:
        if self.task not in TASK_CLASSES:
            raise ValueError(f"task must be one of {sorted(TASK_CLASSES)}, not {self.task!r}")
        self.env_settings()  # checks the env settings it carries (gripper_start)
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if min(self.every_env_steps, self.final_env_steps, self.final_episodes, self.max_evaluations,
               self.first_gate_wait) < 0:  # fmt: skip
            raise ValueError(
                "every_env_steps, final_env_steps, final_episodes, max_evaluations and first_gate_wait "
                "must be >= 0"
            )
        if (
            self.seed_base < 0
            or self.torch_threads < 0
            or self.points_per_segment < 1
            or self.keep_weights < 0
        ):
            raise ValueError(
                "seed_base, torch_threads and keep_weights must be >= 0, points_per_segment >= 1"
            )
        if (
            self.videos < 0
            or self.video_every < 1
            or not 64 <= self.video_size <= 1024
            or self.video_size % 16
        ):
            raise ValueError("videos must be >= 0, video_every >= 1, video_size a multiple of 16 in 64..1024")

    def env_settings(self) -> EnvSettings:
        return EnvSettings(
            depth_image=self.depth_image,
            gripper_start=self.gripper_start,
            camera=CameraSettings(points_per_segment=self.points_per_segment),
        )

    @property
    def schedule(self) -> Schedule:
        """The cadence and evaluation sizes these settings give (``services.evaluator.core.schedule``)."""
        return Schedule(episodes=self.episodes, every_env_steps=self.every_env_steps,
                        seed_base=self.seed_base, final_env_steps=self.final_env_steps,
                        final_episodes=self.final_episodes, first_gate_wait=self.first_gate_wait)  # fmt: skip

    @property
    def seeds(self) -> tuple[int, ...]:
        """The held-out seeds of an evaluation before the budget."""
        return self.seeds_at(-1)

    def at_budget(self, env_steps: int) -> bool:
        """Is a version pulled at ``env_steps`` the run's final evaluation (at or past the budget)?"""
        return self.schedule.at_budget(env_steps)

    def seeds_at(self, env_steps: int) -> tuple[int, ...]:
        """The held-out seeds of an evaluation of a version pulled at ``env_steps`` (see ``Schedule``)."""
        return self.schedule.seeds_at(env_steps)


PRESETS = {"default": EvaluatorConfig()}


__all__ = ["PRESETS", "EvaluatorConfig"]
