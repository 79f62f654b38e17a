"""Topic registry: every key expression, its message type and QoS, built and parsed here only.

Keys look like ``mea/v1/<namespace>/<topic path>``. ``<namespace>`` separates training runs that
share a Zenoh network (default ``default``). Placeholders in a topic path are single chunks.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass

from proto.codec import Message
from proto.control import EpisodeAck, EvalReport, Heartbeat, ReplayGate
from proto.episode import Episode
from proto.inference import ActReply, ActRequest, EStop, ResetReply, ResetRequest
from proto.specs import ID_PATTERN
from proto.weights import WeightsAnnouncement, WeightsBlob

PREFIX = "mea/v1"
CHUNK = re.compile(ID_PATTERN)  # ids (actor, learner, instance) travel in key expressions


class Priority(enum.Enum):
    """Zenoh priorities, highest first (names match zenoh.Priority)."""

    REAL_TIME = 1
    INTERACTIVE_HIGH = 2
    INTERACTIVE_LOW = 3
    DATA_HIGH = 4
    DATA = 5
    DATA_LOW = 6
    BACKGROUND = 7


class Congestion(enum.Enum):
    BLOCK = "block"  # never drop: the publisher waits (episodes, weights, reports)
    DROP = "drop"  # telemetry only: losing a heartbeat is harmless


class Kind(enum.Enum):
    PUBSUB = "pubsub"
    QUERY = "query"  # a queryable answers gets with the message
    LIVELINESS = "liveliness"  # a token, no payload


@dataclass(frozen=True)
class QoS:
    congestion: Congestion
    priority: Priority
    reliable: bool = True
    express: bool = False
    latest_only: bool = False
    """A subscriber keeps only the newest message per key (per sender) and never makes the transport
    wait: for values where only the latest matters (gates, announcements, heartbeats)."""


@dataclass(frozen=True)
class Topic:
    name: str
    path: str  # relative to PREFIX/<namespace>, with {placeholders}
    kind: Kind
    message: type[Message] | None
    qos: QoS
    doc: str
    max_bytes: int = 1024 * 1024
    """Largest encoded message a subscriber accepts on this topic (larger ones are refused and
    counted before decoding): sized to the largest legitimate message with room to spare."""
    writers: tuple[str, ...] = ()
    """Service kinds whose sealed messages consumers accept on this topic (empty: any service of
    the run). Enforced when the run authenticates its bus (see proto/seal.py)."""
    request: type[Message] | None = None
    """QUERY topics whose queries carry a message (as the query's payload): its type."""
    requesters: tuple[str, ...] = ()
    """Service kinds whose sealed requests a server accepts (empty: any service of the run)."""

    @property
    def placeholders(self) -> tuple[str, ...]:
        return tuple(re.findall(r"{(\w+)}", self.path))


_DATA = QoS(Congestion.BLOCK, Priority.DATA)
EPISODE_MAX_BYTES = 64 * 1024 * 1024
"""An 80-step episode with 1,024 points per segment, its depth image and policy images is under 8 MiB."""

EPISODES_RAW = Topic(
    "episodes_raw",
    "episodes/raw/{source}",
    Kind.PUBSUB,
    Episode,
    _DATA,
    "finished episodes from actor `source`",
    EPISODE_MAX_BYTES,
    ("actor",),
)
EPISODES_AUGMENTED = Topic(
    "episodes_augmented",
    "episodes/augmented/{source}",
    Kind.PUBSUB,
    Episode,
    _DATA,
    "raw episodes passed through plus augmented copies, from augmenter `source`",
    EPISODE_MAX_BYTES,
    ("augmenter",),
)
WEIGHTS_ANNOUNCE = Topic(
    "weights_announce",
    "weights/announce/{source}",
    Kind.PUBSUB,
    WeightsAnnouncement,
    QoS(Congestion.BLOCK, Priority.INTERACTIVE_HIGH, express=True, latest_only=True),
    "a new weights version exists at learner `source`",
    writers=("learner",),
)
WEIGHTS_LATEST = Topic(
    "weights_latest",
    "weights/latest/{source}",
    Kind.QUERY,
    WeightsBlob,
    QoS(Congestion.BLOCK, Priority.DATA_HIGH),
    "queryable: the latest weights blob; selector parameter `min_version=N` answers nothing when older",
    256 * 1024 * 1024,
    ("learner",),
)
EVAL_REPORTS = Topic(
    "eval_reports",
    "eval/reports/{source}",
    Kind.PUBSUB,
    EvalReport,
    _DATA,
    "evaluation results from evaluator `source`",
    writers=("evaluator",),
)
REPLAY_GATE = Topic(
    "replay_gate",
    "learner/gate/{source}",
    Kind.PUBSUB,
    ReplayGate,
    QoS(Congestion.BLOCK, Priority.INTERACTIVE_LOW, latest_only=True),
    "the learner's insert allowance (sample-to-insert limiter); actors wait while it is used up",
    writers=("learner",),
)
EPISODE_ACKS = Topic(
    "episode_acks",
    "learner/acks/{source}",
    Kind.PUBSUB,
    EpisodeAck,
    QoS(Congestion.BLOCK, Priority.INTERACTIVE_LOW, latest_only=True),
    "raw episodes learner `source` has taken (a sliding window); actors publish again what it lacks",
    writers=("learner",),
)
STATUS = Topic(
    "status",
    "status/{service}/{instance}",
    Kind.PUBSUB,
    Heartbeat,
    QoS(Congestion.DROP, Priority.BACKGROUND, reliable=False, latest_only=True),
    "heartbeat of a service instance, about once a second",
)
ALIVE = Topic(
    "alive",
    "alive/{service}/{instance}",
    Kind.LIVELINESS,
    None,
    QoS(Congestion.BLOCK, Priority.INTERACTIVE_HIGH),
    "liveliness token held while the instance's session is open",
)

SERVE_RESET = Topic(
    "serve_reset",
    "serve/reset/{source}",
    Kind.QUERY,
    ResetReply,
    QoS(Congestion.BLOCK, Priority.INTERACTIVE_HIGH),
    "queryable of inference server `source`: a ResetRequest starts an episode of a robot's session",
    writers=("inference",),
    request=ResetRequest,
    requesters=("robot",),
)
SERVE_ACT = Topic(
    "serve_act",
    "serve/act/{source}",
    Kind.QUERY,
    ActReply,
    QoS(Congestion.BLOCK, Priority.REAL_TIME, express=True),
    "queryable of inference server `source`: an ActRequest (one observation) is answered with the action",
    4 * 1024 * 1024,
    ("inference",),
    request=ActRequest,
    requesters=("robot",),
)
ESTOP = Topic(
    "estop",
    "safety/estop/{source}",
    Kind.PUBSUB,
    EStop,
    QoS(Congestion.BLOCK, Priority.REAL_TIME, express=True, latest_only=True),
    "emergency stop of operator `source`, republished every second (latched per operator); robots and "
    "servers hold while any operator's is engaged",
    writers=("operator",),
)

TOPICS: tuple[Topic, ...] = (
    EPISODES_RAW,
    EPISODES_AUGMENTED,
    WEIGHTS_ANNOUNCE,
    WEIGHTS_LATEST,
    EVAL_REPORTS,
    REPLAY_GATE,
    EPISODE_ACKS,
    SERVE_RESET,
    SERVE_ACT,
    ESTOP,
    STATUS,
    ALIVE,
)


class TopicKeyError(ValueError):
    """A key expression could not be built or parsed."""


def check_chunk(what: str, value: str) -> str:
    if not isinstance(value, str) or not CHUNK.fullmatch(value):
        raise TopicKeyError(f"{what}={value!r}: must match {CHUNK.pattern}")
    return value


def key(topic: Topic, namespace: str = "default", **parts: str) -> str:
    """Concrete key, e.g. ``key(EPISODES_RAW, source="actor-0")``; ``"*"`` gives a wildcard chunk."""
    check_chunk("namespace", namespace)
    missing = set(topic.placeholders) - set(parts)
    extra = set(parts) - set(topic.placeholders)
    if missing or extra:
        raise TopicKeyError(f"{topic.name}: missing {sorted(missing)}, unexpected {sorted(extra)}")
    for name, value in parts.items():
        if value != "*":
            check_chunk(name, value)
    return f"{PREFIX}/{namespace}/" + topic.path.format(**parts)


def pattern(topic: Topic, namespace: str = "default") -> str:
    """Key expression matching every instance of a topic."""
    return key(topic, namespace, **{p: "*" for p in topic.placeholders})


def parse(key_expr: str) -> tuple[Topic, str, dict[str, str]]:
    """Inverse of :func:`key`: (topic, namespace, placeholder values)."""
    head = PREFIX + "/"
    if not key_expr.startswith(head):
        raise TopicKeyError(f"{key_expr!r}: not under {PREFIX}")
    namespace, _, rest = key_expr[len(head) :].partition("/")
    check_chunk("namespace", namespace)
    chunks = rest.split("/")
    for topic in TOPICS:
        tchunks = topic.path.split("/")
        if len(tchunks) != len(chunks):
            continue
        parts: dict[str, str] = {}
        for t, c in zip(tchunks, chunks, strict=True):
            if t.startswith("{"):
                parts[t[1:-1]] = c
            elif t != c:
                break
        else:
            for name, value in parts.items():
                check_chunk(name, value)
            return topic, namespace, parts
    raise TopicKeyError(f"{key_expr!r}: no topic matches")


def may_write(topic: Topic, parts: dict[str, str], service: str, instance: str) -> str | None:
    """Why ``service/instance`` may not have sent a message on ``topic`` at the key with ``parts``
    (None when it may): its kind must be one of ``topic.writers`` and the key's ``source`` (or
    ``service``/``instance``) placeholders must name the sender itself."""
    if topic.writers and service not in topic.writers:
        return f"{topic.name} is written only by {'/'.join(topic.writers)}, not {service}"
    if "source" in parts and parts["source"] != instance:
        return f"{service}/{instance} may not publish as source {parts['source']}"
    if parts.get("service", service) != service or parts.get("instance", instance) != instance:
        return f"{service}/{instance} may not publish as {parts.get('service')}/{parts.get('instance')}"
    return None


def may_request(topic: Topic, service: str) -> str | None:
    """Why a sealed request from ``service`` may not be answered on ``topic`` (None when it may)."""
    if topic.requesters and service not in topic.requesters:
        return f"{topic.name} answers only {'/'.join(topic.requesters)}, not {service}"
    return None


def by_name(name: str) -> Topic:
    for t in TOPICS:
        if t.name == name:
            return t
    raise TopicKeyError(f"unknown topic {name!r}")
