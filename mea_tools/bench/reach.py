"""`mea bench reach`: the RL core against a known answer. This project's recurrent SAC (its update,
its replay of whole episodes, its networks and its policy runtime) trained with the public Equi-RSAC
recipe on a sparse-reward 2D reach (``reach_task``), by the state or by pixels, beside what a
well-kept SAC does on the same task.

Known answers (docs/results.md, "The RL core against a known answer" and "The memory reach against
the public code's own learner"): Stable-Baselines3 2.9.2's SAC with the same γ, τ, learning rate,
α₀, target entropy, batch of 32 and the same 15 demonstrations solves the reach from the state by
12K env steps on both seeds it ran (1.00 on the 20 goals from 11.5-12K, 0 until 7K); through the
11 x 11 image it stays at 0.00-0.15 to 16K. The public Equi-RSAC code's own recurrent SAC, with the
goal shown once (``goal_steps`` 1), reaches 0.20-0.45 by 10K.

The loop is the public code's order: the demonstrations, then the random episodes, then one rollout
of the current stochastic policy at a time; after each episode, one update per env step it added.
Every ``eval_every`` env steps the deterministic policy runs on ``eval_goals`` fixed starts.

Design notes: docs/benchmarks.md#mea-bench-reach."""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mea_tools.bench import reach_task as rt
from mea_tools.bench.report import emit
from proto.actions import ACTION_DIM
from proto.episode import Episode
from proto.seeds import EVAL_SEED_BASE
from services.algorithms.batch import to_batch
from services.algorithms.imitation import Cloner, CloneSettings
from services.algorithms.networks import NetConfig
from services.algorithms.replay import SequenceReplay
from services.algorithms.sac.algorithm import SacConfig
from services.algorithms.sac.config import ALPHA_LOSSES, SacSettings
from services.algorithms.sac.policy import ActorRuntime

GROUPS = ("none", "c4")
KNOWN: dict[tuple[str, int], dict[str, tuple[float | None, ...]]] = {
    ("state", 0): {
        "known answer: SB3 SAC, state, s0": (0.00, 0.00, 0.00, 0.25, 0.70, 1.00),
        "known answer: SB3 SAC, state, s1": (0.00, 0.00, 0.00, 0.20, 0.20, 1.00),
        "known answer: the public code's recurrent SAC, s0": (0.10, 0.30, 1.00, None, None, None),
        "known answer: the public code's recurrent SAC, s1": (0.00, 0.45, 0.90, None, None, None),
    },
    ("state", 1): {
        "known answer: the public code's recurrent SAC, s0": (0.00, 0.15, 0.20, 0.25, 0.20, None),
        "known answer: the public code's recurrent SAC, s1": (0.00, 0.10, 0.20, 0.10, 0.45, None),
    },
}
"""Success at ``KNOWN_MILESTONES`` env steps of the reference runs per (observation, goal steps), the
same task and recipe (docs/results.md): Stable-Baselines3 2.9.2's SAC with the goal in view, and the
public Equi-RSAC code's own recurrent SAC (its plain LSTM actor and critic, its replay; run to 6.5K
with the goal in view, 10K with it shown once)."""
KNOWN_MILESTONES = (2000, 4000, 6000, 8000, 10000, 12000)


