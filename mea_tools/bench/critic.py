"""`mea bench critic --run RUN_DIR`: what a recurrent SAC run's critic says along its own replay.

Reads the run's newest learner checkpoint (networks and replay) and prints, per kind of stored
episode (demonstrations with their copies, online successes, the latest online failures), the
critic's value of the recorded action beside the same move turned a quarter, reversed, uniform
random actions and the policy's mean, step by step back from the episode's end and from its start
(``services.algorithms.sac.critic_profile``); with ``--targets`` also the live critic's value of
the recorded action and the learner's TD target for it (how far the critic is from what it is
fitted to). With ``--handover N`` it also plays the policy in the simulator from the first N
recorded demonstrations' own states, k steps before their end, beside the critic's value of the
policy's action there (``mea_tools.bench.handover``), and with ``--handover-moves`` the
demonstrated move and its reverse played there before the policy, beside the critic's values of
the two; with ``--behaviour N`` it plays the policy from the evaluator's first N held-out starts
and sums up what the fingers and objects did (``mea_tools.bench.behaviour``). Nothing is written;
the run may be training."""

from __future__ import annotations

import contextlib
import functools
import itertools
import json
import math
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from services.algorithms.batch import to_batch
from services.algorithms.networks import NetConfig
from services.algorithms.registry import lookup
from services.algorithms.replay import SequenceReplay
from services.algorithms.sac.algorithm import SacConfig
from services.algorithms.sac.config import SacSettings
from services.algorithms.sac.critic_profile import COLUMNS, StepProfile, step_profile
from services.algorithms.sac.losses import reversed_move
from services.common.config import refuse
from services.learner import checkpoint

if TYPE_CHECKING:
    from mea_tools.bench.handover import Handover, RecordedDemo
    from services.tasks import EnvSettings

PROG = "mea bench critic"
KINDS = {"demos": {"demo": True}, "successes": {"demo": False, "success": True},
         "failures": {"demo": False, "success": False}}  # fmt: skip
"""Kinds of stored episodes profiled, and the replay's selection of each."""


@dataclass(frozen=True)
class CriticBenchConfig:
    """Profile a run's critic along its stored demonstrations, successes and failures."""

    run: Path | None = None
    """The run directory (RUN_DIR of `mea run`) whose newest learner checkpoint is read."""
    steps: int = 10
    """Steps profiled back from each episode's end and from its start."""
    episodes: int = 200
    """Stored episodes per kind: the first demonstrations, the latest successes and failures."""
    random_actions: int = 8
    """Uniform random actions rated per step (their mean is the ``random`` column)."""
    targets: bool = False
    """Also the live critic's Q of the recorded action and the learner's TD target for it (seeded)."""
    batch: int = 16
    """Episodes per forward pass."""
    threads: int = 1
    """torch threads (a training run may share the cores)."""
    handover: int = 0
    """Play the policy from the first this many recorded demonstrations' own states (0: off)."""
    handover_steps: tuple[int, ...] = (1, 2, 4, 8)
    """Steps before each demonstration's end at which the policy takes over."""
    handover_moves: bool = False
    """With --handover: also play the demo's own action, and that move reversed, before the policy."""
    behaviour: int = 0
    """Held-out starts from which the policy plays, to sum up what it did (0: off)."""
    climb: int = 0
    """Actor updates on the frozen target critic, played on held-out seeds (0: off)."""
    climb_every: int = 10
    """With --climb: updates between the plays."""
    climb_actor: Path | None = None
    """With --climb: the actor's starting weights (None: the checkpoint's)."""
    climb_episodes: int = 20
    """With --climb: held-out seeds per play."""
    json: bool = False
    """Print exactly one JSON object instead of tables."""

    def __post_init__(self) -> None:
        if self.run is None:
            raise ValueError("--run is required: a run directory with learner checkpoints")
        if min(self.steps, self.episodes, self.random_actions, self.batch, self.threads) < 1:
            raise ValueError("--steps, --episodes, --random-actions, --batch and --threads must be >= 1")
        if self.handover < 0:
            raise ValueError(f"--handover must be >= 0, got {self.handover}")
        if self.handover_moves and not self.handover:
            raise ValueError("--handover-moves plays from the demonstrations' states: give --handover N too")
        if self.behaviour < 0:
            raise ValueError(f"--behaviour must be >= 0, got {self.behaviour}")
        if self.climb < 0 or self.climb_every < 1 or self.climb_episodes < 1:
            raise ValueError("--climb must be >= 0, --climb-every and --climb-episodes >= 1")
        if self.climb_actor is not None and not self.climb:
            raise ValueError("--climb-actor is where a climb starts: give --climb N too")
        if not self.handover_steps or min(self.handover_steps) < 1:
            raise ValueError(f"--handover-steps must be one or more integers >= 1, got {self.handover_steps}")


