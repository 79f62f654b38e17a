"""`mea actor`: run one simulated task with a policy source and publish every finished episode.

Policy sources: `expert` (scripted demonstrations, probe/direct styles), `random` (uniform actions,
as Equi-RSAC's warm-up episodes), `learned` (the latest broadcast weights, pulled between episodes
only when newer; stochastic actions, recurrent state carried through the episode). With
`--demos N` the actor first records N successful expert demonstrations.
Seeds: actor `index` i uses seed_base + i * 1e6 + k for its k-th episode; evaluation seeds live at
1e9 and above, so training never sees them.

Replay gate: after its demonstrations, an actor starts a new episode only while the learner's
latest ``ReplayGate`` (fresher than ``--gate-timeout``) still allows env steps; otherwise it waits
(``mea_actor_gate_wait_seconds_total``). Before its first policy episode it listens up to 1.5 s
for a gate; with no learner (no gate seen) it then runs freely. Each actor can overshoot the
allowance by at most the episode it already started.

Policy input: a learned policy's weights say which observation it was trained on
(``PolicySpec.observation``): ``voxel`` (the voxel projection of the point clouds, ``policy_image``)
or ``depth`` (the rendered Equi-RSAC depth image, ``policy_input``). A ``depth`` policy needs the env
to render that image (``--depth-image``); an actor without it refuses such weights like any blob that
does not fit (logged, ``mea_actor_bad_weights_total``), keeps the weights it has and runs on.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from proto.seeds import ACTOR_SEED_STRIDE, actor_seed_base
from proto.topics import EPISODES_RAW, REPLAY_GATE
from services.actor.episodes import EpisodeBuilder
from services.common import config
from services.common.bus.base import Bus
from services.common.config import ServiceConfig
from services.common.replay_gate import GateTracker
from services.common.runtime import ServiceContext
from services.common.weights import WeightsClient
from services.observation.depth_image import policy_images as depth_policy_images
from services.observation.projection import segment_policy_images
from services.tasks import EXPERT_STYLES, TASKS, EnvSettings, ManipulationEnv, make_env
from services.tasks.camera import CameraSettings
from services.tasks.env import Observation

log = logging.getLogger(__name__)
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
    follow_gate: bool = True
    """Wait while the learner's replay gate says its update budget is used up (demos never wait)."""
    gate_timeout: float = 10.0
    """A gate older than this (s) is ignored (learner gone): the actor runs on."""
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


def policy_image(obs: Observation) -> np.ndarray:
    """The learned policy's input for one observation: voxel projection + jaw, uint8 (2, 84, 84),
    bit-identical to what the augmenter attaches to stored episodes."""
    return segment_policy_images(obs.points[None], obs.point_counts[None], np.array([obs.jaw], np.float32))[0]


def policy_input(obs: Observation, observation: str) -> np.ndarray:
    """The learned policy's input for ``observation`` ("voxel" or "depth"), uint8 (2, 84, 84).

    ``voxel``: ``policy_image(obs)``. ``depth``: the rendered depth image's codes + jaw
    (``services.observation.depth_image.policy_images``), taken through float16 first, as the
    published episode stores it, so the input is bit-identical to what the augmenter attaches for
    the learner. Needs ``obs.depth_image`` (an env with ``depth_image=True``); ValueError otherwise.
    """
    if observation == "voxel":
        return policy_image(obs)
    if observation != "depth":
        raise ValueError(f"observation must be voxel or depth, not {observation!r}")
    if obs.depth_image is None:
        raise ValueError("a depth policy needs the rendered depth image: start the actor with --depth-image")
    depth = np.asarray(obs.depth_image).astype(np.float16)[None]
    return depth_policy_images(depth, np.array([obs.jaw], np.float32))[0]


class GateFollower:
    """Waits while the learner's latest ``ReplayGate`` says its allowance is used up."""

    def __init__(self, bus: Bus, stale_after: float, first_wait: float = 1.5) -> None:
        self.tracker = GateTracker(bus.subscribe(REPLAY_GATE, capacity=16))
        self.stale_after, self.first_wait = stale_after, first_wait
        self._first = True

    def blocked(self) -> bool:
        # before the first episode, give a running learner's gate (every ~0.5 s) a chance to arrive
        gate = self.tracker.update(self.first_wait if self._first else 0.0)
        self._first = False
        if gate is None or time.monotonic() - self.tracker.seen_at > self.stale_after:
            return False
        return gate.inserted_steps >= gate.allowed_steps

    def wait(self, stop) -> float:
        """Wait until the gate opens (or goes stale, or ``stop`` is set); returns seconds waited."""
        t0 = time.monotonic()
        while self.blocked() and not stop.wait(0.05):
            pass
        return time.monotonic() - t0

    def close(self) -> None:
        self.tracker.sub.close()


