"""Measure the deterministic-transition prior MEA relies on (paper Sec. IV-D, third prior).

Without contact an action moves the observed points by a known amount in the gripper-centric frame;
this measures how far the simulator is from that (translation, rotation and Chamfer residuals).

Design notes: docs/architecture-notes.md, services/tasks/prior.py."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from proto.actions import DELTA_THETA, DELTA_XYZ
from services.geometry import rotate_z
from services.tasks.env import ManipulationEnv


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric mean nearest-neighbour distance between two clouds (m)."""
    if len(a) == 0 or len(b) == 0:
        return math.inf
    d = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1))
    return float((d.min(axis=1).mean() + d.min(axis=0).mean()) / 2)


def best_fit_yaw(
    before: np.ndarray,
    after: np.ndarray,
    guess: float,
    span_deg: float = 4.0,
    step_deg: float = 0.1,
    max_points: int = 400,
) -> float:
    """Yaw (rad) near ``guess`` that best maps ``before`` onto ``after`` (Chamfer grid search)."""
    rng = np.random.default_rng(0)
    if len(before) > max_points:
        before = before[rng.choice(len(before), max_points, replace=False)]
    if len(after) > max_points:
        after = after[rng.choice(len(after), max_points, replace=False)]
    offsets = np.radians(np.arange(-span_deg, span_deg + 1e-9, step_deg))
    scores = [chamfer(rotate_z(before, guess + o), after) for o in offsets]
    return guess + float(offsets[int(np.argmin(scores))])


@dataclass
class PriorSample:
    translation_error_m: float
    rotation_error_rad: float
    chamfer_m: float


def measure(env: ManipulationEnv, seed: int, steps: int, rng: np.random.Generator) -> list[PriorSample]:
    """Random free-space actions (no contact, no clipping) from a reset; one sample per step."""
    env.reset(seed)
    # start high so random moves stay clear of the objects
    lo, hi = env.robot.pivot_bounds()
    samples = []
    world, origin = env.segment_clouds(), env.robot.pivot()[0]
    for _ in range(steps):
        a = rng.uniform(-1, 1, 5)
        a[0] = 1.0  # jaw held open: the jaw does not change the gripper's shape between steps
        target = env.robot.target_pos + a[1:4] * DELTA_XYZ
        target_yaw = env.robot.target_yaw + a[4] * DELTA_THETA
        # keep the move inside the box, above the objects and away from the yaw stop
        if np.any(target < lo) or np.any(target > hi) or target[2] < lo[2] + 0.08 or abs(target_yaw) > 2.5:
            a[1:5] = -a[1:5]
        env.step(a)
        new = env.segment_clouds()
        if env.contacts().any():
            world, origin = new, env.robot.pivot()[0]
            continue
        o0, o1 = origin, env.robot.pivot()[0]
        t_err, ch = [], []
        for name in env.task.object_names:
            if len(world[name]) == 0 or len(new[name]) == 0:
                continue
            before, after = world[name] - o0, new[name] - o1
            predicted = before - a[1:4] * DELTA_XYZ
            t_err.append(np.linalg.norm(after.mean(0) - predicted.mean(0)))
            ch.append(chamfer(predicted, after))
        yaw = best_fit_yaw(world["gripper"] - o0, new["gripper"] - o1, a[4] * DELTA_THETA)
        samples.append(PriorSample(float(np.mean(t_err)), abs(yaw - a[4] * DELTA_THETA), float(np.mean(ch))))
        world, origin = new, o1
    return samples


def summarise(samples: list[PriorSample]) -> dict[str, float]:
    t = np.array([s.translation_error_m for s in samples]) * 1000
    r = np.degrees([s.rotation_error_rad for s in samples])
    c = np.array([s.chamfer_m for s in samples]) * 1000
    return {
        "samples": len(samples),
        "translation_error_mm_mean": float(t.mean()),
        "translation_error_mm_max": float(t.max()),
        "rotation_error_deg_mean": float(r.mean()),
        "rotation_error_deg_max": float(r.max()),
        "object_chamfer_mm_mean": float(c.mean()),
        "object_chamfer_mm_max": float(c.max()),
    }
