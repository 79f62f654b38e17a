"""MCAP recordings of wire messages: a crash-tolerant recorder and validating readers.

Design notes: docs/architecture-notes.md, services/common/mcap_io/__init__.py."""

from services.common.mcap_io.layout import (
    CONFIG_METADATA_PREFIX,
    LIBRARY,
    MESSAGE_ENCODING,
    PROFILE,
    RECORDING_METADATA,
    RUN_METADATA,
    SCHEMA_ENCODING,
    TMP_SUFFIX,
    TOPIC_PREFIX,
    default_topic,
    tmp_path_for,
)
from services.common.mcap_io.reader import (
    MAX_CHUNK_BYTES,
    ReadStats,
    read_config,
    read_messages,
    read_metadata,
)
from services.common.mcap_io.recorder import McapRecorder
from services.common.mcap_io.recovery import recover
from services.common.mcap_io.segments import (
    SEGMENT_METADATA,
    SegmentedRecorder,
    read_recording,
    recording_segments,
)

__all__ = [
    "CONFIG_METADATA_PREFIX",
    "LIBRARY",
    "MAX_CHUNK_BYTES",
    "MESSAGE_ENCODING",
    "PROFILE",
    "RECORDING_METADATA",
    "RUN_METADATA",
    "SCHEMA_ENCODING",
    "SEGMENT_METADATA",
    "TMP_SUFFIX",
    "TOPIC_PREFIX",
    "McapRecorder",
    "ReadStats",
    "SegmentedRecorder",
    "default_topic",
    "read_config",
    "read_messages",
    "read_metadata",
    "read_recording",
    "recording_segments",
    "recover",
    "tmp_path_for",
]
