"""Surgical Grasp Any (paper Sec. IV-C, after GASv2): grasp a needle, block or rod with a PSM-like
instrument, hybrid P-control then policy, FSM rewards.

Design notes: docs/architecture-notes.md, services/tasks/surgical/env.py."""

from __future__ import annotations

import numpy as np
import pybullet as pb

from proto.discrete_actions import NAMES, to_vector
from services.observation.dsa import dsa_image, in_cube, voxel_centroid, world_clouds
from services.tasks.camera import _downsample, sample_fixed
from services.tasks.env import EnvSettings, Observation, check_action
from services.tasks.surgical import objects
from services.tasks.surgical.camera import CameraPose, ObliqueCamera, image_noise
from services.tasks.surgical.control import HybridController, centroid_error, fsm_index, fsm_reward
from services.tasks.surgical.oracle import Oracle
from services.tasks.surgical.scene import WORKSPACE, Scene, draw
from services.tasks.surgical.settings import SurgicalCameraSettings, SurgicalSettings

SETTLE_STEPS = 10
"""Physics steps the world rests after a reset."""
RAMP_STEPS = 12
"""Physics steps over which the drive frame travels to its new place each action."""


class SurgicalGraspAny:
    """The task as the registry sees it (``services.tasks.TASK_CLASSES``): names, the oracle, and the
    factory of its own env (it does not run in ManipulationEnv)."""

    name = "surgical_grasp_any"
    object_names = ("object_0",)
    expert_styles = ("direct",)
    """The oracle has one style: straight to the object."""

    @classmethod
    def make_env(cls, settings: SurgicalSettings | EnvSettings | None = None) -> SurgicalGraspEnv:
        return SurgicalGraspEnv(coerce_settings(settings))

    def expert(self, env: SurgicalGraspEnv, style: str, rng: np.random.Generator):
        if style not in self.expert_styles:
            raise ValueError(f"{self.name} has expert styles {self.expert_styles}, not {style!r}")
        return Oracle(env)

    def fixed_index(self) -> int:
        """No immovable object here."""
        return -1


def coerce_settings(settings: SurgicalSettings | EnvSettings | None) -> SurgicalSettings:
    """SurgicalSettings from what a caller of ``make_env`` has: the general EnvSettings (an actor's)
    give their points per segment; the baseline depth image does not exist for this task."""
    if settings is None:
        return SurgicalSettings()
    if isinstance(settings, SurgicalSettings):
        return settings
    if settings.depth_image:
        raise ValueError("surgical_grasp_any has no baseline depth image (depth_image=True)")
    points = settings.camera.points_per_segment
    return SurgicalSettings(camera=SurgicalCameraSettings(points_per_segment=points))


