"""`mea actor`: run one simulated task with a policy source and publish every finished episode.

Policy sources: `expert` (scripted demonstrations, probe/direct styles), `random` (uniform actions,
as Equi-RSAC's warm-up episodes), `learned` (the latest broadcast weights, pulled between episodes
only when newer). With `--demos N` the actor first records N successful expert demonstrations.
Seeds: actor `index` i uses seed_base + i * 1e6 + k for its k-th episode; evaluation seeds live at
1e9 and above, so training never sees them.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from proto.topics import EPISODES_RAW
from services.actor.episodes import EpisodeBuilder
from services.actor.tasks import EXPERT_STYLES, TASKS, EnvSettings, ManipulationEnv, make_env
from services.actor.tasks.camera import CameraSettings
from services.common import config
from services.common.config import ServiceConfig
from services.common.runtime import ServiceContext
from services.common.weights import WeightsClient

log = logging.getLogger(__name__)
SEED_STRIDE = 1_000_000
POLICIES = ("expert", "random", "learned")


@dataclasses.dataclass(frozen=True)
class ActorConfig:
    """Simulate a task and publish whole episodes."""

    task: str = "block_pull"
    """Task: block_pull, block_pick or drawer_open."""
    policy: str = "random"
    """Policy source after the demonstrations: expert, random or learned (latest broadcast weights)."""
    demos: int = 0
    """Successful scripted demonstrations to publish first (alternating probe/direct styles)."""
    expert_style: str = "alternate"
    """Expert style: alternate, probe (touch the fixed object first) or direct."""
    episodes: int = 0
    """Episodes to run after the demonstrations (0: until stopped)."""
    index: int = 0
    """Actor index: picks the seed stream and the default /metrics port."""
    seed_base: int = 0
    """First seed of the stream."""
    depth_image: bool = False
    """Also record the baseline depth image (the `equirsac` variant's observation)."""
    points_per_segment: int = 256
    """Points per segment in each observation."""
    max_demo_attempts: int = 4
    """Expert attempts per requested demonstration before giving up (only successes count)."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {sorted(TASKS)}, not {self.task!r}")
        if self.policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES}, not {self.policy!r}")
        if self.expert_style not in ("alternate", *EXPERT_STYLES):
            raise ValueError(f"expert_style must be alternate, probe or direct, not {self.expert_style!r}")

    def env_settings(self) -> EnvSettings:
        return EnvSettings(
            depth_image=self.depth_image, camera=CameraSettings(points_per_segment=self.points_per_segment)
        )


PRESETS = {"default": ActorConfig()}


def expert_style(cfg_style: str, k: int) -> str:
    return cfg_style if cfg_style != "alternate" else EXPERT_STYLES[k % 2]


def run_episode(
    env: ManipulationEnv, seed: int, act, builder: EpisodeBuilder, on_step=None
) -> EpisodeBuilder:
    """Roll out one episode with ``act(obs) -> action``; ``on_step(seconds)`` sees each step's time."""
    obs = env.reset(seed)
    builder.observe(obs)
    for _ in range(env.settings.max_steps):
        t0 = time.perf_counter()
        action = act(obs)
        obs, reward, terminated, truncated, _ = env.step(action)
        if on_step is not None:
            on_step(time.perf_counter() - t0)
        builder.observe(obs)
        builder.step(action, reward, terminated, truncated)
        if terminated or truncated:
            break
    return builder


class Actor:
    """The actor's loop around an env, separate from transport so tests can drive it directly."""

    def __init__(self, cfg: ActorConfig, instance: str, env: ManipulationEnv | None = None) -> None:
        self.cfg = cfg
        self.instance = instance
        self.env = env or make_env(cfg.task, cfg.env_settings())
        self.counter = 0
        self.rng = np.random.default_rng([cfg.seed_base, cfg.index, 17])

    def next_seed(self) -> int:
        seed = self.cfg.seed_base + self.cfg.index * SEED_STRIDE + self.counter
        self.counter += 1
        return seed

    def builder(self, seed: int, kind: str, version: int, is_demo: bool) -> EpisodeBuilder:
        return EpisodeBuilder(task=self.cfg.task, seed=seed, actor_id=self.instance, policy_version=version,
                              policy_kind=kind, is_demo=is_demo, segments=self.env.segment_names)  # fmt: skip

    def expert_episode(self, k: int, on_step=None) -> EpisodeBuilder:
        style = expert_style(self.cfg.expert_style, k)
        seed = self.next_seed()
        expert_rng = np.random.default_rng([seed, 3])
        holder: dict = {}

        def act(_obs):
            if "expert" not in holder:  # built after reset, from the privileged state
                holder["expert"] = self.env.task.expert(self.env, style, expert_rng)
            return holder["expert"].act()

        return run_episode(self.env, seed, act, self.builder(seed, f"expert_{style}", -1, True), on_step)

    def random_episode(self, on_step=None) -> EpisodeBuilder:
        seed = self.next_seed()
        return run_episode(self.env, seed, lambda _o: self.rng.uniform(-1, 1, 5), self.builder(seed, "random", -1, False),
                           on_step)  # fmt: skip

    def episode_id(self, b: EpisodeBuilder) -> str:
        return f"{self.instance}-{b.meta['seed']}-{self.counter}"


def _metrics(ctx: ServiceContext):
    m = ctx.metrics
    return {
        "steps": m.counter("mea_actor_env_steps", "Environment steps taken."),
        "episodes": m.counter(
            "mea_actor_episodes", "Episodes finished and published, by policy kind.", ["kind"]
        ),
        "successes": m.counter("mea_actor_successes", "Successful episodes, by policy kind.", ["kind"]),
        "step_seconds": m.histogram(
            "mea_actor_step_seconds",
            "Wall time of one env step (physics + observation).",
            (0.005, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.2, 0.5, 1.0),
        ),  # fmt: skip
        "publish_seconds": m.histogram(
            "mea_actor_publish_seconds",
            "Time to encode and publish one episode.",
            (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.5),
        ),  # fmt: skip
        "failed_demos": m.counter(
            "mea_actor_failed_demos", "Expert attempts that failed (not published as demos)."
        ),
    }


def run(cfg: ActorConfig, bus_factory=None) -> int:
    if cfg.policy == "learned":
        raise SystemExit(
            "mea actor: the learned policy needs the learner's policy runtime (not in this build)"
        )
    counts = {"env_steps": 0, "episodes": 0, "successes": 0}
    kwargs = {"bus_factory": bus_factory} if bus_factory else {}
    with ServiceContext("actor", cfg.service, counters=lambda: counts, index=cfg.index, **kwargs) as ctx:
        actor = Actor(cfg, ctx.instance)
        mx = _metrics(ctx)
        weights = WeightsClient(ctx.bus) if cfg.policy == "learned" else None

        def on_step(seconds: float) -> None:
            counts["env_steps"] += 1
            mx["steps"].inc()
            mx["step_seconds"].observe(seconds)

        def publish(b: EpisodeBuilder) -> None:
            t0 = time.perf_counter()
            ctx.bus.publish(EPISODES_RAW, b.finish(actor.episode_id(b)), source=ctx.instance)
            mx["publish_seconds"].observe(time.perf_counter() - t0)
            kind = b.meta["policy_kind"]
            counts["episodes"] += 1
            mx["episodes"].labels(kind).inc()
            if b.success:
                counts["successes"] += 1
                mx["successes"].labels(kind).inc()

        demos, attempts = 0, 0
        while (
            demos < cfg.demos and attempts < cfg.demos * cfg.max_demo_attempts and not ctx.shutdown.is_set()
        ):
            b = actor.expert_episode(demos, on_step)
            attempts += 1
            if b.success:
                publish(b)
                demos += 1
            else:
                mx["failed_demos"].inc()
        if demos < cfg.demos:
            log.warning("fewer demonstrations than requested", extra={"demos": demos, "requested": cfg.demos})
        k = 0
        while (cfg.episodes == 0 or k < cfg.episodes) and not ctx.shutdown.is_set():
            if weights is not None:
                weights.poll()
                ctx.policy_version = weights.version
            b = actor.expert_episode(k, on_step) if cfg.policy == "expert" else actor.random_episode(on_step)
            publish(b)
            k += 1
        actor.env.close()
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(ActorConfig, PRESETS, argv, "mea actor", ActorConfig.__doc__ or ""))


def launch_args(run_cfg, run_dir: Path, index: int) -> list[str]:
    """Arguments `mea run` passes to actor ``index``."""
    args = ["--task", run_cfg.task, "--index", str(index), "--policy", "random"]
    if index == 0 and run_cfg.demos:
        args += ["--demos", str(run_cfg.demos)]
    return args


__all__ = ["Actor", "ActorConfig", "launch_args", "main", "run", "run_episode"]
