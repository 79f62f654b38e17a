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
    """Evaluation episodes M per version (Equi-RSAC: 10; `mea run` passes its --eval-episodes, 20)."""
    every_env_steps: int = 250
    """Evaluate the newest version once the learner's env steps advanced by this much since the last
    evaluation (Equi-RSAC: 250 for Pull and Drawer, 500 for Pick). The first version is evaluated as
    soon as it exists."""
    seed_base: int = EVAL_SEED_BASE
    """First held-out seed: every evaluation runs seeds seed_base .. seed_base + M - 1, so versions are
    compared on the same episodes (actors' seeds stay below 1e9)."""
    run_dir: Path | None = None
    """Run directory: the eval history is appended to RUN_DIR/eval/history.jsonl (none: not recorded)."""
    final_env_steps: int = 0
    """The run's env-step budget: once the learner reaches it, the next version is evaluated off the
    cadence, so the run ends with an evaluation at its budget (0: no budget)."""
    final_episodes: int = 0
    """Episodes of an evaluation at or past the budget (final_env_steps), on seeds seed_base ..
    seed_base + final_episodes - 1 (0: --episodes; `mea run` passes its --final-eval-episodes, 50)."""
    points_per_segment: int = 256
    """Points per segment in each observation (as the actors')."""
    depth_image: bool = False
    """Render the depth image, which `depth` policies (the equirsac variant) observe."""
    max_evaluations: int = 0
    """Stop after this many evaluations (0: until stopped)."""
    first_gate_wait: float = 2.0
    """Before the first evaluation, wait this long (s) for a replay gate so the version gets its env steps."""
    keep_weights: int = 100
    """Keep the weights of the newest this many evaluated versions in RUN_DIR/eval/weights (0: none), so a
    version the history scored can be served (`mea serve --weights RUN_DIR --version N`)."""
    torch_threads: int = 1
    """torch intra-op threads for the policy (0: torch's default)."""
    tensorboard_dir: Path | None = None
    """Write eval/success_rate, eval/return, eval/length and eval/grasp_score of each evaluation here
    (in its own directory, <dir>/<instance>), against the learner's env steps, and the videos as
    animations (`mea run`: RUN_DIR/tb; none: not written)."""
    videos: int = 2
    """Episodes of a chosen evaluation recorded as an MP4 in RUN_DIR/eval/videos (the scene beside the
    policy's image; its first held-out seeds): the 1st evaluation, every video_every-th after it, and
    the one at the budget. 0: none. Needs run_dir."""
    video_every: int = 5
    """Film every this many-th evaluation (counted over the run's history, so a restart keeps the count)."""
    video_size: int = 256
    """Pixels per side of each picture in a video frame."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""

    def __post_init__(self) -> None:
        if self.task not in TASK_CLASSES:
            raise ValueError(f"task must be one of {sorted(TASK_CLASSES)}, not {self.task!r}")
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
            depth_image=self.depth_image, camera=CameraSettings(points_per_segment=self.points_per_segment)
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
