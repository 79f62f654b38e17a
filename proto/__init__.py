"""Versioned wire schemas (msgpack) and the topic registry. See proto/README.md."""

from proto.codec import Message, decode
from proto.control import EpisodeAck, EvalReport, Heartbeat, ReplayGate
from proto.episode import Augmentation, Episode
from proto.msgpack_wire import DEFAULT_LIMITS, Limits, ProtocolError
from proto.weights import WeightsAnnouncement, WeightsBlob, tensors_digest

__all__ = [
    "DEFAULT_LIMITS",
    "Augmentation",
    "Episode",
    "EpisodeAck",
    "EvalReport",
    "Heartbeat",
    "Limits",
    "Message",
    "ProtocolError",
    "ReplayGate",
    "WeightsAnnouncement",
    "WeightsBlob",
    "decode",
    "tensors_digest",
]