def run_episode(
    env: ManipulationEnv, seed: int, act, builder: EpisodeBuilder, on_step=None
) -> EpisodeBuilder:
    """Roll out one episode with ``act(obs) -> action``; ``on_step(seconds)`` sees each step's time."""
    obs = env.reset(seed)
    builder.meta["fixed_object"] = env.task.fixed_index()  # privileged, for the learner's critic
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
        seed = self.cfg.seed_base + self.cfg.index * ACTOR_SEED_STRIDE + self.counter
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

    def learned_episode(self, policy, on_step=None) -> EpisodeBuilder:
        """One episode with a ``PolicyRuntime`` (stochastic; its recurrent state starts afresh)."""
        seed = self.next_seed()
        policy.reset()
        observation = policy.spec.observation
        return run_episode(self.env, seed, lambda o: policy.act(policy_input(o, observation)),
                           self.builder(seed, "learned", policy.version, False), on_step)  # fmt: skip

    def policy_episode(self, k: int, policy=None, on_step=None) -> EpisodeBuilder:
        """Episode k after the demonstrations, with the configured policy source."""
        if self.cfg.policy == "expert":
            return self.expert_episode(k, on_step)
        if self.cfg.policy == "learned":
            return self.learned_episode(policy, on_step)
        return self.random_episode(on_step)

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
        "gate_wait": m.counter(
            "mea_actor_gate_wait_seconds", "Time spent waiting for the learner's replay gate to open."
        ),
        "bad_weights": m.counter("mea_actor_bad_weights", "Weights versions that could not be loaded."),
    }


def _load_weights(weights: WeightsClient, policy, mx, counts: dict, depth_image: bool = False) -> None:
    """Pull a newer version if one was announced; a blob that does not fit, or that wants the depth
    image from an actor that does not render it, is counted and skipped (the old weights stay)."""
    blob = weights.poll()
    if blob is None:
        return
    try:
        from services.learner.core.policy import PolicySpec  # torch: only for learned actors

        observation = PolicySpec.from_json(blob.config_json).observation
        if observation == "depth" and not depth_image:
            raise ValueError("a depth-image policy needs an actor started with --depth-image")
        policy.load(blob)
    except ValueError as exc:
        mx["bad_weights"].inc()
        log.error("weights not loaded", extra={"version": blob.version, "error": str(exc)[:300]})
        return
    # for `mea bench system`: which version, and when (wall clock) it became the acting policy
    counts["weights_version"], counts["weights_loaded_at"] = blob.version, time.time()


def run(cfg: ActorConfig, bus_factory=None) -> int:
    counts = {"env_steps": 0, "episodes": 0, "successes": 0}
    kwargs = {"bus_factory": bus_factory} if bus_factory else {}
    with ServiceContext("actor", cfg.service, counters=lambda: counts, index=cfg.index, **kwargs) as ctx:
        actor = Actor(cfg, ctx.instance)
        mx = _metrics(ctx)
        weights = WeightsClient(ctx.bus) if cfg.policy == "learned" else None
        gate = GateFollower(ctx.bus, cfg.gate_timeout) if cfg.follow_gate else None
        policy = None
        if cfg.policy == "learned":
            from services.learner.core.policy import PolicyRuntime  # torch: only for learned actors

            policy = PolicyRuntime(deterministic=False, seed=cfg.seed_base + cfg.index * ACTOR_SEED_STRIDE)

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
            if gate is not None:
                mx["gate_wait"].inc(gate.wait(ctx.shutdown))
            if weights is not None:
                _load_weights(weights, policy, mx, counts, cfg.depth_image)
                if not policy.ready:  # no weights yet: wait for the learner's first version
                    ctx.shutdown.wait(0.2)
                    continue
                ctx.policy_version = policy.version
            if ctx.shutdown.is_set():
                break
            publish(actor.policy_episode(k, policy, on_step))
            k += 1
        if gate is not None:
            gate.close()
        actor.env.close()
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(ActorConfig, PRESETS, argv, "mea actor", ActorConfig.__doc__ or ""))


def launch_args(run_cfg, run_dir: Path, index: int) -> list[str]:
    """Arguments `mea run` passes to actor ``index``: the learned policy when the run has a learner
    (random otherwise), demonstrations from actor 0 only (not again on resume), the rendered depth
    image for the equirsac variant, and a seed base that moves on with every resume so that no
    training seed repeats (run seed s, resume r: s * 1e8 + r * 1e5; evaluation seeds are >= 1e9)."""
    policy = "learned" if "learner" in run_cfg.services else "random"
    args = ["--task", run_cfg.task, "--index", str(index), "--policy", policy,
            "--seed-base", str(actor_seed_base(run_cfg.seed, run_cfg.resumes))]  # fmt: skip
    if index == 0 and run_cfg.demos and run_cfg.resume is None:
        args += ["--demos", str(run_cfg.demos)]
    if run_cfg.variant == "equirsac":
        args += ["--depth-image"]
    if not run_cfg.follow_gate:
        args += ["--no-follow-gate"]
    return args


__all__ = [
    "Actor",
    "ActorConfig",
    "launch_args",
    "main",
    "policy_image",
    "policy_input",
    "run",
    "run_episode",
]