def _algorithm(run: Path) -> SacConfig:
    """The run learner's recurrent SAC settings from RUN_DIR/learner/learner.json; refused in one line."""
    path = run / "learner" / "learner.json"
    try:
        algo = json.loads(path.read_text())["algorithm"]
    except FileNotFoundError:
        refuse(PROG, f"{path}: no such file (is {run} a run directory whose learner has started?)")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        refuse(PROG, f"{path}: not a learner's settings ({type(exc).__name__}: {exc})")
    name = algo.get("name") if isinstance(algo, dict) else algo
    try:
        sac = lookup(str(name)).config is SacConfig
    except ValueError:
        sac = False
    if not sac:
        refuse(
            PROG, f"{path}: the learner is {name!r}; this profiles recurrent SAC critics (equi_rsac, rsac)"
        )
    try:
        return SacConfig(name=algo["name"], net=NetConfig.from_dict(algo["net"]), sac=SacSettings(**algo["sac"]),
                         observation=algo.get("observation", "voxel"))  # fmt: skip
    except (KeyError, TypeError, ValueError) as exc:
        refuse(PROG, f"{path}: its settings do not build a learner here ({type(exc).__name__}: {exc})")


def _table(kind: str, count: int, profile: StepProfile) -> str:
    where = (
        "steps back from the end (1 = the last transition)" if profile.from_end else "steps from the start"
    )
    head = f"{kind}, {count} episodes, by {where}; min-Q of the action, mean per step"
    extra = [c for c in profile.values if c not in COLUMNS]  # live, target (--targets)
    lag = ["target-live"] if {"live", "target"} <= set(extra) else []
    cols = ["k" if profile.from_end else "t", "n", "reward", *COLUMNS, "rec-rand", "mean-rec", *extra, *lag]
    lines = [head, "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for i, step in enumerate(profile.steps):
        if not profile.counts[i]:
            continue
        v = {c: profile.values[c][i] for c in profile.values}
        cells = [str(step), str(profile.counts[i]), f"{profile.rewards[i]:.2f}", *(f"{v[c]:.3f}" for c in COLUMNS),
                 f"{v['recorded'] - v['random']:+.3f}", f"{v['policy_mean'] - v['recorded']:+.3f}",
                 *(f"{v[c]:.3f}" for c in extra), *(f"{v['target'] - v['live']:+.3f}" for _ in lag)]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _num(x: float) -> float | None:
    """A JSON number (NaN, an empty mean, becomes null)."""
    return None if math.isnan(x) else round(float(x), 6)


def _jsonable(profile: StepProfile) -> dict[str, Any]:
    return {"steps": list(profile.steps), "counts": profile.counts.tolist(),
            "reward": [_num(x) for x in profile.rewards],
            **{c: [_num(x) for x in v] for c, v in profile.values.items()}}  # fmt: skip


def run(cfg: CriticBenchConfig) -> dict:
    assert cfg.run is not None
    algo = _algorithm(cfg.run)
    inputs = _sim_inputs(cfg, algo) if cfg.handover or cfg.behaviour or cfg.climb else None
    start = _climb_actor(cfg.climb_actor, algo) if cfg.climb_actor is not None else None
    try:
        path, learner, replay_state, _ = checkpoint.load_newest(cfg.run / "learner" / "checkpoints")
    except checkpoint.CheckpointError as exc:
        refuse(PROG, str(exc))
    torch.set_num_threads(cfg.threads)
    agent = algo.build(0, torch.device("cpu"))
    try:
        agent.load_state_dict(learner["sac"])
        replay = SequenceReplay.from_state_dict(replay_state)
    except (KeyError, RuntimeError, ValueError) as exc:
        refuse(PROG, f"{path}: does not load into the learner its run describes ({type(exc).__name__})")
    out: dict[str, Any] = {"run": str(cfg.run), "checkpoint": path.name, "updates": agent.updates,
                           "alpha": float(agent.alpha), "kinds": {}}  # fmt: skip
    fitted = {"live": agent.critic, "targets": agent.td_targets} if cfg.targets else {}
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)  # the targets' sampled next actions: the same checkpoint, the same table
        _profile_kinds(cfg, agent, replay, fitted, out)
    if inputs is not None and cfg.handover:
        out["handover"] = _handover(cfg, algo, agent, replay, inputs)
    if inputs is not None and cfg.behaviour:
        out["behaviour"] = _behaviour(cfg, algo, agent, inputs)
    if inputs is not None and cfg.climb:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)  # the policy's sampling noise in the climb: the same run, the same table
            out["climb"] = _climb(cfg, algo, agent, replay, inputs, start)
    if cfg.json:
        json.dump(out, sys.stdout)
        print()
    else:
        live = "; live: the critic itself, target: its TD target" if cfg.targets else ""
        print(
            f"{path.name}: {agent.updates:,} updates, alpha {float(agent.alpha):.3g} (the target critic rates{live})"
        )
    return out


