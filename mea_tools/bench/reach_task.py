"""A sparse-reward 2D reach whose right answer is known: the task `mea bench reach` trains recurrent
SAC on, with nothing of Block Pull's simulator, observation or demonstrations in the way.

A point in [-1, 1]^2 moves by ``STEP`` (dx, dy) per step (the action's other three entries do nothing,
as the jaw and dθ mostly do in Block Pull). The goal is drawn at least ``MIN_START_DISTANCE`` away;
reward 1 and the end of the episode within ``RADIUS`` of it, else 0; ``MAX_STEPS`` steps. The policy
sees the state (the four coordinates as a 1 x 1 image of four channels), an N x N image of the world
with the point and the goal marked (channel 0 and 1; rows +x, columns +y), or a ``centred`` image of
2N - 1 pixels with the point at its centre and the goal at its offset from it, as a gripper-centred
observation shows the blocks. A quarter turn of the world turns either image exactly as
``groups.transform_images`` does, so the task is C4-equivariant.

Pure numpy: no simulator, no services."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from proto.actions import ACTION_DIM

STEP = 0.2
"""Distance moved per unit of dx and dy."""
RADIUS = 0.2
"""Success radius around the goal."""
MIN_START_DISTANCE = 1.0
"""The goal is drawn at least this far from the start."""
MAX_STEPS = 50
"""Steps before the time limit (Block Pull's)."""
OBSERVATIONS = ("state", "image", "centred")
CODE_MAX = 255


@dataclass(frozen=True)
class ReachState:
    point: np.ndarray
    """(2,) float64 position."""
    goal: np.ndarray
    """(2,) float64 goal."""


def draw_start(rng: np.random.Generator) -> ReachState:
    """A start and a goal in [-1, 1]^2 at least ``MIN_START_DISTANCE`` apart (rejection sampling)."""
    while True:
        p, g = rng.uniform(-1.0, 1.0, 2), rng.uniform(-1.0, 1.0, 2)
        if np.linalg.norm(p - g) >= MIN_START_DISTANCE:
            return ReachState(p, g)


def step(s: ReachState, action: np.ndarray) -> tuple[ReachState, float, bool]:
    """(next state, reward, reached). (dx, dy) = action[1:3] (``proto.actions``' layout), clipped to
    [-1, 1]; the point stays in the box."""
    d = np.clip(np.asarray(action, np.float64)[1:3], -1.0, 1.0)
    p = np.clip(s.point + STEP * d, -1.0, 1.0)
    reached = bool(np.linalg.norm(p - s.goal) < RADIUS)
    return ReachState(p, s.goal), float(reached), reached


def expert_action(s: ReachState) -> np.ndarray:
    """A straight line to the goal: (dx, dy) along it, each within [-1, 1]; the rest zero."""
    a = np.zeros(ACTION_DIM, np.float32)
    d = (s.goal - s.point) / STEP
    a[1:3] = d / max(1.0, float(np.abs(d).max()))
    return a


def _code(v: np.ndarray) -> np.ndarray:
    return np.rint((np.asarray(v) + 1.0) * 0.5 * CODE_MAX).astype(np.uint8)


def pixel(v: np.ndarray, size: int) -> tuple[int, int]:
    """(row, column) of a position: rows follow +x, columns +y; the centre pixel is the origin."""
    i = np.rint((np.clip(v, -1.0, 1.0) + 1.0) * 0.5 * (size - 1)).astype(int)
    return int(i[0]), int(i[1])


def check_image_size(size: int) -> None:
    """ValueError unless the world image's ``size`` is odd and >= 3 (a centre pixel at the origin)."""
    if size < 3 or size % 2 == 0:
        raise ValueError(f"the image size must be odd and >= 3 (a centre pixel at the origin), not {size}")


def image_side(observation: str, size: int) -> int:
    """H = W of an observation's image for the world image's ``size``."""
    return 1 if observation == "state" else 2 * size - 1 if observation == "centred" else size


def observe(s: ReachState, observation: str, size: int, t: int = 0, goal_steps: int = 0) -> np.ndarray:
    """uint8 codes (C, H, W) of the observation at step ``t``: ``state`` (4, 1, 1) the coordinates in
    [-1, 1] as 0..255; ``image`` (2, size, size) with the point's pixel in channel 0 and the goal's in
    channel 1; ``centred`` (2, 2 size - 1, 2 size - 1), the same at the same scale, shifted to put the
    point at the centre.

    ``goal_steps`` K > 0 shows the goal in the first K observations only, so that a policy must
    remember it: the images then lack its mark, and the state gains a fifth channel saying whether it
    is shown (its coordinates read 0 when not)."""
    if observation not in OBSERVATIONS:
        raise ValueError(f"observation must be one of {OBSERVATIONS}, not {observation!r}")
    shown = goal_steps == 0 or t < goal_steps
    if observation == "state":
        goal = s.goal if shown else np.zeros(2)
        flag = [1.0 if shown else -1.0] if goal_steps else []
        codes = _code(np.concatenate([s.point, goal, flag]))
        return codes.reshape(-1, 1, 1)
    check_image_size(size)
    n = image_side(observation, size)
    img = np.zeros((2, n, n), np.uint8)
    if observation == "image":
        img[(0, *pixel(s.point, size))] = CODE_MAX
        if shown:
            img[(1, *pixel(s.goal, size))] = CODE_MAX
    else:  # twice the world's span, so every offset of the goal fits
        img[(0, *pixel(np.zeros(2), n))] = CODE_MAX
        if shown:
            img[(1, *pixel(0.5 * (s.goal - s.point), n))] = CODE_MAX
    return img


def channels(observation: str, goal_steps: int = 0) -> int:
    """Channels of ``observe``'s codes."""
    return (5 if goal_steps else 4) if observation == "state" else 2
