"""Episode: one whole rollout as the actors publish it, and augmented copies with provenance.

Per-step arrays follow one convention: observations (and the privileged state recorded beside
them) have ``T+1`` rows, one per visited state including the last; actions, rewards and the two
end flags have ``T`` rows, one per transition. Nothing is stored twice: the next observation of
step ``t`` is observation ``t+1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from proto.actions import ACTION_DIM
from proto.codec import Message
from proto.msgpack_wire import ProtocolError
from proto.specs import ID_PATTERN, Arr, Bool, Float, Int, ListOf, MapOf, Nested, Opt, Str, spec

TASKS = ("block_pull", "block_pick", "drawer_open", "surgical_grasp_any")
DSA_TASKS = ("surgical_grasp_any",)
"""Tasks whose episodes carry the env's DSA image (``images``: uint8 (T+1, 3, 64, 64)) as the policy's
observation, and no voxel or depth input (``services.observation.dsa``)."""
POLICY_KINDS = ("expert_probe", "expert_direct", "random", "learned", "jump_start")
"""``jump_start``: a demonstration's first steps replayed, then the learned policy (JSRL)."""
AUGMENTATION_KINDS = ("isometric", "mea", "mea+isometric")
OBJECT_SYMMETRY = {"block_pull": 4, "block_pick": 4, "drawer_open": 1, "surgical_grasp_any": 1}
"""Order n of each task's objects' rotational symmetry about z: an object's yaw in
``object_poses`` means the same body placement modulo 2 pi / n (square blocks 4, a drawer 1)."""


def succeeded(terminated, rewards=None) -> bool:
    """The one definition of a successful episode: its last step terminated, and (where the rewards
    are given) not with a negative reward. The general-manipulation tasks end early only on success;
    ``surgical_grasp_any`` also ends on a failed grasp, which it rewards with -0.1; a time limit sets
    ``truncated`` instead. Without the rewards, a terminated end counts as success (right for the
    general tasks only)."""
    if len(terminated) == 0 or not terminated[-1]:
        return False
    return rewards is None or float(rewards[-1]) >= 0.0


@dataclass(frozen=True)
class Augmentation(Message):
    """Where an augmented episode came from and how it was made (enough to regenerate it)."""

    TYPE = "Augmentation"
    VERSION = 1
    NESTED_ONLY = True

    source_episode_id: str = spec(Str(pattern=ID_PATTERN), "`episode_id` of the raw episode transformed")
    kind: str = spec(Str(choices=AUGMENTATION_KINDS), "which transforms were applied")
    seed: int = spec(Int(0, 2**63 - 1), "seed of the generator that drew the group elements")
    copy_index: int = spec(Int(0, 1_000_000), "index of this copy among those made from the source")
    phase_split: int = spec(Int(0, 100_000), "H_p: first step of the trivial phase (MEA); 0 if not MEA")
    params: dict = spec(
        MapOf(Arr(("float32", "float64", "int64"), ("N",), finite=True)),
        "group parameters, 1-D arrays by name: `rotation` (1,) rad (rotated copies), `delta_r`, `delta_z`, "
        "`delta_rot`, `delta_theta`, `eps` (H_p,) and `start` (1,) (MEA copies), `quarter_turns` (H_p,) "
        "(discrete MEA copies); see section 4",
    )


