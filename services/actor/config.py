"""The actor's settings: which task, which policy source, how many demonstrations, which seeds."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from proto.seeds import ACTOR_SEED_STRIDE, RESTART_SEED_STRIDE
from services.common.config import ServiceConfig
from services.tasks import EXPERT_STYLES, TASK_CLASSES, EnvSettings
from services.tasks.camera import CameraSettings

POLICIES = ("expert", "random", "learned")
EXPERTS = ("observable", "privileged")
MAX_ENVS = 64
"""Envs one actor steps at most (each is a pybullet world in the actor's memory)."""


def check_expert(expert: str, name: str = "--expert") -> None:
    """Refuse an expert that is not one of ``EXPERTS``, naming the setting ``name`` in one line."""
    if expert not in EXPERTS:
        raise ValueError(f"{name} must be one of {', '.join(EXPERTS)}, not {expert!r}")


@dataclasses.dataclass(frozen=True)
class ActorConfig:
    """Simulate a task and publish whole episodes."""

    task: str = "block_pull"
    """Task: block_pull, block_pick, drawer_open or surgical_grasp_any."""
    policy: str = "random"
    """Policy after the demonstrations: expert, random or learned."""
    demos: int = 0
    """Successful scripted demonstrations to publish first (alternating probe/direct styles)."""
    random_steps: int = 0
    """Env steps of random episodes after the demos (the random prefill)."""
    expert_style: str = "alternate"
    """Expert style: alternate, probe (touch the fixed object first) or direct."""
    expert: str = "observable"
    """Scripted expert of the general tasks: observable or privileged."""
    episodes: int = 0
    """Episodes to run after the demonstrations (0: until stopped)."""
    index: int = 0
    """Actor index: picks the seed stream and the default /metrics port."""
    envs: int = 1
    """Envs stepped in lockstep with one batched policy step (env j acts as actor index*envs+j)."""
    seed_base: int = 0
    """First seed of the stream."""
    depth_image: bool = False
    """Also record the baseline depth image (the `equirsac` variant's observation)."""
    points_per_segment: int = 256
    """Points per segment in each observation."""
    gripper_start: str = "random"
    """Gripper pose at reset: random or fixed (the public Equi-RSAC start)."""
    max_demo_attempts: int = 4
    """Expert attempts per requested demonstration before giving up (only successes count)."""
    jump_start: float = 0.0
    """Share of learned episodes that replay a demonstration up to a drawn step first (JSRL)."""
    jump_start_demos: int = 0
    """Demonstrations the run recorded (on actor 0, first sitting): the ones jump starts replay."""
    jump_start_seed_base: int = 0
    """The first sitting's seed base, under which actor 0 recorded those demonstrations."""
    incarnation: int = 0
    """Restarts of this actor in this run (moves its seeds on)."""
    follow_gate: bool = True
    """Wait while the learner's replay gate says its update budget is used up (demos never wait)."""
    gate_timeout: float = 10.0
    """A gate older than this (s) is ignored (learner gone): the actor runs on."""
    unacked_limit: int = 32
    """Published episodes kept until the learner acknowledges them."""
    resend_seconds: float = 300.0
    """Publish an episode again when no ack named it for this long."""
    tensorboard_dir: Path | None = None
    """Write the actor's charts here (TensorBoard); None: not written."""
    tensorboard_every: int = 1
    """Episodes per TensorBoard point (1: each episode, as CleanRL writes them)."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""

    def __post_init__(self) -> None:
        if self.task not in TASK_CLASSES:
            raise ValueError(f"task must be one of {sorted(TASK_CLASSES)}, not {self.task!r}")
        self.env_settings()  # checks the env settings it carries (gripper_start)
        if self.incarnation < 0 or self.random_steps < 0:
            raise ValueError("incarnation and random_steps must be >= 0")
        if not 0.0 <= self.jump_start <= 1.0:
            raise ValueError(f"jump_start must be in [0, 1], not {self.jump_start}")
        if self.jump_start > 0 and (self.jump_start_demos < 1 or self.policy != "learned"):
            raise ValueError(
                "jump_start needs the run's demonstrations (jump_start_demos >= 1) and a learned policy"
            )
        if not 1 <= self.envs <= MAX_ENVS:
            raise ValueError(f"envs must be in 1..{MAX_ENVS}, not {self.envs}")
        if self.tensorboard_every < 1:
            raise ValueError("tensorboard_every must be >= 1")
        if self.unacked_limit < 1 or self.resend_seconds <= 0:
            raise ValueError("unacked_limit must be >= 1 and resend_seconds > 0")
        if self.policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES}, not {self.policy!r}")
        check_expert(self.expert, "expert")
        if self.expert_style not in ("alternate", *EXPERT_STYLES):
            raise ValueError(f"expert_style must be alternate, probe or direct, not {self.expert_style!r}")

    def first_seed(self) -> int:
        """This actor's first episode seed (``proto.seeds``): its seed base, moved on per actor index
        and per restart."""
        return self.seed_base + self.index * ACTOR_SEED_STRIDE + self.incarnation * RESTART_SEED_STRIDE

    def env_settings(self) -> EnvSettings:
        return EnvSettings(
            depth_image=self.depth_image,
            gripper_start=self.gripper_start,
            camera=CameraSettings(points_per_segment=self.points_per_segment),
        )


PRESETS = {"default": ActorConfig()}


def env_configs(cfg: ActorConfig) -> list[ActorConfig]:
    """One single-env config per env of ``cfg``: env j as actor ``index * envs + j`` alone, so an
    actor with K envs runs, seed for seed, what K single-env actors run (the demos and the random
    prefill stay with env 0, as with actor 0)."""
    k = cfg.envs
    return [
        dataclasses.replace(
            cfg,
            index=cfg.index * k + j,
            envs=1,
            demos=cfg.demos if j == 0 else 0,
            random_steps=cfg.random_steps if j == 0 else 0,
        )  # fmt: skip
        for j in range(k)
    ]


def expert_style(cfg_style: str, k: int, styles: tuple[str, ...] = EXPERT_STYLES) -> str:
    """Style of the k-th expert episode: ``cfg_style``, or with ``alternate`` the task's ``styles`` in
    turn (the general tasks alternate probe and direct; a task with one style keeps it)."""
    return cfg_style if cfg_style != "alternate" else styles[k % len(styles)]
