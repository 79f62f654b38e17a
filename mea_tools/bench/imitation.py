"""`mea bench imitation`: the imitation ceiling. Behaviour cloning of the run's recurrent actor on N
scripted demonstrations, evaluated deterministically on the evaluator's held-out seeds.

Design notes: docs/architecture-notes.md, mea_tools/bench/imitation.py."""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pybullet as pb
import torch

from mea_tools.bench.report import emit
from proto.episode import Episode
from proto.seeds import EVAL_SEED_BASE
from proto.weights import WeightsBlob
from services.actor.config import check_expert
from services.actor.rollout import RolloutActor
from services.algorithms.batch import to_batch
from services.algorithms.imitation import Cloner, CloneSettings, held_loss
from services.algorithms.networks import build_actor
from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors
from services.algorithms.replay import SequenceReplay
from services.augmenter.core.pipeline import augment_episode
from services.common import weights_file
from services.common.config import ServiceConfig
from services.episodes.scores import summarize
from services.evaluator.config import EvaluatorConfig
from services.evaluator.evaluation import EpisodeRunner
from services.learner import init_actor
from services.learner.config import learner_presets
from services.plan import actor_config, augmenter_config, learner_config
from services.run_config import RunConfig
from services.tasks import GENERAL_TASKS, make_env
from services.tasks.block_pull import HALF, PullExpert, block_yaw, footprint
from services.tasks.env import EnvSettings
from services.variants import VARIANTS, variant

HELD_EPISODES = 64
"""Episodes of the fixed batch the BC loss is read on (drawn once per clone with its own seed)."""
PROGRESS_EVERY = 500
"""Updates between progress lines on stderr."""


@dataclass(frozen=True)
class ImitationBenchConfig:
    """Clone N scripted demos into the run's actor and evaluate it on the held-out seeds."""

    task: str = "block_pull"
    """Task: block_pull, block_pick or drawer_open."""
    variant: str = "equiobs"
    """As `mea run --variant`: equiobs, mea or equirsac."""
    demos: tuple[int, ...] = (2, 20, 100)
    """Demonstrations cloned, one clone per value and training seed."""
    train_seeds: tuple[int, ...] = (0, 1)
    """Training seeds (network init and batch draws) per demo count."""
    updates: int = 4000
    """Gradient updates per clone."""
    batch: int = 16
    """Whole episodes per update."""
    rotations: int | None = None
    """Rotated copies per demo; None: the learner preset's."""
    mea_copies: int | None = None
    """MEA copies per demo (--variant mea); None: the augmenter's (the paper's 6)."""
    gripper_start: str = "random"
    """As `mea run --gripper-start`: demos recorded and clones evaluated from it."""
    learner_preset: str = "cpu-small"
    """Learner preset whose actor network is cloned into."""
    eval_episodes: int = 50
    """Held-out evaluation episodes per clone (the evaluator's seeds from 1e9)."""
    run_seed: int = 0
    """The run seed whose demonstrations are cloned (`mea run --seed`)."""
    expert: str | None = None
    """Scripted expert: observable or privileged; None: mea run's."""
    out: Path | None = None
    """Write each clone's weights and result.json under DIR/d<N>-s<seed>/, and DIR/imitation.json."""
    threads: int = 1
    """torch intra-op threads."""
    json: bool = False
    """Print exactly one JSON object instead of tables."""

    def __post_init__(self) -> None:
        if self.task not in GENERAL_TASKS:
            raise ValueError(f"--task must be one of {', '.join(GENERAL_TASKS)}, not {self.task!r}")
        fits = [k for k, v in VARIANTS.items() if init_actor.supports(v.algorithm)]  # an actor to clone into
        if self.variant not in fits:
            raise ValueError(f"--variant must be one of {', '.join(fits)}, not {self.variant!r}")
        sac = learner_presets(VARIANTS[self.variant].algorithm)
        if self.learner_preset not in sac:
            raise ValueError(f"--learner-preset must be one of {', '.join(sac)}, not {self.learner_preset!r}")
        if not self.demos or min(self.demos) < 1:
            raise ValueError(f"--demos must be one or more counts >= 1, not {list(self.demos)}")
        if not self.train_seeds or min(self.train_seeds) < 0:
            raise ValueError(f"--train-seeds must be one or more seeds >= 0, not {list(self.train_seeds)}")
        if self.updates < 0 or self.batch < 1 or self.eval_episodes < 1 or self.threads < 1:
            raise ValueError("--updates must be >= 0, --batch, --eval-episodes and --threads >= 1")
        if (self.rotations is not None and self.rotations < 0) or self.run_seed < 0:
            raise ValueError("--rotations and --run-seed must be >= 0")
        EnvSettings(gripper_start=self.gripper_start)  # its check, in one line
        if self.mea_copies is not None and (self.mea_copies < 0 or self.variant != "mea"):
            raise ValueError(f"--mea-copies must be >= 0 and needs --variant mea, not {self.mea_copies} "
                             f"with --variant {self.variant}")  # fmt: skip

        if self.expert is not None:
            check_expert(self.expert)
        if self.out is not None and self.out.exists() and not self.out.is_dir():
            raise ValueError(f"--out: {str(self.out)!r} is a file, not a directory")