class SurgicalGraspEnv:
    """pybullet DIRECT simulation of Surgical Grasp Any; ``reset(seed)`` then ``step(action)``."""

    segment_names = ("gripper", "object_0")

    def __init__(self, settings: SurgicalSettings | None = None) -> None:
        self.settings = settings = settings or SurgicalSettings()
        self.task = SurgicalGraspAny()
        self.client = pb.connect(pb.DIRECT)
        self.camera = ObliqueCamera(settings.camera)
        self.scene = Scene(self.client, settings, pivot_height=0.0)
        self.scene.pivot_height = self.pivot_height = self._calibrate()
        self.controller = HybridController(settings.controller)
        self.seed, self.t, self.substeps = 0, 0, 0
        self.trials, self.grasped, self.failed = 0, False, False
        self.fsm = "prog_norm"
        self._err: np.ndarray | None = None
        self.camera_pose = CameraPose()
        self.placement = None

    # --- set-up -------------------------------------------------------------------------------
    def _calibrate(self) -> float:
        """Height of the pivot above the closed tips: the gripper's observed point centroid, seen by
        the nominal camera with the jaw open at the workspace centre (a fixed point of the tool)."""
        inst = self.scene.instrument
        tip = np.array([0.0, 0.0, WORKSPACE[2].mean()])
        inst.reset(tip, 0.0, jaw_open=True)  # pivot_height 0: pivot = tip
        z, seg = self.camera.render(self.client)
        pts = self.camera.unproject(seg == inst.body, z)
        return float(pts[:, 2].mean() - tip[2])

    @property
    def instrument(self):
        return self.scene.instrument

    @property
    def centroid_error(self) -> np.ndarray | None:
        """The P-controller's error at the last observation (occupancy units; None: a segment unseen)."""
        return None if self._err is None else self._err.copy()

    @property
    def jaw_open(self) -> bool:
        """The commanded jaw state (what a discrete toggle flips)."""
        return self.instrument.state.jaw_open

    def step_physics(self) -> None:
        pb.stepSimulation(physicsClientId=self.client)
        self.substeps += 1

    def _rng(self, stream: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.t, stream])

    # --- POMDP --------------------------------------------------------------------------------
    def reset(self, seed: int) -> Observation:
        self.seed, self.t = int(seed), 0
        s = self.settings
        placement = draw(s, np.random.default_rng(self.seed))
        self.placement = placement
        self.scene.build(placement)
        self.camera_pose = CameraPose()  # the episode's camera offsets (domain randomisation), for the record
        if s.randomisation.enabled:
            self.camera_pose = CameraPose.draw(s.randomisation, np.random.default_rng([self.seed, 7]))
        self.camera.set_pose(self.camera_pose)
        for _ in range(SETTLE_STEPS):
            self.step_physics()
        self.trials, self.grasped, self.failed = 0, False, False
        self.fsm = "prog_norm"
        world = self._perceive()
        self.controller.reset(self._err)
        return self._observation(world)

    def episode_conditions(self) -> dict[str, np.ndarray]:
        """What this episode drew besides its seed, for ``Episode.conditions``: whether domain
        randomisation was on, the camera's offsets, the object's kind and scale."""
        p, c = self.placement, self.camera_pose
        return {
            "randomised": np.array([int(self.settings.randomisation.enabled)], np.int64),
            "camera_offsets": np.array([c.distance, c.pitch_deg, c.roll_deg, c.yaw_deg], np.float64),
            "object_kind": np.array([objects.KINDS.index(p.spec.kind)], np.int64),
            "object_scale": np.array([p.spec.scale], np.float64),
        }

    def step(self, action: np.ndarray) -> tuple[Observation, float, bool, bool, dict]:
        """One env step. An action that is not ``ACTION_DIM`` finite numbers is refused with a
        ValueError naming what is wrong, before anything (instrument, physics, time) changes."""
        a = check_action(action)
        s, acts = self.settings, self.settings.actions
        by_controller = self.controller.active
        executed = self.controller.action(self._err) if by_controller else np.clip(a, -1.0, 1.0)
        delta = executed[1:4] * acts.step_translation  # one scale for the controller and the policy
        turn = float(executed[4]) * acts.step_rotation
        if s.randomisation.enabled and s.randomisation.action_noise > 0:
            u = self._rng(9).uniform(-1.0, 1.0, 4) * s.randomisation.action_noise
            delta, turn = delta + u[:3] * acts.unit_translation, turn + float(u[3]) * acts.unit_rotation
        was_open = self.jaw_open
        clipped = self._command(delta, turn, bool(executed[0] >= 0))
        self.instrument.settle(self.step_physics, RAMP_STEPS, s.min_substeps, s.max_substeps, s.tolerance)
        reached, _ = self.instrument.measured_pivot()
        blocked = bool(np.linalg.norm(reached - self.instrument.state.pivot) > s.blocked_tolerance)
        self._grasp_logic(was_open)
        self.t += 1
        world = self._perceive()
        self.controller.update(self._err)
        self.fsm = self._fsm_state(clipped)
        terminated = self.fsm.startswith("done")
        truncated = not terminated and self.t >= s.max_steps
        obs = self._observation(world)
        success = self.fsm == "done_success"
        info = {"success": success, "fsm": self.fsm, "executed_action": executed.astype(np.float32),
                "controller_acted": by_controller, "clipped": clipped, "blocked": blocked,
                "grasped": self.grasped}  # fmt: skip
        return obs, fsm_reward(self.fsm, s.rewards), terminated, truncated, info

    def _command(self, delta: np.ndarray, turn: float, jaw_open: bool) -> bool:
        """Move the commanded tips by ``delta`` and the yaw by ``turn`` within the limits; True when a
        limit clipped the command."""
        st, inst = self.instrument.state, self.instrument
        want = inst.tip_from_pivot(st.pivot) + delta
        tip = np.clip(want, WORKSPACE[:, 0], WORKSPACE[:, 1])
        limit = self.settings.actions.yaw_limit
        want_yaw = st.yaw + turn
        yaw = float(np.clip(want_yaw, -limit, limit))
        inst.command(inst.pivot_from_tip(tip), yaw, jaw_open)
        return bool(np.any(np.abs(tip - want) > 1e-12) or abs(yaw - want_yaw) > 1e-12)

    def _grasp_logic(self, was_open: bool) -> None:
        scene, s = self.scene, self.settings
        if was_open and not self.jaw_open and not self.grasped and not self.failed:
            self.trials += 1
            if all(self.instrument.jaw_contacts(scene.object)):
                scene.attach()
                self.grasped = True
            elif self.trials >= s.max_grasp_trial:
                self.failed = True
        elif not was_open and self.jaw_open and self.grasped:
            scene.release()  # opening on a grasped object drops it
            self.failed = True

    def _fsm_state(self, clipped: bool) -> str:
        s, scene = self.settings, self.scene
        if self.failed or (self.grasped and not scene.held()):
            return "done_fail"
        if self.grasped and (s.lift_height <= 0 or scene.lifted() >= s.lift_height):
            return "done_success"
        if clipped or (self._err is not None and self._err[2] < s.controller.fsm_z_err_min):
            return "prog_abnorm_1"
        return "prog_norm"

    # --- observation --------------------------------------------------------------------------
    def _perceive(self) -> dict[str, np.ndarray]:
        """Render, back-project and crop each segment's points (world), and update the centroid error."""
        s = self.settings
        z, seg = self.camera.render(self.client)
        masks = {"gripper": seg == self.instrument.body, "object_0": seg == self.scene.object}
        if s.randomisation.enabled:
            z, masks = image_noise(z, masks, s.randomisation, s.camera.distance, self._rng(8))
        world = {}
        for name, mask in masks.items():
            pts = self.camera.unproject(mask, z)
            pts = pts[in_cube(pts, s.dsa)]  # the occupancy grid's cube
            world[name] = _downsample(pts, s.camera.downsample_voxel)
        self._err = centroid_error(
            voxel_centroid(world["gripper"], s.dsa), voxel_centroid(world["object_0"], s.dsa), s.controller
        )
        return world

    def _observation(self, world: dict[str, np.ndarray]) -> Observation:
        s = self.settings
        pivot, yaw = self.instrument.measured_pivot()
        rng = self._rng(1)  # the draw of points depends only on (seed, step)
        P = s.camera.points_per_segment
        points = np.zeros((2, P, 3), np.float32)
        counts = np.zeros(2, np.int32)
        for i, name in enumerate(self.segment_names):
            pts = world[name]
            points[i], counts[i] = sample_fixed(pts - pivot if len(pts) else pts, P, rng)
        pose = np.array([*pivot, yaw], np.float32)
        controller_state, fsm_state = int(self.controller.active), fsm_index(self.fsm)
        gripper, obj = world_clouds(points, counts, pose[:3])
        image = dsa_image(gripper, obj, s.dsa, gripper_state=int(not self.jaw_open), fsm_state=fsm_state,
                          controller_state=controller_state)  # fmt: skip
        return Observation(
            points=points,
            point_counts=counts,
            jaw=self.instrument.jaw_opening(),
            gripper_pose=pose,
            object_poses=self.scene.object_pose()[None].astype(np.float32),
            contacts=np.array([self.instrument.touches(self.scene.object)]),
            image=image,
            controller_state=controller_state,
            fsm_state=fsm_state,
        )

    def observe(self) -> Observation:
        """The observation of the current state (no time passes)."""
        return self._observation(self._perceive())

    # --- placing a state (physics audits) ------------------------------------------------------
    def place_state(
        self, seed: int, pivot: np.ndarray, yaw: float, jaw_open: bool, reset: bool = True
    ) -> None:
        """Put the world into a recorded state, for ``services.augmenter.audit_surgical``: the task
        from ``seed`` (its object where the seed places it, on the tray; ``reset=False`` keeps the
        world as it is), the instrument at rest with its *measured* pivot at ``pivot`` (the commanded
        pivot is corrected once for the drive's sag, then clipped to the workspace), at ``yaw``, the
        jaw commanded open or closed; the policy in control (the P-controller latched off), no grasp
        and the FSM normal, so the next ``step`` executes the given action through the drive."""
        if reset:
            self.reset(seed)
        inst = self.instrument
        want = np.asarray(pivot, np.float64)
        command = want.copy()
        for _ in range(2):  # place, measure the sag under gravity, place again corrected for it
            tip = np.clip(inst.tip_from_pivot(command), WORKSPACE[:, 0], WORKSPACE[:, 1])
            inst.reset(inst.pivot_from_tip(tip), float(yaw), jaw_open=bool(jaw_open))
            for _ in range(SETTLE_STEPS):
                self.step_physics()
            command = command + (want - inst.measured_pivot()[0])
        self.controller.active = False
        self.trials, self.grasped, self.failed = 0, False, False
        self.fsm = "prog_norm"

    # --- helpers for policies -----------------------------------------------------------------
    def discrete_action(self, index: int) -> np.ndarray:
        """The 5-vector of discrete action ``index`` (``proto.discrete_actions``) in the current state."""
        return to_vector(index, self.jaw_open)

    def sample_action(self, rng: np.random.Generator) -> np.ndarray:
        """A uniformly random discrete action as its 5-vector (the random policy's)."""
        return self.discrete_action(int(rng.integers(len(NAMES))))

    def pivot_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) (3,) of the commanded pivot: the tips' workspace raised by the pivot height
        (what MEA's ``MeaDiscreteSettings.pivot_low`` / ``pivot_high`` must equal)."""
        lift = np.array([0.0, 0.0, self.pivot_height])
        return WORKSPACE[:, 0] + lift, WORKSPACE[:, 1] + lift

    def tip(self) -> np.ndarray:
        """Commanded closed-jaw tip position (privileged)."""
        return self.instrument.tip_from_pivot(self.instrument.state.pivot)

    def close(self) -> None:
        if self.client is not None and pb.isConnected(self.client):
            pb.disconnect(self.client)
        self.client = None
