"""Settings of Surgical Grasp Any: world scale, workspace, action scales, hybrid control, rewards,
camera and domain randomisation, as frozen dataclasses (GASv2/SurRoL reference values unless said).

Units. The simulated world is scaled like SurRoL: ``SCALING`` sim units = 1 real metre (1 sim unit =
20 cm real), which keeps millimetre-sized parts well inside Bullet's collision margins. Every length
below is in sim units unless its name ends in ``_real``; the world frame has the tray's top at z = 0
and the workspace centred on x = y = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from services.observation.dsa import SURGICAL_GRASP_ANY, DsaSpec

SCALING = 5.0
"""Sim units per real metre (SurRoL's world scaling)."""

FSM_STATES = ("prog_norm", "prog_abnorm_1", "prog_abnorm_2", "prog_abnorm_3", "done_fail", "done_success")
"""The reference's finite-state-machine states; ``fsm_state`` in an observation is an index into this.
prog_abnorm_1: a workspace/yaw limit clipped the command or the gripper dived below the object
(z error under ``fsm_z_err_min``); 2 and 3 (object sliding, toggle) are kept for the codes' sake and
not raised here."""


def real(metres: float) -> float:
    """Real metres -> sim units."""
    return metres * SCALING


@dataclass(frozen=True)
class ActionSettings:
    """What one unit of action moves (reference ``psm_env._set_action`` and ``DiscreteAction``).

    One scale for every stored action: a unit of dx, dy or dz moves the tips ``step_translation``
    (``unit_translation x discrete_position_scale`` = 0.015 sim, 3 mm real) whoever acted, the
    policy or the hybrid P-controller, and a unit of dtheta turns ``step_rotation`` (45 degrees).
    The reference's P-controller instead drives the raw env (1 cm real per unit) beneath its
    discrete-action wrapper, so its steps and the policy's mean different motions while the episode
    does not say which was which; here the controller's clipped output in [-1, 1] moves at most one
    discrete step per axis, and ``pivot_{t+1} - pivot_t = step_translation * a_t`` holds for every
    recorded step (unless a limit clipped it: ``info['clipped']``, or the tool was blocked:
    ``info['blocked']``), which is the transition prior MEA's ``delta_xyz`` rests on."""

    unit_translation: float = real(0.01)
    """Sim units per unit of the raw env's translation: 1 cm real (0.05 sim), the reference's."""
    unit_rotation: float = math.radians(45.0)
    """Radians turned per unit of the raw env's rotation (45 degrees)."""
    discrete_position_scale: float = 0.3
    """Every executed translation is scaled by this (the reference's simulated ``pos_action_scale``):
    a discrete +-x step, or a saturated P-controller axis, moves 0.3 cm real."""
    discrete_rotation_scale: float = 1.0
    """Every executed rotation is scaled by this: a discrete +-yaw step turns 45 degrees."""
    yaw_limit: float = math.pi
    """The commanded yaw is clipped to [-yaw_limit, yaw_limit] (the jaws are two-fold symmetric, so
    +-pi reaches every grasp orientation)."""

    @property
    def step_translation(self) -> float:
        """Sim units the tips move per unit of a stored dx, dy or dz (0.015: MEA's ``delta_xyz``)."""
        return self.unit_translation * self.discrete_position_scale

    @property
    def step_rotation(self) -> float:
        """Radians turned per unit of a stored dtheta."""
        return self.unit_rotation * self.discrete_rotation_scale


@dataclass(frozen=True)
class ControllerSettings:
    """The hybrid controller's P-controller (reference ``wrapper/pid.py``, simulation values)."""

    enabled: bool = True
    """False: the policy acts from the first step (``controller_state`` is 0 throughout)."""
    gain: tuple[float, float, float] = (10.0, 10.0, 10.0)
    """Kp per axis on the voxel-centroid error (occupancy units); the action is clipped to [-1, 1]."""
    phase_threshold: tuple[float, float, float] = (0.1, 0.1, 0.1)
    """The P-controller acts while any |axis error| exceeds this (occupancy units; 0.1 = 2 cm real)."""
    error_offset: tuple[float, float, float] = (0.0, 0.0, -0.1)
    """Added to gripper centroid - object centroid: the P-controller brings the gripper's centroid
    0.1 occupancy units (2 cm real) above the object's. The reference adds it twice to the action
    (once in the error, again in the command), which only moves the P-controller's set-point to the
    hand-over boundary; here it is added once."""
    fsm_z_err_min: float = -0.06
    """A z error below this (gripper centroid too low over the object) makes the step abnormal."""


@dataclass(frozen=True)
class RewardSettings:
    """FSM rewards (reference ``gym_ras.yaml``)."""

    success: float = 1.0
    fail: float = -0.1
    normal_step: float = -0.001
    abnormal_step: float = -0.01


@dataclass(frozen=True)
class SurgicalCameraSettings:
    """The oblique stereo-camera stand-in: one depth + segmentation view (reference view parameters)."""

    image_size: int = 256
    """Pixels per side rendered by pybullet's tiny renderer (the reference renders 600). At 256 a pixel
    covers at most 0.0041 sim units on the tray (its far edge), under the occupancy voxel (0.005), so
    the voxelised clouds have no holes; 128 would be 2.4x faster (measured 255 vs 106 steps/s on a
    busy 2-core VM) but leaves every other voxel row empty at the far side."""
    fov_deg: float = 45.0
    yaw_deg: float = 180.0
    pitch_deg: float = -20.0
    roll_deg: float = 0.0
    distance: float = real(0.2)
    """Camera distance to its target (0.2 x SCALING)."""
    target: tuple[float, float, float] = (0.0, 0.0, real(0.035))
    """Point the camera looks at: the workspace centre."""
    near: float = 0.05
    far: float = 3.0
    points_per_segment: int = 256
    """Points drawn per segment (services.tasks.camera.sample_fixed)."""
    downsample_voxel: float = 1.0 / 200.0
    """One point per occupied voxel of this edge before the draw: the DSA grid's voxel (its lattice
    contains the grid's corner, so each point is one occupied DSA voxel)."""


@dataclass(frozen=True)
class RandomisationSettings:
    """Domain randomisation (reference ``domain_random_enhance``), drawn from the episode seed.

    Applied where: camera pose noise on the rendering camera (points are back-projected with the
    nominal camera, so they carry the calibration error); depth noise, blur and cutout on the
    rendered depth/mask images before back-projection; action noise on the executed motion (the
    stored action stays the commanded one). The object scale is always drawn (``scale_range``):
    it is part of the task's distribution in the reference, not a switch."""

    enabled: bool = False
    camera_distance: float = 0.05 * SCALING
    """Camera distance jitter, +- sim units (0.05 x SCALING, the reference's). Back-projecting with the
    nominal camera then shifts every point alike along the view axis, which centroid differences
    do not see."""
    camera_pitch_deg: float = 3.0
    camera_roll_deg: float = 3.0
    camera_yaw_deg: float = 1.0
    """Up-axis jitter, +- degrees."""
    depth_noise: float = 0.005
    """Uniform depth noise, +- this fraction of the camera distance."""
    blur_sigma: float = 0.3
    """Gaussian blur (3 x 3 kernel) of the depth image."""
    cutout_keep: tuple[float, float] = (0.8, 1.0)
    """Fraction of each segment's pixels kept (a random rectangle of the rest is cut out)."""
    action_noise: float = 0.01
    """Uniform noise of +- this many action units on each executed translation and rotation component
    (the reference's 0.01): +-0.1 mm real and +-0.45 degrees per step."""


@dataclass(frozen=True)
class SurgicalSettings:
    """Everything Surgical Grasp Any is configured by."""

    max_steps: int = 80
    """Time limit; reaching it truncates the episode."""
    max_grasp_trial: int = 1
    """Closings allowed without a grasp: reaching it ends the episode as a failure."""
    lift_height: float = real(0.005)
    """Success: the grasped object has risen this far (0.5 cm real) above where it lay. 0: success
    as soon as the grasp holds (the reference's ``done_success`` on attaching)."""
    hold_tolerance: float = real(0.002)
    """... and stays within this of where the grasp attached it relative to the jaws."""
    scale_range: tuple[float, float] = (0.75, 1.25)
    """Object scale factor, drawn per episode."""
    object_probabilities: tuple[float, float, float] = (0.5, 0.25, 0.25)
    """Needle, block, rod."""
    tray_constraint_force: float = 20.0
    """maxForce of the fixed constraint holding the object on the tray (and of the grasp)."""
    sim_hz: float = 240.0
    max_substeps: int = 48
    """Most physics steps per action (the drive converges in about 20)."""
    min_substeps: int = 8
    tolerance: float = 2e-4
    """Pivot position error (sim units) at which an action counts as reached."""
    blocked_tolerance: float = 1e-3
    """After a step's physics, a pivot further than this from the commanded one (sim units, 0.2 mm
    real; free motion and lifting settle within 0.2 mm sim) is reported as ``info['blocked']``."""
    actions: ActionSettings = field(default_factory=ActionSettings)
    controller: ControllerSettings = field(default_factory=ControllerSettings)
    rewards: RewardSettings = field(default_factory=RewardSettings)
    camera: SurgicalCameraSettings = field(default_factory=SurgicalCameraSettings)
    dsa: DsaSpec = SURGICAL_GRASP_ANY
    """The occupancy grid (200^3 voxels over a 1-sim-unit cube, world-aligned, centred on the
    workspace centre) and the policy image the P-controller's centroids and the observation's
    ``image`` come from; the augmenter re-projects MEA copies with the same spec
    (``services.observation.dsa.SURGICAL_GRASP_ANY``)."""
    randomisation: RandomisationSettings = field(default_factory=RandomisationSettings)

    def __post_init__(self) -> None:
        if self.max_steps < 1 or self.max_grasp_trial < 1:
            raise ValueError("max_steps and max_grasp_trial must be >= 1")
        if abs(sum(self.object_probabilities) - 1.0) > 1e-9 or min(self.object_probabilities) < 0:
            raise ValueError(f"object_probabilities must be a distribution, got {self.object_probabilities}")
        if not 0 < self.scale_range[0] <= self.scale_range[1]:
            raise ValueError(f"scale_range must be 0 < low <= high, got {self.scale_range}")
