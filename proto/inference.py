"""Serving a policy to a robot: session reset, act(observation) -> action, and the operator's e-stop.

A robot (``mea robot``, or a real arm's bridge) talks to an inference server (``mea serve``) with two
queries, each a request message sent as the query's payload and a reply message:

* ``ResetRequest`` -> ``ResetReply`` on SERVE_RESET: start an episode of session ``session`` (one
  robot). The server drops the session's recurrent state and pins the newest policy it holds; the
  reply says which (version) and what it observes, and gives the episode number later requests name.
* ``ActRequest`` -> ``ActReply`` on SERVE_ACT: one observation in, one action out. The action has
  passed the session's safety envelope: ``held`` says it is a hold (no motion, jaw kept) and
  ``reasons`` why it was held or clamped.

Observations are the project's own: the segmented point cloud in the gripper-centric frame (as
``Episode.points``; the server projects it) or an image already projected (as ``Episode.images``).
``state`` carries the pivot and jaw the envelope checks; it is not range-checked on the wire, so a
robot sending NaN or a pose far outside its workspace gets a held reply naming the reason rather than
no reply at all.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from proto.actions import ACTION_DIM
from proto.codec import Message
from proto.episode import TASKS
from proto.msgpack_wire import ProtocolError
from proto.specs import ID_PATTERN, Arr, Bool, Float, Int, ListOf, Opt, Str, spec

OBSERVATIONS = ("voxel", "depth", "dsa")
"""What a policy observes (``services.algorithms.policy.OBSERVATIONS``)."""
REASON = r"[a-z_]{1,32}"
STATE_DIM = 5
"""``ActRequest.state``: pivot x, y, z (m, robot base frame), yaw (rad), jaw opening (0 closed .. 1 open)."""


@dataclass(frozen=True)
class ResetRequest(Message):
    """Start an episode of one robot's session (creates the session on first use)."""

    TYPE = "ResetRequest"
    VERSION = 1

    session: str = spec(
        Str(pattern=ID_PATTERN), "session id: one per robot (its recurrent state and envelope)"
    )
    task: str = spec(
        Str(choices=TASKS), "task the robot performs (the server refuses a policy that cannot observe it)"
    )
    created_at: float = spec(Float(0.0), "UNIX time (s) of the request")


@dataclass(frozen=True)
class ResetReply(Message):
    """The episode started, or why not (``accepted`` false: no weights yet, wrong task)."""

    TYPE = "ResetReply"
    VERSION = 1

    session: str = spec(Str(pattern=ID_PATTERN), "session id")
    accepted: bool = spec(Bool(), "false: no episode started (see `reason`)")
    reason: str = spec(Str(max_len=256), "why not accepted; empty otherwise")
    episode: int = spec(
        Int(0, 2**62), "episode number within the session (0 when refused); ActRequest names it"
    )
    policy_version: int = spec(Int(-1, 2**62), "weights version pinned for this episode (-1: none)")
    run_id: str = spec(Str(max_len=128), "training run the weights come from (empty: none)")
    observation: str = spec(Str(choices=(*OBSERVATIONS, "")), "what the policy observes: `voxel` (send points or "
                            "a (2, 84, 84) image), `depth` or `dsa` (send the image); empty when refused")  # fmt: skip


@dataclass(frozen=True)
class ActRequest(Message):
    """One observation of a session's current episode."""

    TYPE = "ActRequest"
    VERSION = 1

    session: str = spec(Str(pattern=ID_PATTERN), "session id")
    episode: int = spec(Int(1, 2**62), "episode number from the session's ResetReply")
    step: int = spec(Int(0, 1_000_000), "step within the episode, from 0")
    stamp: float = spec(Float(0.0), "UNIX time (s) the observation was taken (the server's watchdog ages it)")
    state: np.ndarray = spec(
        Arr(("float32",), (STATE_DIM,)),
        "pivot x, y, z (m, robot base frame), yaw (rad), jaw opening 0..1; NaN or inf is answered with a hold",
    )
    executed: np.ndarray | None = spec(
        Opt(Arr(("float32",), (ACTION_DIM,))),
        "the action the robot executed on the previous step (what the envelope let through, or what the robot's "
        "own controller did instead); nil on step 0",
        default=None,
    )
    points: np.ndarray | None = spec(
        Opt(Arr(("float32",), ("S", "P", 3))),
        "segmented point clouds in the gripper-centric frame (m), gripper first, as `Episode.points`",
        default=None,
    )
    point_counts: np.ndarray | None = spec(
        Opt(Arr(("int32",), ("S",))), "points observed per segment before resampling", default=None
    )
    image: np.ndarray | None = spec(
        Opt(Arr(("uint8",), ("C", "H", "W"))),
        "the policy image, already projected (uint8 codes)",
        default=None,
    )
    nonce: int = spec(
        Int(0, 2**63 - 1),
        "random per request; the reply echoes it, so a recorded reply replayed later does not match",
        default=0,
    )

    def validate(self, dims: dict[str, int]) -> None:
        if (self.points is None) != (self.point_counts is None):
            raise ProtocolError("points", "points and point_counts come together")
        if (self.points is None) == (self.image is None):
            raise ProtocolError("image", "send exactly one of points (with point_counts) or image")


@dataclass(frozen=True)
class ActReply(Message):
    """The command for one observation, after the session's safety envelope."""

    TYPE = "ActReply"
    VERSION = 1

    session: str = spec(Str(pattern=ID_PATTERN), "session id")
    episode: int = spec(Int(0, 2**62), "episode the action belongs to")
    step: int = spec(Int(0, 1_000_000), "step it answers")
    action: np.ndarray = spec(
        Arr(("float32",), (ACTION_DIM,), finite=True, lo=-1.0, hi=1.0),
        "the command, normalised (jaw, dx, dy, dz, dtheta); a hold is (jaw kept, 0, 0, 0, 0)",
    )
    policy_version: int = spec(Int(-1, 2**62), "weights version that chose it (-1: none, a hold)")
    held: bool = spec(Bool(), "true: a hold (see `reasons`)")
    reasons: list = spec(
        ListOf(Str(pattern=REASON), max_len=16), "why held, or which limits clamped the action"
    )
    compute_seconds: float = spec(Float(0.0), "server time from request to reply (s)")
    nonce: int = spec(Int(0, 2**63 - 1), "the request's nonce", default=0)


@dataclass(frozen=True)
class EStop(Message):
    """An operator's emergency stop. Latched: engaged until that operator (or another) releases it."""

    TYPE = "EStop"
    VERSION = 1

    operator_id: str = spec(Str(pattern=ID_PATTERN), "operator instance id")
    engaged: bool = spec(Bool(), "true: every robot holds")
    created_at: float = spec(Float(0.0), "UNIX time (s)")
    reason: str = spec(Str(max_len=256), "free text", default="")