# ------------------------------------------------------------------------------------------------
# the run's settings, demonstrations and replay
# ------------------------------------------------------------------------------------------------


def run_config(cfg: ImitationBenchConfig):
    """The `mea run` whose demos, augmentation and learner network are cloned."""
    return RunConfig(task=cfg.task, variant=cfg.variant, learner_preset=cfg.learner_preset, seed=cfg.run_seed,
                     demos=max(cfg.demos), success_rotations=cfg.rotations, gripper_start=cfg.gripper_start)  # fmt: skip


def record_demos(run, n: int, expert: str | None = None) -> list:
    """The first ``n`` demonstrations `mea run` records (actor 0 of ``run``: its expert, seeds, styles
    and attempt cap; ``expert`` another of its experts), as the augmenter receives them (through the
    wire codec)."""
    acfg = dataclasses.replace(actor_config(run, 0, ServiceConfig()), demos=n)
    if expert is not None:
        acfg = dataclasses.replace(acfg, expert=expert)
    actor = RolloutActor(acfg, "actor-0")
    kept, attempts = [], 0
    while len(kept) < n and attempts < n * acfg.max_demo_attempts:
        b = actor.expert_episode(len(kept))
        attempts += 1
        if b.success:
            kept.append(Episode.decode(b.finish(actor.episode_id(b)).encode()))
    actor.env.close()
    return kept


def demo_replay(demos: list, run, learner, mea_copies: int | None = None) -> tuple[Any, dict[str, int]]:
    """A ``SequenceReplay`` of the learner's shape holding ``demos`` and every copy the run's augmenter
    makes of them (``mea_copies`` MEA copies each where given), sized to fit them all; and its counts."""
    settings = augmenter_config(run, ServiceConfig()).augment
    if mea_copies is not None:
        settings = dataclasses.replace(settings, mea_copies=mea_copies)
    per_demo = [
        1 + settings.isometric_count(d) + (settings.mea_count(d) if settings.applies_mea(d) else 0)
        for d in demos
    ]
    capacity = sum(k * d.num_steps for k, d in zip(per_demo, demos, strict=True))
    net = learner.algorithm.net
    replay = SequenceReplay(max(capacity, learner.seq_len), image_size=net.image_size,
                            seq_len=learner.seq_len, channels=net.in_channels, seed=0,
                            max_episodes=max(1, sum(per_demo)))  # fmt: skip
    episodes = 0
    for d in demos:
        outputs, _ = augment_episode(d, settings)
        for ep in outputs:
            replay.insert(ep)
        episodes += len(outputs)
    return replay, {"demos": len(demos), "episodes": episodes, "transitions": len(replay)}


# ------------------------------------------------------------------------------------------------
# evaluation
# ------------------------------------------------------------------------------------------------


class BetweenBlocks:
    """Block Pull: episodes in which the paddle went down between the two blocks (its tool centre
    low enough for the closed tips to be below the blocks' tops, between their inner faces along the
    pulling line, within a block's width of their x). Read from the simulator after every step."""

    def __init__(self, env) -> None:
        self.env = env
        # PullExpert.PUSH_Z holds the closed tips about 1 cm above the floor
        self.low_z = 2 * float(HALF[2]) + PullExpert.PUSH_Z - 0.01
        self.now = False
        self.episodes = 0

    def step(self, _seconds: float) -> None:
        env, task = self.env, self.env.task
        tcp = env.robot.tcp()
        poses = [
            pb.getBasePositionAndOrientation(b, physicsClientId=env.client)
            for b in (task.fixed, task.movable)
        ]
        (lo, lo_yaw), (hi, hi_yaw) = sorted(((p[1], block_yaw(q)) for p, q in poses))
        x = 0.5 * (poses[0][0][0] + poses[1][0][0])
        inside = lo + footprint(lo_yaw) < tcp[1] < hi - footprint(hi_yaw) and abs(tcp[0] - x) < footprint(0.0)
        self.now = self.now or (tcp[2] < self.low_z and inside)

    def end(self, _seconds: float) -> None:
        self.episodes += int(self.now)
        self.now = False


