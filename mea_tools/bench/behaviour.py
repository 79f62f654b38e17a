"""Behaviour: what a run's policy does from the evaluator's held-out starts, read from the simulator's
privileged state (`mea bench critic --behaviour N`).

A success rate says that a policy fails, not how. Played by its mean action, the episode is summed
up by what the fingers and the objects did: when the fingers first came low among the objects,
which object the arm came to first (the first listed on a tie) and for how many steps it was at
each, how far each object moved, and how the distance between the two objects changed (Block Pull
succeeds when it closes). The policy reads only its observation; the privileged state is read by
this summary alone."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

NEAR_BAND = 0.02
"""The arm within this distance (m) of an object is at it. Not contact: a pushed object slides on
while the env rests after each step, so a push leaves a gap of a centimetre or so."""
GAP_BAND = 0.01
"""The objects' distance counts as closed (opened) when it ended this much (m) below (above) its start."""


@dataclass(frozen=True)
class Behaviour:
    """One episode of the policy's mean action from ``seed``."""

    seed: int
    success: bool
    steps: int
    low_at: int | None
    """First step (1-based) after which the fingers were low: their lowest point below the objects'
    mean centre height, where moving sideways meets an object (None: never)."""
    first_near: int | None
    """The object (index into ``object_labels``) the arm came to first (None: none)."""
    near: tuple[int, ...]
    """Steps after which the arm was at each object (within ``NEAR_BAND``), in ``object_labels`` order."""
    moved: tuple[float, ...]
    """Each object's horizontal displacement over the episode (m), in ``object_labels`` order."""
    gap: tuple[float, float]
    """Horizontal distance between the first two objects' centres at the start and at the end (m)."""


def object_labels(env) -> tuple[str, ...]:
    """Names of the objects as ``Behaviour`` lists them: ``immovable`` then ``movable`` where the task
    has one immovable object (Block Pull, Block Pick, Drawer Open), else the task's object names."""
    return tuple(_labelled(env)[0])


def _labelled(env) -> tuple[tuple[str, ...], list[int]]:
    """The labels and, in the current episode, the object slot of each (which slot holds the
    immovable object is drawn at every reset)."""
    names = tuple(env.task.object_names)
    try:
        fixed = int(env.task.fixed_index())
    except (AttributeError, ValueError):
        fixed = None
    if fixed is None or len(names) != 2:
        return names, list(range(len(names)))
    return ("immovable", "movable"), [fixed, 1 - fixed]


def _poses(env) -> np.ndarray:
    return np.asarray(env.task.object_poses(), float)[:, :3]


def at_objects(env) -> np.ndarray:
    """Per object slot (``object_names`` order), whether any part of the arm is within ``NEAR_BAND`` of it."""
    import pybullet as pb  # deferred: the summary functions below need no simulator

    arm, c = env.robot.body, env.client
    return np.array([
        any(pb.getClosestPoints(arm, body, NEAR_BAND, physicsClientId=c) for body, _ in parts)
        for parts in env.task.object_segments().values()
    ])  # fmt: skip


def play_behaviour(env, runtime, observe: Callable, seed: int) -> Behaviour:
    """Reset ``env`` to ``seed`` and ``runtime`` afresh, act with the runtime until the episode ends,
    and sum up the privileged state after every step."""
    obs = env.reset(seed)
    runtime.reset()
    slots = _labelled(env)[1]  # label order, this episode
    start = _poses(env)[slots]
    low = float(start[:, 2].mean())
    near = np.zeros(len(start), np.int64)
    low_at = first_near = None
    terminated, steps = False, 0
    while steps < env.settings.max_steps:
        obs, _reward, terminated, truncated, _info = env.step(runtime.act(observe(obs)))
        steps += 1
        at = at_objects(env)[slots]
        if first_near is None and at.any():
            first_near = int(np.flatnonzero(at)[0])
        near += at
        if low_at is None and env.robot.lowest_point() < low:
            low_at = steps
        if terminated or truncated:
            break
    start, end = start[:, :2], _poses(env)[slots, :2]
    gap = (float(np.linalg.norm(start[0] - start[1])), float(np.linalg.norm(end[0] - end[1])))
    moved = tuple(float(d) for d in np.linalg.norm(end - start, axis=1))
    return Behaviour(
        seed, bool(terminated), steps, low_at, first_near, tuple(int(k) for k in near), moved, gap
    )


def summarize_behaviour(plays: Sequence[Behaviour], labels: Sequence[str]) -> dict[str, float | int]:
    """Shares over the episodes (of all; ``low_by_5``: fingers low within the first five steps), the
    mean first step low among those that came low, per object the share the arm came to (and came
    to first) and the mean displacement, and the mean distance between the objects at start and end."""
    n = len(plays)
    if not n:
        return {"episodes": 0}
    low = [p.low_at for p in plays if p.low_at is not None]
    out: dict[str, float | int] = {
        "episodes": n,
        "success": sum(p.success for p in plays) / n,
        "low": len(low) / n,
        "low_by_5": sum(t <= 5 for t in low) / n,
        "mean_low_at": float(np.mean(low)) if low else float("nan"),
        "gap_start": float(np.mean([p.gap[0] for p in plays])),
        "gap_end": float(np.mean([p.gap[1] for p in plays])),
        "gap_closed": sum(p.gap[1] < p.gap[0] - GAP_BAND for p in plays) / n,
        "gap_opened": sum(p.gap[1] > p.gap[0] + GAP_BAND for p in plays) / n,
    }
    for i, label in enumerate(labels):
        out[f"near_{label}"] = sum(p.near[i] > 0 for p in plays) / n
        out[f"first_{label}"] = sum(p.first_near == i for p in plays) / n
        out[f"moved_{label}"] = float(np.mean([p.moved[i] for p in plays]))
    return out


def behaviour_table(summary: dict[str, float | int], labels: Sequence[str]) -> str:
    s = summary
    lines = [
        f"behaviour: the policy's mean action from {s['episodes']} held-out starts, read from the simulator's "
        "privileged state (fingers low: below the objects' centres; at an object: the arm within "
        f"{100 * NEAR_BAND:g} cm of it; moved and distances in cm)",
        "| success | fingers low | low within 5 steps | first step low | objects' distance start -> end "
        f"| closed by > {100 * GAP_BAND:g} cm | opened by > {100 * GAP_BAND:g} cm |",
        "|---|---|---|---|---|---|---|",
        f"| {s['success']:.2f} | {s['low']:.2f} | {s['low_by_5']:.2f} | {s['mean_low_at']:.1f} | "
        f"{100 * s['gap_start']:.1f} -> {100 * s['gap_end']:.1f} | {s['gap_closed']:.2f} | {s['gap_opened']:.2f} |",
        "",
        "| object | arm at it | at it first | moved |",
        "|---|---|---|---|",
    ]
    for label in labels:
        lines.append(f"| {label} | {s[f'near_{label}']:.2f} | {s[f'first_{label}']:.2f} | "
                     f"{100 * s[f'moved_{label}']:.1f} |")  # fmt: skip
    return "\n".join(lines)


__all__ = [
    "GAP_BAND",
    "NEAR_BAND",
    "Behaviour",
    "behaviour_table",
    "object_labels",
    "play_behaviour",
    "at_objects",
    "summarize_behaviour",
]