@dataclass(frozen=True)
class ReachBenchConfig:
    """Recurrent SAC (the public recipe) on the sparse-reward reach, per seed, beside the known answer."""

    observation: str = "state"
    """state (4 coordinates), image (point and goal marked) or centred (the goal's offset, centred)."""
    group: str = "none"
    """Networks: none (plain layers) or c4 (Equi-RSAC's; image only)."""
    env_steps: int = 12000
    """Env steps per run, demonstrations and random episodes included (the public count)."""
    seeds: tuple[int, ...] = (0, 1)
    """Training seeds, one run each."""
    demos: int = 15
    """Straight-line demonstrations stored first."""
    random_episodes: int = 20
    """Uniform-random episodes stored after them."""
    eval_every: int = 500
    """Env steps between deterministic evaluations."""
    eval_goals: int = 20
    """Fixed starts per evaluation."""
    image_size: int = 11
    """N of the N x N image (odd; 0.2 per pixel at 11)."""
    batch_size: int = 32
    """Whole episodes per update."""
    updates_per_step: float = 1.0
    """Updates per env step."""
    alpha_lr: float = 1e-3
    """Temperature learning rate (the public 1e-3)."""
    alpha_loss: str = "alpha"
    """Temperature loss (``SacSettings.alpha_loss``): alpha (the public code) or log_alpha (SB3)."""
    goal_steps: int = 0
    """Show the goal in the first K observations only (0: always), so the policy must remember it."""
    actor_prev_action: bool = True
    """The actor's LSTM reads a_{t-1} (Equi-RSAC); the critic's always does."""
    fixed_alpha: float = 0.0
    """Hold α at this value instead of tuning it (0: tuned from 0.1)."""
    backup_entropy: bool = True
    """Critic targets include the entropy bonus (``SacSettings.backup_entropy``)."""
    share_encoder: bool = False
    """The actor reads the critic's encoder, detached (the public code: separate encoders)."""
    clone_updates: int = 0
    """BC updates of the actor on the demonstrations before the first learned rollout (0: none)."""
    threads: int = 1
    """torch intra-op threads."""
    out: Path | None = None
    """Write DIR/reach-<arm>-s<seed>.jsonl (one line per evaluation) and DIR/reach.json."""
    json: bool = False
    """Print exactly one JSON object instead of tables."""

    def __post_init__(self) -> None:
        if self.observation not in rt.OBSERVATIONS:
            raise ValueError(
                f"--observation must be one of {', '.join(rt.OBSERVATIONS)}, not {self.observation!r}"
            )
        if self.group not in GROUPS:
            raise ValueError(f"--group must be one of {', '.join(GROUPS)}, not {self.group!r}")
        if self.group != "none" and self.observation == "state":
            raise ValueError(
                "--group c4 needs --observation image or centred (the state's coordinates are not images)"
            )
        if self.observation != "state":
            rt.check_image_size(self.image_size)
        if not self.seeds or min(self.seeds) < 0:
            raise ValueError(f"--seeds must be one or more seeds >= 0, not {list(self.seeds)}")
        for name in ("env_steps", "eval_every", "eval_goals", "batch_size", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1, not {getattr(self, name)}")
        if self.demos < 0 or self.random_episodes < 0 or self.demos + self.random_episodes < 1:
            raise ValueError("--demos and --random-episodes must be >= 0, and store at least one episode")
        if self.fixed_alpha < 0:
            raise ValueError(f"--fixed-alpha must be >= 0 (0: tuned), not {self.fixed_alpha}")
        if self.goal_steps < 0:
            raise ValueError(f"--goal-steps must be >= 0, not {self.goal_steps}")
        if self.clone_updates < 0 or (self.clone_updates and not self.demos):
            raise ValueError(f"--clone-updates must be >= 0 and needs --demos > 0, not {self.clone_updates}")
        if self.alpha_loss not in ALPHA_LOSSES:
            raise ValueError(
                f"--alpha-loss must be one of {', '.join(ALPHA_LOSSES)}, not {self.alpha_loss!r}"
            )
        if not 0 < self.updates_per_step <= 16 or self.alpha_lr <= 0:
            raise ValueError("--updates-per-step must be in (0, 16] and --alpha-lr > 0")
        if self.out is not None and self.out.exists() and not self.out.is_dir():
            raise ValueError(f"--out: {str(self.out)!r} is a file, not a directory")


# ------------------------------------------------------------------------------------------------
# the learner's pieces, as the learner builds them
# ------------------------------------------------------------------------------------------------


def net_config(cfg: ReachBenchConfig) -> NetConfig:
    """Small widths: for the state a 1 x 1 "image" of its four coordinates (and the goal-shown flag
    with ``goal_steps``), so the encoder is an MLP on them; for the image two stride-2 convolutions."""
    common = dict(image_embed=64, action_embed=16, q_action_embed=64, lstm_hidden=64, mlp_hidden=(64, 64),
                  actor_prev_action=cfg.actor_prev_action)  # fmt: skip
    if cfg.observation == "state":
        return NetConfig(
            group="none",
            image_size=1,
            in_channels=rt.channels("state", cfg.goal_steps),
            encoder=((16, 1, 1),),
            final_kernel=1,
            **common,
        )
    n = rt.image_side(cfg.observation, cfg.image_size)
    first = 3 if (n - 3) // 2 % 2 == 0 else 5  # a grid symmetric under quarter turns (NetConfig's check)
    encoder = ((8, first, 2), (16, 3, 2))
    return NetConfig(group=cfg.group, image_size=n, in_channels=rt.channels(cfg.observation), encoder=encoder,
                     final_kernel=_final_kernel(n, encoder), **common)  # fmt: skip


def _final_kernel(n: int, encoder: tuple[tuple[int, int, int], ...]) -> int:
    for _, k, stride in encoder:
        n = (n - k) // stride + 1
    return n


def sac_config(cfg: ReachBenchConfig) -> SacConfig:
    """The public recipe: no BC, separate encoders, α from 0.1, γ 0.9 (``SacSettings``' defaults)."""
    name = "rsac" if cfg.group == "none" else "equi_rsac"
    return SacConfig(
        name=name,
        net=net_config(cfg),
        sac=SacSettings(
            alpha_lr=cfg.alpha_lr,
            alpha_loss=cfg.alpha_loss,
            share_encoder=cfg.share_encoder,
            init_alpha=cfg.fixed_alpha or 0.1,
            autotune_alpha=not cfg.fixed_alpha,
            backup_entropy=cfg.backup_entropy,
        ),
    )


def episode(
    states: list[rt.ReachState],
    actions: list[np.ndarray],
    reached: bool,
    cfg: ReachBenchConfig,
    kind: str,
    serial: int,
) -> Episode:
    """The episode as an actor would publish it; the privileged arrays hold the point (gripper pose)."""
    T = len(actions)
    pose = np.zeros((T + 1, 4), np.float32)
    pose[:, :2] = [s.point for s in states]
    rewards = np.zeros(T, np.float32)
    rewards[-1] = float(reached)
    end = np.zeros(T, bool)
    end[-1] = True
    return Episode(
        episode_id=f"reach-{serial}-0",
        task="block_pull",  # the schema's task names; nothing here reads it
        seed=serial,
        actor_id="reach",
        policy_version=-1 if kind != "learned" else 0,
        policy_kind=kind,
        is_demo=kind == "expert_direct",
        created_at=1.0,
        segments=["gripper"],
        points=np.zeros((T + 1, 1, 1, 3), np.float32),
        point_counts=np.zeros((T + 1, 1), np.int32),
        jaw=np.zeros(T + 1, np.float32),
        actions=np.stack(actions).astype(np.float32),
        rewards=rewards,
        terminated=end & reached,
        truncated=end & (not reached),
        gripper_pose=pose,
        object_poses=np.zeros((T + 1, 0, 7), np.float32),
        contacts=np.zeros((T + 1, 0), bool),
        images=np.stack(
            [rt.observe(s, cfg.observation, cfg.image_size, t, cfg.goal_steps) for t, s in enumerate(states)]
        ),
    )


def rollout(
    start: rt.ReachState, act, cfg: ReachBenchConfig
) -> tuple[list[rt.ReachState], list[np.ndarray], bool]:
    """One episode from ``start``; ``act(state, t) -> action``."""
    states, actions, reached = [start], [], False
    while len(actions) < rt.MAX_STEPS and not reached:
        a = np.asarray(act(states[-1], len(actions)), np.float32)
        s, _, reached = rt.step(states[-1], a)
        states.append(s)
        actions.append(a)
    return states, actions, reached


def policy_act(runtime: ActorRuntime, cfg: ReachBenchConfig):
    runtime.reset()

    def act(s: rt.ReachState, t: int) -> np.ndarray:
        a = runtime.act(rt.observe(s, cfg.observation, cfg.image_size, t, cfg.goal_steps))
        runtime.executed(a)
        return a

    return act


LATER_MOVES = 2
"""Moves after the first that ``evaluate_headings`` reads: from the nearest start
(``MIN_START_DISTANCE``) to within ``RADIUS`` takes at least three diagonal steps."""


def heading(s: rt.ReachState, action: np.ndarray) -> float:
    """cos of the angle between the move (dx, dy) and the way to the goal (0 for no move)."""
    move, way = np.clip(action[1:3], -1.0, 1.0), s.goal - s.point
    norm = float(np.linalg.norm(move) * np.linalg.norm(way))
    return float(move @ way) / norm if norm > 0 else 0.0


def evaluate_headings(runtime: ActorRuntime, cfg: ReachBenchConfig) -> dict[str, float]:
    """Deterministic success on the fixed starts (seeded like the evaluator's held-out seeds), and the
    mean heading (``heading``) of the first move and of the next ``LATER_MOVES`` (every start needs
    them, so no episode ends before them): with the goal hidden after the first step, a policy that
    sees it but cannot carry it scores high on the first and low on the next."""
    wins, first, later = 0, [], []
    for i in range(cfg.eval_goals):
        start = rt.draw_start(np.random.default_rng(EVAL_SEED_BASE + i))
        states, actions, reached = rollout(start, policy_act(runtime, cfg), cfg)
        wins += reached
        cos = [heading(s, a) for s, a in zip(states, actions, strict=False)]
        first.append(cos[0])
        later += cos[1 : 1 + LATER_MOVES]
    return {"success": wins / cfg.eval_goals, "heading_first": float(np.mean(first)),
            "heading_later": float(np.mean(later)) if later else math.nan}  # fmt: skip


# ------------------------------------------------------------------------------------------------
# one run
# ------------------------------------------------------------------------------------------------


def train(cfg: ReachBenchConfig, seed: int, log=None) -> dict[str, Any]:
    """One run: its evaluations (env steps, success, α, entropy) and its speed."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    sac = sac_config(cfg)
    agent = sac.build(seed, torch.device("cpu"))
    replay = SequenceReplay(max(cfg.env_steps, 1000) * 2, image_size=sac.net.image_size, seq_len=rt.MAX_STEPS,
                            constant_channels=(), channels=sac.net.in_channels, seed=seed)  # fmt: skip
    explore = ActorRuntime.of(agent.actor, sac.spec(), deterministic=False)
    explore.generator = torch.Generator().manual_seed(seed)
    greedy = ActorRuntime.of(agent.actor, sac.spec(), deterministic=True)
    curve: list[dict[str, float]] = []
    stats: dict[str, float] = {}
    env_steps, credit, serial, update_seconds = 0, 0.0, 0, 0.0
    t0 = time.perf_counter()

    def record() -> None:
        row = {"env_steps": env_steps, **evaluate_headings(greedy, cfg), "updates": agent.updates,
               "alpha": stats.get("alpha", math.nan), "entropy": stats.get("entropy", math.nan)}  # fmt: skip
        curve.append(row)
        if log is not None:
            log(row)

    record()
    while env_steps < cfg.env_steps:
        start = rt.draw_start(rng)
        if serial < cfg.demos:
            kind, act = "expert_direct", lambda s, _t: rt.expert_action(s)
        elif serial < cfg.demos + cfg.random_episodes:
            kind, act = "random", lambda _s, _t: rng.uniform(-1.0, 1.0, ACTION_DIM)
        else:
            kind, act = "learned", policy_act(explore, cfg)
        states, actions, reached = rollout(start, act, cfg)
        replay.insert_episode(episode(states, actions, reached, cfg, kind, serial))
        serial += 1
        before = env_steps
        env_steps += len(actions)
        credit += len(actions) * cfg.updates_per_step
        u0 = time.perf_counter()
        while credit >= 1.0:
            batch = to_batch(replay.sample(cfg.batch_size, rng, trim=True))
            stats = agent.update(batch)
            credit -= 1.0
        update_seconds += time.perf_counter() - u0
        if cfg.clone_updates and serial == cfg.demos + cfg.random_episodes:
            # the actor (not the critic, nor its own optimiser) starts from a clone of the demos
            clone = CloneSettings(batch_size=cfg.batch_size, lr=sac.sac.lr, demo_fraction=1.0)
            Cloner(agent.actor, replay, rng, clone).run(cfg.clone_updates)
            record()  # before its first rollout
        if env_steps // cfg.eval_every > before // cfg.eval_every:
            record()
    wall = time.perf_counter() - t0
    return {"seed": seed, "curve": curve, "env_steps": env_steps, "wall_seconds": wall,
            "update_ms": 1000 * update_seconds / max(agent.updates, 1), "updates": agent.updates}  # fmt: skip


def at(curve: list[dict[str, float]], steps: int) -> float | None:
    """Success at the last evaluation at or before ``steps`` (None if the run stopped before)."""
    rows = [r for r in curve if r["env_steps"] <= steps]
    if not rows or curve[-1]["env_steps"] < steps - rt.MAX_STEPS:
        return None
    return rows[-1]["success"]


def first_solved(curve: list[dict[str, float]], level: float = 0.9) -> int | None:
    """Env steps of the first evaluation at or above ``level``."""
    return next((int(r["env_steps"]) for r in curve if r["success"] >= level), None)


def _headings(row: dict[str, float]) -> str:
    return f"{row['heading_first']:.2f} / {row['heading_later']:.2f}"


def arm_name(cfg: ReachBenchConfig) -> str:
    """observation-group, then what differs from the public recipe."""
    parts = [cfg.observation, cfg.group]
    if cfg.goal_steps:
        parts.append(f"goal{cfg.goal_steps}")
    if not cfg.actor_prev_action:
        parts.append("noprev")
    if cfg.fixed_alpha:
        parts.append(f"alpha{cfg.fixed_alpha:g}")
    if not cfg.backup_entropy:
        parts.append("nobackup")
    if cfg.share_encoder:
        parts.append("shared")
    if cfg.clone_updates:
        parts.append(f"clone{cfg.clone_updates}")
    if (cfg.alpha_loss, cfg.alpha_lr) != ("alpha", 1e-3):
        parts.append(f"{cfg.alpha_loss}{cfg.alpha_lr:g}")
    return "-".join(parts)


def known_rows(cfg: ReachBenchConfig) -> list[dict[str, Any]]:
    """The table's rows of the known answers for this observation and goal steps (none elsewhere)."""
    return [
        {"run": name, **{f"{m // 1000}K": v for m, v in zip(KNOWN_MILESTONES, vals, strict=True)},
         "first >= 0.9": None, "heading 1st / next (last)": None, "update ms": None, "wall s": None}
        for name, vals in KNOWN.get((cfg.observation, cfg.goal_steps), {}).items()
    ]  # fmt: skip


def run(cfg: ReachBenchConfig) -> dict[str, Any]:
    torch.set_num_threads(cfg.threads)
    arm = arm_name(cfg)
    if cfg.out is not None:
        cfg.out.mkdir(parents=True, exist_ok=True)
    runs = []
    for seed in cfg.seeds:
        path = None if cfg.out is None else cfg.out / f"reach-{arm}-s{seed}.jsonl"
        if path is not None:
            path.write_text("")

        def log(row: dict[str, float], seed: int = seed, path: Path | None = path) -> None:
            print(f"[reach {arm} s{seed}] {json.dumps(row)}", file=sys.stderr, flush=True)
            if path is not None:
                with path.open("a") as f:
                    f.write(json.dumps(row) + "\n")

        runs.append(train(cfg, seed, log))
    rows = [
        {"run": f"this learner, {arm}, s{r['seed']}",
         **{f"{m // 1000}K": at(r["curve"], m) for m in KNOWN_MILESTONES},
         "first >= 0.9": first_solved(r["curve"]), "heading 1st / next (last)": _headings(r["curve"][-1]),
         "update ms": r["update_ms"], "wall s": r["wall_seconds"]}
        for r in runs
    ]  # fmt: skip
    known = known_rows(cfg)
    title = "beside the known answer" if known else "no known answer for this task"
    result = emit(
        "reach",
        {f"success on {cfg.eval_goals} fixed goals, {title}": rows + known},
        {},
        cfg.json,
        meta={"config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()}},
    )
    if cfg.out is not None:
        (cfg.out / "reach.json").write_text(json.dumps({"runs": runs, **result}, default=float))
    return result