@dataclass(frozen=True)
class Episode(Message):
    """A finished episode: policy observations, actions, rewards, flags and privileged state."""

    TYPE = "Episode"
    VERSION = 3
    OLDER_READABLE = {1: frozenset({"fixed_object", "conditions"}), 2: frozenset({"conditions"})}
    # v2 added fixed_object, v3 conditions

    episode_id: str = spec(Str(pattern=ID_PATTERN), "unique id, `<actor_id>-<seed>-<counter>` by convention")
    task: str = spec(Str(choices=TASKS), "task name")
    seed: int = spec(Int(0, 2**63 - 1), "seed passed to the environment's reset")
    actor_id: str = spec(Str(pattern=ID_PATTERN), "id of the actor instance that ran it")
    policy_version: int = spec(Int(-1, 2**62), "weights version that acted; -1 for scripted or random")
    policy_kind: str = spec(Str(choices=POLICY_KINDS), "what chose the actions")
    is_demo: bool = spec(Bool(), "true for a scripted demonstration")
    created_at: float = spec(Float(0.0), "UNIX time (s) when the episode finished")
    segments: list = spec(
        ListOf(Str(pattern=r"[a-z0-9_]{1,32}"), max_len=16),
        "names of the S point-cloud segments; `gripper` first, then one per object",
    )
    points: np.ndarray = spec(
        Arr(("float32",), ("T+1", "S", "P", 3), finite=True),
        "segmented point clouds in the gripper-centric frame (m): origin at the gripper pivot (the "
        "gripper points' centroid, calibrated once; 3.1), world orientation; P points per segment, "
        "resampled to a fixed count (3.3)",
    )
    point_counts: np.ndarray = spec(
        Arr(("int32",), ("T+1", "S")), "points observed per segment before resampling (0: segment unseen)"
    )
    jaw: np.ndarray = spec(
        Arr(("float32",), ("T+1",), finite=True, lo=0.0, hi=1.0), "jaw opening, 0 closed .. 1 open"
    )
    actions: np.ndarray = spec(
        Arr(("float32",), ("T", ACTION_DIM), finite=True, lo=-1.0, hi=1.0),
        "normalised actions (jaw, dx, dy, dz, dtheta)",
    )
    rewards: np.ndarray = spec(Arr(("float32",), ("T",), finite=True), "reward received after each action")
    terminated: np.ndarray = spec(
        Arr(("bool",), ("T",)),
        "true on the step that ended the task: success, or a failure that ends it with a negative reward "
        "(`surgical_grasp_any`: a failed grasp, -0.1)",
    )
    truncated: np.ndarray = spec(Arr(("bool",), ("T",)), "true on the step that hit the time limit")
    gripper_pose: np.ndarray = spec(
        Arr(("float32",), ("T+1", 4), finite=True),
        "privileged: gripper pivot (x, y, z) and yaw in the world frame (m, rad; 3.1, 3.2); not a policy input",
    )
    object_poses: np.ndarray = spec(
        Arr(("float32",), ("T+1", "S-1", 7), finite=True),
        "privileged: per object, in `segments[1:]` order, (x, y, z, qx, qy, qz, qw) in the world frame (3.4)",
    )
    contacts: np.ndarray = spec(
        Arr(("bool",), ("T+1", "S-1")), "privileged: gripper touches object i (`segments[1 + i]`; 3.4)"
    )
    fixed_object: int = spec(
        Int(-1, 15),
        "privileged: index (into the objects, `segments[1:]`) of the immovable object; -1 where the task "
        "has none or the producer does not know it",
        default=-1,
    )
    images: np.ndarray | None = spec(
        Opt(Arr(("uint8", "uint16", "float16", "float32"), ("T+1", "C", "H", "W"), finite=True)),
        "optional images (channels first): uint8 policy images or float16 rendered depth (3.5); nil when "
        "the consumer renders them",
        default=None,
    )
    conditions: dict | None = spec(
        Opt(MapOf(Arr(("float32", "float64", "int64"), ("N",), finite=True))),
        "privileged: what the env drew for this episode besides its seed (domain randomisation: "
        "`randomised` (1,) 0/1, `camera_offsets` (4,) distance sim units, pitch, roll, yaw degrees, "
        "`object_scale` (1,), `object_kind` (1,) index into the task's objects); nil where none (3.6)",
        default=None,
    )
    augmentation: Augmentation | None = spec(
        Opt(Nested(Augmentation)), "nil for a raw episode; provenance for an augmented one", default=None
    )

    @property
    def num_steps(self) -> int:
        return int(self.actions.shape[0])

    @property
    def succeeded(self) -> bool:
        """Whether the episode succeeded (``succeeded(terminated, rewards)``)."""
        return succeeded(self.terminated, self.rewards)

    def validate(self, dims: dict[str, int]) -> None:
        if dims.get("T", 0) < 1:
            raise ProtocolError("actions", "an episode needs at least one step")
        n_seg = self.points.shape[1]
        if len(self.segments) != n_seg:
            raise ProtocolError("segments", f"{len(self.segments)} names for {n_seg} point segments")
        if not self.segments or self.segments[0] != "gripper":
            raise ProtocolError("segments", "first segment must be `gripper`")
        if len(set(self.segments)) != len(self.segments):
            raise ProtocolError("segments", "names must be unique")
        if (self.point_counts < 0).any():
            raise ProtocolError("point_counts", "negative count")
        ends = self.terminated | self.truncated
        if ends[:-1].any():
            raise ProtocolError("terminated", "only the last step may end the episode")
        if not ends[-1]:
            raise ProtocolError("terminated", "the last step must be terminated or truncated")
        if self.terminated[-1] and self.truncated[-1]:
            raise ProtocolError("truncated", "a step is either terminated or truncated, not both")
        if self.fixed_object >= n_seg - 1:
            raise ProtocolError("fixed_object", f"object {self.fixed_object} of {n_seg - 1}")
        if self.augmentation is not None and self.augmentation.phase_split > self.num_steps:
            raise ProtocolError("augmentation.phase_split", "beyond the episode's last step")