def evaluate(
    blob,
    task: str,
    depth_image: bool,
    episodes: int,
    gripper_start: str = "random",
    seed_base: int = EVAL_SEED_BASE,
    deterministic: bool = True,
) -> dict[str, Any]:
    """``blob``'s deterministic policy (or, not ``deterministic``, the policy sampled as actors sample
    it, noise seeded) on ``episodes`` held-out seeds from ``seed_base`` (the evaluator's first by
    default), in the evaluator's env through its ``EpisodeRunner``."""
    ecfg = EvaluatorConfig(task=task, episodes=episodes, depth_image=depth_image, gripper_start=gripper_start,
                           seed_base=seed_base)  # fmt: skip
    env = make_env(task, ecfg.env_settings())
    probe = BetweenBlocks(env) if task == "block_pull" else None
    runner = EpisodeRunner(env, task, "imitation", None if probe is None else probe.step,
                           None if probe is None else probe.end)  # fmt: skip
    runtime = PolicyRuntime(deterministic=deterministic)
    runtime.load(blob)
    try:
        results = runner.episodes(runtime, ecfg.seeds)
    finally:
        env.close()
    summary = summarize(results, env.settings.max_steps)
    return {"success": summary.success_rate, "successes": sum(r.success for r in results), "episodes": len(results),
            "mean_length": summary.mean_length, "lowered_between": None if probe is None else probe.episodes,
            "seeds": [ecfg.seeds[0], ecfg.seeds[-1]]}  # fmt: skip


# ------------------------------------------------------------------------------------------------
# one clone
# ------------------------------------------------------------------------------------------------


def _log(msg: str) -> None:
    print(f"[bench imitation] {msg}", file=sys.stderr, flush=True)


def clone(replay, learner, seed: int, updates: int, batch: int, tag: str):
    """A fresh actor of ``learner``'s network (initialised as the learner initialises it with ``seed``)
    cloned for ``updates`` steps; (actor, BC loss on a fixed batch before and after, seconds)."""
    torch.manual_seed(seed)  # as build_trainer: the actor is the first network drawn
    algo = learner.algorithm
    actor = build_actor(algo.net)
    settings = CloneSettings(batch_size=batch, lr=algo.sac.lr, demo_fraction=learner.demo_fraction,
                             successes_as_demos=learner.successes_as_demos, trim=algo.trim_batches)  # fmt: skip
    cloner = Cloner(actor, replay, np.random.default_rng(seed), settings)
    held = to_batch(replay.sample(HELD_EPISODES, np.random.default_rng([seed, 1]), trim=True))
    before = held_loss(actor, held)
    t0 = time.perf_counter()
    cloner.run(
        updates, PROGRESS_EVERY, lambda k, loss: _log(f"{tag}: {k}/{updates} updates, BC loss {loss:.4f}")
    )
    seconds = time.perf_counter() - t0
    return actor, before, held_loss(actor, held), seconds


def clone_blob(actor, learner, run_id: str):
    """The clone as the learner publishes its actor: a ``WeightsBlob`` with the policy spec."""
    algo = learner.algorithm
    spec = PolicySpec(algo.net, algo.observation).to_json()
    return WeightsBlob.create(0, algo.name, run_id, actor_tensors(actor), spec)


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=2, default=float) + "\n")
    tmp.replace(path)


# ------------------------------------------------------------------------------------------------
# the benchmark
# ------------------------------------------------------------------------------------------------