def _profile_kinds(
    cfg: CriticBenchConfig, agent, replay: SequenceReplay, fitted: dict[str, Any], out: dict[str, Any]
) -> None:
    """Each kind's profiles into ``out["kinds"]`` (and printed, without ``--json``)."""
    for kind, where in KINDS.items():
        slots = replay.slots(**where)
        slots = slots[: cfg.episodes] if kind == "demos" else slots[-cfg.episodes :]
        if not slots.size:
            out["kinds"][kind] = {"episodes": 0}
            continue
        batches = [to_batch(replay.gather(slots[i : i + cfg.batch])) for i in range(0, slots.size, cfg.batch)]
        profiles = [step_profile(agent.actor, agent.critic_target, batches, steps=cfg.steps, from_end=end,
                                 random_actions=cfg.random_actions, **fitted) for end in (True, False)]  # fmt: skip
        out["kinds"][kind] = {"episodes": int(slots.size), "from_end": _jsonable(profiles[0]),
                              "from_start": _jsonable(profiles[1])}  # fmt: skip
        if not cfg.json:
            for p in profiles:
                print(_table(kind, int(slots.size), p) + "\n")


@dataclass(frozen=True)
class _SimInputs:
    demos: list[RecordedDemo]
    task: str
    settings: EnvSettings


def _sim_inputs(cfg: CriticBenchConfig, algo: SacConfig) -> _SimInputs:
    """What ``--handover`` and ``--behaviour`` play, checked before anything is printed (refused in one
    line); the demonstrations only for ``--handover``."""
    assert cfg.run is not None
    # deferred: pybullet and the tasks, needed only for the plays in the simulator
    from mea_tools.bench.handover import recorded_demos
    from services.play import run_env_settings, run_setting
    from services.tasks import TASK_CLASSES

    demos = recorded_demos(cfg.run, cfg.handover) if cfg.handover else []
    if cfg.handover and not demos:
        refuse(
            PROG, f"{cfg.run}: no recorded demonstrations under {cfg.run}/episodes (--handover needs them)"
        )
    task = run_setting(cfg.run, "task", "")
    if task not in TASK_CLASSES:
        refuse(PROG, f"{cfg.run}/config.json: names no task this project has ({task!r})")
    try:
        settings = run_env_settings(cfg.run, algo.observation)
    except ValueError as exc:
        refuse(PROG, str(exc))
    return _SimInputs(demos, task, settings)


@contextlib.contextmanager
def _policy_in_simulator(algo: SacConfig, agent, inputs: _SimInputs) -> Iterator[tuple[Any, Any, Callable]]:
    """(env, runtime, observe): a simulator of the run's task, closed on exit, and the checkpoint's
    policy acting by its mean action on what ``observe`` makes of an observation."""
    from services.algorithms.sac.policy import ActorRuntime, PolicySpec
    from services.episodes.rollout import policy_input
    from services.tasks import make_env

    runtime = ActorRuntime.of(agent.actor, PolicySpec(algo.net, algo.observation))
    observe = functools.partial(policy_input, observation=algo.observation)
    env = make_env(inputs.task, inputs.settings)
    try:
        yield env, runtime, observe
    finally:
        env.close()


