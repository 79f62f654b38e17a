"""Handover: a run's own demonstrations played again in the simulator up to k steps before their end,
then finished by the policy's mean action (`mea bench critic --handover`).

The critic's value of the policy's action on a demonstration's state is a claim about what the
policy does from there. Playing the policy from exactly that state checks the claim: a critic that
rates the policy's action near a demonstration's while the policy never finishes from there
overestimates on states the policy itself never visits (its own episodes start elsewhere)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.common.mcap_io.segments import read_recording

EPISODES = "episodes"
"""RUN_DIR/episodes: the run's recorded raw episodes (the actors' own, before augmentation)."""


@dataclass(frozen=True)
class RecordedDemo:
    episode_id: str
    seed: int
    actions: np.ndarray  # (T, action_dim)


@dataclass(frozen=True)
class Handover:
    """One play: the demo's first ``replayed`` actions, then the policy (``policy_steps`` of them)."""

    seed: int
    replayed: int
    success: bool
    policy_steps: int


def recorded_demos(run: Path, limit: int) -> list[RecordedDemo]:
    """The first ``limit`` demonstrations among the run's recorded raw episodes (segments oldest
    first, a segment still being written included), each once. Unreadable records are skipped
    (counted and logged by the reader)."""
    found: dict[str, RecordedDemo] = {}
    if not (run / EPISODES).is_dir():  # a run that records nothing: no demos, not a warning
        return []
    for _topic, msg in read_recording(run / EPISODES, types={"Episode"}, on_error="skip"):
        if getattr(msg, "is_demo", False) and msg.episode_id not in found:
            actions = np.asarray(msg.actions, np.float32)
            found[msg.episode_id] = RecordedDemo(msg.episode_id, int(msg.seed), actions)
            if len(found) >= limit:  # stop before decoding another episode
                break
    return list(found.values())


def play_handover(
    env, runtime, observe: Callable, demo: RecordedDemo, back: int, first: np.ndarray | None = None
) -> Handover:
    """Reset ``env`` to the demo's seed and ``runtime`` afresh; for the first ``len - back`` steps the
    demo's action is executed (the runtime still reads each observation and is told the executed
    action, so its recurrent state is the one it would have had), then the runtime's own action
    until the episode ends. ``observe(obs)`` gives the runtime's input. ``back`` >= the demo's
    length hands over at the first step; 0 replays the whole demo (a check that the simulator
    reproduces it). ``first``, if given, is executed in place of the runtime's action at the
    handover step and counts as the policy part's first step: the play then measures Q of that
    action under the policy, the quantity the critic's Q(h, first) estimates."""
    replayed = max(0, len(demo.actions) - back)
    obs = env.reset(demo.seed)
    runtime.reset()
    terminated, steps = False, 0
    while steps < env.settings.max_steps:
        action = runtime.act(observe(obs))
        if steps < replayed:
            action = demo.actions[steps]
            runtime.executed(action)
        elif steps == replayed and first is not None:
            action = np.asarray(first, np.float32)
            runtime.executed(action)
        obs, _reward, terminated, truncated, _info = env.step(action)
        steps += 1
        if terminated or truncated:
            break
    return Handover(demo.seed, replayed, bool(terminated), steps - replayed)


def summarize(plays: Iterable[Handover], gamma: float) -> dict[str, float | int]:
    """Successes, mean policy steps to a success and the mean discounted return of the policy's part
    (gamma^(steps - 1) for a success in ``steps`` policy steps with reward 1 at the success, else 0:
    the quantity a critic's Q of the first policy action estimates). A success reached while the
    demo was still being replayed counts with return 1 (the reward the replayed action earns)."""
    plays = list(plays)
    wins = [p.policy_steps for p in plays if p.success]
    returns = [gamma ** max(0, p.policy_steps - 1) if p.success else 0.0 for p in plays]
    return {
        "episodes": len(plays),
        "successes": len(wins),
        "mean_policy_steps": float(np.mean(wins)) if wins else float("nan"),
        "mean_return": float(np.mean(returns)) if returns else float("nan"),
    }


def handover_table(
    backs: Sequence[int], summaries: dict[int, dict], critic: dict[int, float], reproduced: str
) -> str:
    lines = [
        "handover: the run's original demonstrations replayed in the simulator up to k steps before their end, then "
        f"finished by the policy's mean (return = gamma^(steps-1) on a success); {reproduced}",
        "| k | n | success | policy steps | return | critic Q(policy mean) | critic - return |",
        "|---|---|---|---|---|---|---|",
    ]
    for k in backs:
        s, q = summaries[k], critic.get(k, float("nan"))
        lines.append(f"| {k} | {s['episodes']} | {s['successes']}/{s['episodes']} | {s['mean_policy_steps']:.1f} | "
                     f"{s['mean_return']:.3f} | {q:.3f} | {q - s['mean_return']:+.3f} |")  # fmt: skip
    return "\n".join(lines)


def move_rows(
    backs: Sequence[int],
    plays: dict[str, dict[int, list[Handover]]],
    critic: dict[str, dict[int, float]],
    gamma: float,
) -> list[dict[str, float | int]]:
    """Per k, what the demo's own action and the same move reversed are worth when the policy follows
    (``plays[col][k]``, col in ``recorded``/``reversed``) beside the critic's min-Q of each action at
    that step (``critic[col][k]``; NaN where it has none): the critic's slope between a move and its
    reverse against the one the simulator gives under the same policy."""
    rows: list[dict[str, float | int]] = []
    nan = float("nan")
    for k in backs:
        rec, rev = (summarize(plays[col][k], gamma) for col in ("recorded", "reversed"))
        q_rec, q_rev = (critic.get(col, {}).get(k, nan) for col in ("recorded", "reversed"))
        rows.append({
            "k": k, "episodes": rec["episodes"],
            "successes_recorded": rec["successes"], "successes_reversed": rev["successes"],
            "return_recorded": rec["mean_return"], "return_reversed": rev["mean_return"],
            "return_gap": rec["mean_return"] - rev["mean_return"],
            "critic_recorded": q_rec, "critic_reversed": q_rev, "critic_gap": q_rec - q_rev,
        })  # fmt: skip
    return rows


def move_table(rows: Sequence[dict[str, float | int]]) -> str:
    lines = [
        "a demonstrated move and the same move reversed, k steps before the demo's end, then the policy's mean: "
        "return = gamma^(steps-1) on a success (the true Q of the move under this policy) beside the critic's min-Q",
        "| k | n | successes (move / reversed) | return: move | reversed | gap | critic: move | reversed | gap |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['k']} | {r['episodes']} | {r['successes_recorded']} / {r['successes_reversed']} | "
                     f"{r['return_recorded']:.3f} | {r['return_reversed']:.3f} | {r['return_gap']:+.3f} | "
                     f"{r['critic_recorded']:.3f} | {r['critic_reversed']:.3f} | {r['critic_gap']:+.3f} |")  # fmt: skip
    return "\n".join(lines)


__all__ = [
    "Handover",
    "RecordedDemo",
    "handover_table",
    "move_rows",
    "move_table",
    "play_handover",
    "recorded_demos",
    "summarize",
]