def summary_rows(rows: list[dict]) -> list[dict]:
    """Per demo count: success mean ± std (and range) over training seeds, the sampled policy's mean
    success, lowered-between mean, wall time."""
    out = []
    for n in sorted({r["demos"] for r in rows}):
        rs = [r for r in rows if r["demos"] == n]
        s = np.array([r["success"] for r in rs], float)
        row = {"demos": n, "seeds": len(rs), "success": f"{s.mean():.2f} ± {s.std():.2f}",
               "success_mean": float(s.mean()), "success_std": float(s.std()),
               "success_min": float(s.min()), "success_max": float(s.max()),
               "sampled_success_mean": float(np.mean([r["sampled_success"] for r in rs]))}  # fmt: skip
        if rs[0].get("lowered_between") is not None:
            row["lowered_between_mean"] = float(np.mean([r["lowered_between"] for r in rs]))
        row["wall_s"] = float(sum(r["train_s"] + r["eval_s"] for r in rs))
        out.append(row)
    return out


def run(cfg: ImitationBenchConfig) -> dict:
    torch.set_num_threads(cfg.threads)
    rc = run_config(cfg)
    learner = learner_config(rc, Path("unused"), ServiceConfig())
    t0 = time.perf_counter()
    expert = cfg.expert or actor_config(rc, 0, ServiceConfig()).expert
    stream = record_demos(rc, max(cfg.demos), expert)
    _log(f"{len(stream)} demonstrations recorded ({time.perf_counter() - t0:.1f} s): seeds "
         f"{[int(e.seed) for e in stream[:8]]}{' ...' if len(stream) > 8 else ''}")  # fmt: skip
    if len(stream) < max(cfg.demos):
        _log(f"the expert gave {len(stream)} of {max(cfg.demos)} demos; larger counts use what there is")
    rows: list[dict] = []
    for n in sorted(set(cfg.demos)):
        replay, counts = demo_replay(stream[:n], rc, learner, cfg.mea_copies)
        _log(f"{n} demos: {counts['episodes']} episodes, {counts['transitions']} transitions in replay")
        for seed in cfg.train_seeds:
            tag = f"d{n}-s{seed}"
            actor, before, after, train_s = clone(replay, learner, seed, cfg.updates, cfg.batch, tag)
            blob = clone_blob(actor, learner, f"imitation-{cfg.task}-{cfg.variant}-{tag}")
            e0 = time.perf_counter()
            depth = variant(cfg.variant).depth_image
            ev = evaluate(blob, cfg.task, depth, cfg.eval_episodes, cfg.gripper_start)
            # as actors act it (and an online learner's critic targets sample it): its log std matters
            sampled = evaluate(
                blob, cfg.task, depth, cfg.eval_episodes, cfg.gripper_start, deterministic=False
            )
            row = {"demos": n, "train_seed": seed, "success": ev["success"], "sampled_success": sampled["success"],
                   "lowered_between": ev["lowered_between"],
                   "bc_loss_start": before, "bc_loss_end": after, "updates": cfg.updates,
                   "train_s": round(train_s, 1), "eval_s": round(time.perf_counter() - e0, 1)}  # fmt: skip
            if ev["lowered_between"] is None:
                row.pop("lowered_between")
            _log(f"{tag}: success {ev['successes']}/{ev['episodes']}, BC loss {before:.4f} -> {after:.4f}")
            if cfg.out is not None:
                path = weights_file.write(cfg.out / tag / weights_file.DIRECTORY, blob)
                _write_json(
                    cfg.out / tag / "result.json", {**row, **counts, "evaluation": ev, "weights": str(path)}
                )
            rows.append(row)
        del replay
    meta = {"task": cfg.task, "variant": cfg.variant, "learner_preset": cfg.learner_preset,
            "group": learner.algorithm.net.group, "observation": learner.algorithm.observation, "run_seed": cfg.run_seed,
            "expert": expert,
            "rotations": rc.resolved_success_rotations(), "mea_copies": cfg.mea_copies, "gripper_start": cfg.gripper_start, "batch": cfg.batch, "updates": cfg.updates,
            "eval_episodes": cfg.eval_episodes, "demo_seeds": [int(e.seed) for e in stream],
            "demo_styles": [e.policy_kind for e in stream]}  # fmt: skip
    sections = {"clones": rows, "per demo count (mean ± std over training seeds)": summary_rows(rows)}
    result = emit("imitation", sections, {}, cfg.json, meta)
    if cfg.out is not None:
        _write_json(cfg.out / "imitation.json", result)
    return result


__all__ = ["BetweenBlocks", "ImitationBenchConfig", "run"]