def _summary_json(summary: dict[str, float | int]) -> dict[str, float | int | None]:
    return {k: v if isinstance(v, int) else _num(v) for k, v in summary.items()}


def _handover(
    cfg: CriticBenchConfig, algo: SacConfig, agent, replay: SequenceReplay, inputs: _SimInputs
) -> dict[str, Any]:
    """The handover plays beside the critic's Q of the policy's mean on the same demonstrations."""
    from mea_tools.bench.handover import handover_table, move_rows, move_table, play_handover, summarize

    demos = inputs.demos
    # the critic's side: the same original episodes as they sit in the replay (an evicted one is not)
    slot_of = dict(zip(replay.episode_ids(), replay.slots().tolist(), strict=True))
    slots = np.array([slot_of[d.episode_id] for d in demos if d.episode_id in slot_of], dtype=np.int64)
    critic: dict[int, float] = {}
    moves_critic: dict[str, dict[int, float]] = {}
    if slots.size:
        batches = [to_batch(replay.gather(slots[i : i + cfg.batch])) for i in range(0, slots.size, cfg.batch)]
        prof = step_profile(agent.actor, agent.critic_target, batches, steps=max(cfg.handover_steps),
                            from_end=True, random_actions=1)  # fmt: skip
        critic = {k: float(v) for k, v in zip(prof.steps, prof.values["policy_mean"], strict=True)}
        moves_critic = {col: dict(zip(prof.steps, prof.values[col].tolist(), strict=True))
                        for col in ("recorded", "reversed")}  # fmt: skip
    with _policy_in_simulator(algo, agent, inputs) as (env, runtime, observe):
        replays = [play_handover(env, runtime, observe, d, 0) for d in demos]
        plays = {k: [play_handover(env, runtime, observe, d, k) for d in demos] for k in cfg.handover_steps}
        moves = _move_plays(cfg.handover_steps, demos, env, runtime, observe) if cfg.handover_moves else None
    reproduced = sum(p.success and p.policy_steps == 0 for p in replays)
    summaries = {k: summarize(plays[k], algo.sac.gamma) for k in cfg.handover_steps}
    note = f"{reproduced} of {len(demos)} demonstrations reproduced their success when replayed whole"
    if slots.size < len(demos):
        note += f"; the critic's column covers the {slots.size} still in the replay"
    if not cfg.json:
        print(handover_table(cfg.handover_steps, summaries, critic, note) + "\n")
    plays_json = {str(k): _summary_json(summaries[k]) for k in cfg.handover_steps}
    out = {"demos": len(demos), "in_replay": int(slots.size), "reproduced": reproduced,
           "steps": list(cfg.handover_steps), "plays": plays_json,
           "critic_policy_mean": [_num(critic.get(k, math.nan)) for k in cfg.handover_steps]}  # fmt: skip
    if moves is not None:
        rows = move_rows(cfg.handover_steps, moves, moves_critic, algo.sac.gamma)
        if not cfg.json:
            print(move_table(rows) + "\n")
        out["moves"] = [{key: _num(v) if isinstance(v, float) else v for key, v in r.items()} for r in rows]
    return out


def _move_plays(
    backs: Sequence[int], demos: Sequence[RecordedDemo], env, runtime, observe: Callable
) -> dict[str, dict[int, list[Handover]]]:
    """Per column (``recorded``, ``reversed``) and k, the plays that execute the demo's own action k
    steps before its end, or that move reversed, then the policy (demos shorter than k left out)."""
    from mea_tools.bench.handover import play_handover

    out: dict[str, dict[int, list[Handover]]] = {"recorded": {}, "reversed": {}}
    for k in backs:
        long_enough = [d for d in demos if len(d.actions) >= k]
        for col in out:
            out[col][k] = []
            for d in long_enough:
                a = d.actions[len(d.actions) - k]
                first = a if col == "recorded" else reversed_move(torch.tensor(a)).numpy()
                out[col][k].append(play_handover(env, runtime, observe, d, k, first=first))
    return out


