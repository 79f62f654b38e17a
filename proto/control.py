"""Service status heartbeats, the learner's replay gate, and evaluation reports."""

from __future__ import annotations

from dataclasses import dataclass

from proto.codec import Message
from proto.episode import TASKS
from proto.specs import ID_PATTERN, Float, Int, ListOf, MapOf, Str, spec

SERVICES = (
    "router", "actor", "augmenter", "learner", "evaluator", "inference", "robot", "operator", "launcher", "bench",
    "test",
)  # fmt: skip
STATES = ("starting", "running", "stopping", "failed")


@dataclass(frozen=True)
class Heartbeat(Message):
    """Periodic status of one service instance (also what `mea run`'s live table shows)."""

    TYPE = "Heartbeat"
    VERSION = 1

    service: str = spec(Str(choices=SERVICES), "service kind")
    instance_id: str = spec(Str(pattern=ID_PATTERN), "instance id, unique per service kind")
    pid: int = spec(Int(0, 2**31 - 1), "OS process id")
    state: str = spec(Str(choices=STATES), "lifecycle state")
    started_at: float = spec(Float(0.0), "UNIX time (s) the process started")
    created_at: float = spec(Float(0.0), "UNIX time (s) of this heartbeat")
    policy_version: int = spec(Int(-1, 2**62), "weights version in use (-1: none)")
    counters: dict = spec(MapOf(Float()), "key counters and gauges by metric-like name")
    detail: str = spec(Str(max_len=512), "free text: last error or a short note", default="")


@dataclass(frozen=True)
class EvalReport(Message):
    """Result of evaluating one weights version on held-out seeds."""

    TYPE = "EvalReport"
    VERSION = 1

    evaluator_id: str = spec(Str(pattern=ID_PATTERN), "evaluator instance id")
    run_id: str = spec(Str(pattern=ID_PATTERN), "training run id the weights belong to")
    task: str = spec(Str(choices=TASKS), "task evaluated")
    policy_version: int = spec(Int(0, 2**62), "weights version evaluated")
    env_steps: int = spec(Int(-1, 2**62), "training env steps when that version was made (-1 unknown)")
    episodes: int = spec(Int(1, 1_000_000), "evaluation episodes run")
    success_rate: float = spec(Float(0.0, 1.0), "fraction of successful episodes")
    mean_return: float = spec(Float(), "mean undiscounted return")
    mean_length: float = spec(Float(0.0), "mean episode length (steps)")
    grasp_score: float = spec(Float(0.0, 1.0), "mean s_g = (H_max - H) / H_max on success, 0 on failure")
    created_at: float = spec(Float(0.0), "UNIX time (s) of the report")


@dataclass(frozen=True)
class ReplayGate(Message):
    """The learner's sample-to-insert limiter, as producers see it: may more env steps come now?

    Actors publish a new (non-demonstration) episode only while ``inserted_steps < allowed_steps``;
    otherwise they wait for a newer gate. The learner publishes it about twice a second and whenever
    the allowance changes from zero to positive."""

    TYPE = "ReplayGate"
    VERSION = 1

    learner_id: str = spec(Str(pattern=ID_PATTERN), "learner instance id")
    run_id: str = spec(Str(pattern=ID_PATTERN), "training run id")
    inserted_steps: int = spec(
        Int(0, 2**62), "raw env steps the learner has inserted (augmented copies not counted)"
    )
    allowed_steps: int = spec(Int(0, 2**62), "inserted steps the limiter allows before producers must wait")
    updates: int = spec(Int(0, 2**62), "gradient updates done")
    policy_version: int = spec(Int(-1, 2**62), "latest weights version published")
    replay_transitions: int = spec(Int(0, 2**62), "transitions stored (raw and augmented)")
    created_at: float = spec(Float(0.0), "UNIX time (s) of this gate")


ACK_WINDOW = 256
"""Raw episode ids an ``EpisodeAck`` carries: the newest the learner has taken."""


@dataclass(frozen=True)
class EpisodeAck(Message):
    """The raw episodes that reached the learner, newest last: a sliding window, so one ack that is
    superseded before it is read loses nothing. Actors keep each episode they published until an
    ack names it, and publish it again when an augmenter or learner (re)starts or the ack is late;
    the learner stores an episode id once (repeats are acknowledged again, not stored)."""

    TYPE = "EpisodeAck"
    VERSION = 1

    learner_id: str = spec(Str(pattern=ID_PATTERN), "learner instance id")
    run_id: str = spec(Str(pattern=ID_PATTERN), "training run id")
    episode_ids: list = spec(
        ListOf(Str(pattern=ID_PATTERN), max_len=ACK_WINDOW),
        "raw episode ids taken (stored, repeated or refused), oldest first",
    )
    created_at: float = spec(Float(0.0), "UNIX time (s) of this ack")
