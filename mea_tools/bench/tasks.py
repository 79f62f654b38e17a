"""`mea bench tasks`: scripted-expert success, env speed and the transition prior, per task.

Each (task, style) job runs in its own spawned process over seeded episodes and reports success,
whether the probe demonstrations touched the fixed object, and env steps/s of that process
(physics + observation, what an actor pays per step). A separate job per task measures the
deterministic-transition prior MEA relies on (mm / degrees).

``surgical_grasp_any`` has its own rows (section ``surgical``): the discrete oracle's success over the
seeded episodes with domain randomisation off and on, episode length, the steps the hybrid
P-controller took, and env steps/s (the transition prior is a general-task measure).
"""

from __future__ import annotations

import dataclasses
import itertools
import multiprocessing as mp
import time

import numpy as np

from mea_tools.bench.report import emit
from services.tasks import GENERAL_TASKS, make_env
from services.tasks.experts import seed_for_style
from services.tasks.prior import measure, summarise
from services.tasks.surgical.settings import RandomisationSettings, SurgicalSettings

STYLES = ("direct", "probe")


@dataclasses.dataclass(frozen=True)
class TasksBenchConfig:
    """Benchmark the simulated tasks."""

    tasks: tuple[str, ...] = ("block_pull", "block_pick", "drawer_open", "surgical_grasp_any")
    """Tasks to measure."""
    episodes: int = 100
    """Seeded expert episodes per task and style."""
    prior_episodes: int = 4
    """Episodes of random free-space moves for the transition-prior measure (10 steps each)."""
    workers: int = 2
    """Processes running jobs in parallel (one core each)."""
    seed_base: int = 0
    """First seed."""
    json: bool = False
    """Print exactly one JSON object on stdout."""


def _expert_job(task: str, style: str, episodes: int, seed_base: int) -> dict:
    env = make_env(task)
    success = touched = steps = 0
    fixed_bodies = None
    t0 = time.perf_counter()
    seeds = itertools.count(seed_base)
    for _ in range(episodes):
        # the observable expert (the demos'): a style is a layout, so skip to the next seed that gives it
        obs = env.reset(seed_for_style(env, style, seeds))
        expert = env.task.observable_expert(env)
        # the probe must touch the immovable object: it is whichever slot is not the movable one
        fixed_bodies = [b for b, _ in env.task.object_segments()[_fixed_name(env)]]
        touch = False
        for _ in range(env.settings.max_steps):
            obs, _, terminated, truncated, _ = env.step(expert.act(obs))
            steps += 1
            touch = touch or any(env.gripper_touches(b) for b in fixed_bodies)
            if terminated or truncated:
                break
        success += bool(terminated)
        touched += touch
    elapsed = time.perf_counter() - t0
    env.close()
    return {"task": task, "style": style, "episodes": episodes, "success": success, "success_rate": success / episodes,
            "touched_fixed": touched, "env_steps": steps, "env_steps_per_s": steps / elapsed}  # fmt: skip


def _surgical_job(task: str, randomisation: bool, episodes: int, seed_base: int) -> dict:
    env = make_env(task, SurgicalSettings(randomisation=RandomisationSettings(enabled=randomisation)))
    success = steps = controller_steps = 0
    t0 = time.perf_counter()
    for k in range(episodes):
        seed = seed_base + k
        env.reset(seed)
        oracle = env.task.expert(env, "direct", np.random.default_rng([seed, 3]))
        for _ in range(env.settings.max_steps):
            _, _, terminated, truncated, info = env.step(oracle.act())
            steps += 1
            controller_steps += bool(info["controller_acted"])
            if terminated or truncated:
                break
        success += bool(info["success"])
    elapsed = time.perf_counter() - t0
    env.close()
    return {"task": task, "randomisation": randomisation, "episodes": episodes, "success": success,
            "success_rate": success / episodes, "mean_length": steps / episodes,
            "controller_steps_mean": controller_steps / episodes, "env_steps": steps,
            "env_steps_per_s": steps / elapsed}  # fmt: skip


def _fixed_name(env) -> str:
    """Segment name of the immovable object (privileged; the task records which slot it is)."""
    names = env.task.object_names
    return names[env.task.fixed_index()]


def _prior_job(task: str, episodes: int, seed_base: int) -> dict:
    env = make_env(task)
    samples = []
    for k in range(episodes):
        samples += measure(env, seed_base + k, 10, np.random.default_rng(seed_base + k))
    env.close()
    return {"task": task, **summarise(samples)}


def run(cfg: TasksBenchConfig) -> dict:
    general = [t for t in cfg.tasks if t in GENERAL_TASKS]
    others = [t for t in cfg.tasks if t not in GENERAL_TASKS]
    ctx = mp.get_context("spawn")
    with ctx.Pool(cfg.workers) as pool:
        experts = [
            pool.apply_async(_expert_job, (t, s, cfg.episodes, cfg.seed_base))
            for t in general
            for s in STYLES
        ]
        surgical = [
            pool.apply_async(_surgical_job, (t, dr, cfg.episodes, cfg.seed_base))
            for t in others
            for dr in (False, True)
        ]
        priors = [pool.apply_async(_prior_job, (t, cfg.prior_episodes, cfg.seed_base)) for t in general]
        expert_rows = [r.get() for r in experts]
        surgical_rows = [r.get() for r in surgical]
        prior_rows = [r.get() for r in priors]
    # the reference figure is the general tasks' (the public Equi-RSAC envs); surgical alone stands in
    speeds = [r["env_steps_per_s"] for r in expert_rows or surgical_rows]
    measured = {"env_steps_per_second": min(speeds) if speeds else None}
    meta = {"config": dataclasses.asdict(cfg), "note": "env_steps_per_s: one process, physics + observation"}
    sections = {"experts": expert_rows, "surgical": surgical_rows, "transition_prior": prior_rows}
    return emit("tasks", sections, measured, cfg.json, meta)