def _behaviour(cfg: CriticBenchConfig, algo: SacConfig, agent, inputs: _SimInputs) -> dict[str, Any]:
    """The policy's mean action from the evaluator's first ``cfg.behaviour`` held-out starts, summed up."""
    from mea_tools.bench.behaviour import behaviour_table, object_labels, play_behaviour, summarize_behaviour
    from proto.seeds import EVAL_SEED_BASE

    with _policy_in_simulator(algo, agent, inputs) as (env, runtime, observe):
        labels = object_labels(env)
        plays = [play_behaviour(env, runtime, observe, EVAL_SEED_BASE + i) for i in range(cfg.behaviour)]
    summary = summarize_behaviour(plays, labels)
    if not cfg.json:
        print(behaviour_table(summary, labels) + "\n")
    return _summary_json(summary)


def _climb_actor(path: Path, algo: SacConfig) -> dict[str, torch.Tensor]:
    """The actor state ``--climb-actor`` names, fitted to the run's actor as the learner's
    ``--init-actor`` is; refused in one line."""
    from services.learner import init_actor

    try:
        return init_actor.check_fits(init_actor.read(path)[1], algo)
    except (OSError, ValueError) as exc:
        refuse(PROG, f"--climb-actor {path}: {exc}")


def _climb(
    cfg: CriticBenchConfig, algo: SacConfig, agent, replay: SequenceReplay, inputs: _SimInputs,
    start: dict[str, torch.Tensor] | None,
) -> list[dict[str, Any]]:  # fmt: skip
    """The actor stepped on the frozen target critic (``climb``), batches drawn as the run's learner
    draws them, played by its mean action from the first ``--climb-episodes`` held-out starts at
    every point."""
    from mea_tools.bench.behaviour import play_behaviour
    from proto.seeds import EVAL_SEED_BASE
    from services.algorithms.sac.climb import climb

    if start is not None:
        agent.actor.load_state_dict(start)
    draw = _learner_batches(cfg.run)
    rng = np.random.default_rng(0)
    batches = (to_batch(replay.sample(draw["batch_size"], rng, demo_fraction=draw["demo_fraction"],
                                      successes_as_demos=draw["successes_as_demos"], trim=True))
               for _ in itertools.count())  # fmt: skip
    demos = replay.slots(demo=True)
    kind = "demonstrations" if demos.size else "latest episodes"  # a run without demonstrations
    probe = to_batch(replay.gather(demos[: cfg.batch] if demos.size else replay.slots()[-cfg.batch :]))
    rows: list[dict[str, Any]] = []
    with _policy_in_simulator(algo, agent, inputs) as (env, runtime, observe):
        steps = climb(agent.actor, agent.critic_target, batches, cfg.climb, cfg.climb_every, algo.sac.actor_rate,
                      float(agent.alpha), probe)  # fmt: skip
        for point in steps:
            plays = [
                play_behaviour(env, runtime, observe, EVAL_SEED_BASE + i) for i in range(cfg.climb_episodes)
            ]
            rows.append({"updates": point.updates, "success": sum(p.success for p in plays) / len(plays),
                         "q_sample": _num(point.q_sample), "q_mean": _num(point.q_mean),
                         "q_recorded": _num(point.q_recorded)})  # fmt: skip
    if not cfg.json:
        head = (f"the actor climbing the frozen target critic (Adam at {algo.sac.actor_rate:g}, alpha "
                f"{float(agent.alpha):.3g}); success of its mean action on {cfg.climb_episodes} held-out "
                f"starts; min-Q on {probe.actions.shape[0]} {kind}")  # fmt: skip
        cols = ["updates", "success", "q_sample", "q_mean", "q_recorded"]
        lines = [head, "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        lines += ["| " + " | ".join(f"{r[c]:.3f}" if isinstance(r[c], float) else str(r[c]) for c in cols) + " |"
                  for r in rows]  # fmt: skip
        print("\n".join(lines) + "\n")
    return rows


def _learner_batches(run: Path) -> dict[str, Any]:
    """How the run's learner draws its batches (RUN_DIR/learner/learner.json, read by ``_algorithm``)."""
    d = json.loads((run / "learner" / "learner.json").read_text())
    return {"batch_size": int(d["batch_size"]), "demo_fraction": float(d.get("demo_fraction", 0.0)),
            "successes_as_demos": bool(d.get("successes_as_demos", False))}  # fmt: skip


__all__ = ["CriticBenchConfig", "run"]
