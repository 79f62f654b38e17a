"""What `mea robot` needs from an arm: the adapter contract, and the simulated arm that implements it.

Design notes: docs/architecture-notes.md, services/inference/adapter.py."""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from proto.actions import ACTION_DIM, DELTA_THETA, DELTA_XYZ, JAW
from services.episodes.rollout import policy_input
from services.inference.core.envelope import Limits
from services.tasks import ManipulationEnv, make_env
from services.tasks.env import Observation


@dataclass(frozen=True)
class RobotObservation:
    """One observation as the inference server takes it (``proto.inference.ActRequest``)."""

    state: np.ndarray
    """float32 (5,): pivot x, y, z (m, base frame), yaw (rad), jaw opening 0..1."""
    stamp: float
    """UNIX time (s) it was taken."""
    points: np.ndarray | None = None
    point_counts: np.ndarray | None = None
    image: np.ndarray | None = None


@dataclass(frozen=True)
class StepOutcome:
    """What one executed command did (the simulator's reward and flags; a real arm reports zeros)."""

    observation: RobotObservation
    executed: np.ndarray
    reward: float = 0.0
    terminated: bool = False
    truncated: bool = False


class RobotAdapter(Protocol):
    task: str
    max_steps: int

    def reset(self, seed: int, observation: str) -> RobotObservation: ...

    def execute(self, action: np.ndarray) -> StepOutcome: ...

    def hold(self, reason: str) -> None: ...

    def close(self) -> None: ...


def observation_of(obs: Observation, observation: str, stamp: float) -> RobotObservation:
    """The request-side observation of a task env's observation, in the form ``observation`` needs:
    points for ``voxel`` (the server projects them), the image for ``depth`` and ``dsa``."""
    state = np.append(np.asarray(obs.gripper_pose, np.float32), np.float32(obs.jaw)).astype(np.float32)
    if observation == "voxel":
        return RobotObservation(state, stamp, np.asarray(obs.points, np.float32),
                                np.asarray(obs.point_counts, np.int32))  # fmt: skip
    return RobotObservation(state, stamp, image=np.ascontiguousarray(policy_input(obs, observation)))


def action_scale(env: ManipulationEnv) -> tuple[float, float]:
    """(metres, radians) one action unit moves in ``env`` (the surgical task's are its own)."""
    actions = getattr(getattr(env, "settings", None), "actions", None)
    if actions is not None and hasattr(actions, "step_translation"):
        return float(actions.step_translation), float(actions.step_rotation)
    return DELTA_XYZ, DELTA_THETA


def sim_limits(env: ManipulationEnv) -> Limits:
    """The envelope of a simulated arm: one full step per command, and the box the env keeps the
    commanded pivot in widened by two steps, so the envelope never binds where the env's own limits
    act (its episodes stay those the evaluator runs) but still stops anything beyond."""
    per_unit, per_turn = action_scale(env)
    bounds = getattr(env, "pivot_bounds", None) or env.robot.pivot_bounds
    low, high = (np.asarray(b, np.float64) for b in bounds())
    margin = 2.0 * per_unit
    return Limits(metres_per_unit=per_unit, radians_per_unit=per_turn,
                  max_translation=per_unit * math.sqrt(3.0) * (1 + 1e-6), max_rotation=per_turn * (1 + 1e-6),
                  workspace_low=tuple(float(x) for x in low - margin),
                  workspace_high=tuple(float(x) for x in high + margin),
                  observation_margin=margin)  # fmt: skip


class SimRobot:
    """A pybullet task as the arm. ``hold`` (any thread) makes the next command a hold: the sim moves
    only when stepped, so holding is stepping with no motion and the jaw kept."""

    def __init__(self, task: str, settings=None, env: ManipulationEnv | None = None) -> None:
        self.task = task
        self.env = env or make_env(task, settings)
        self.max_steps = int(self.env.settings.max_steps)
        self._observation = "voxel"
        self._jaw = 1.0
        self._lock = threading.Lock()
        self.holds: list[str] = []
        self._hold_next = False

    def reset(self, seed: int, observation: str) -> RobotObservation:
        self._observation, self._jaw = observation, 1.0
        with self._lock:
            self._hold_next = False
        return observation_of(self.env.reset(seed), observation, time.time())

    def hold(self, reason: str) -> None:
        with self._lock:
            self.holds.append(reason)
            self._hold_next = True

    def execute(self, action: np.ndarray) -> StepOutcome:
        a = np.asarray(action, np.float32).copy()
        with self._lock:
            if self._hold_next:
                a[:] = 0.0
                a[JAW] = self._jaw
                self._hold_next = False
        obs, reward, terminated, truncated, info = self.env.step(a)
        executed = np.asarray(info.get("executed_action", a), np.float32).reshape(ACTION_DIM)
        self._jaw = 1.0 if executed[JAW] >= 0 else -1.0
        return StepOutcome(observation_of(obs, self._observation, time.time()), executed, float(reward),
                           bool(terminated), bool(truncated))  # fmt: skip

    def close(self) -> None:
        self.env.close()
