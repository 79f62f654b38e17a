"""MCAP recordings of wire messages: a crash-tolerant recorder and validating readers.

Layout of a recording (profile ``mea``, library ``mea-rl``):

* one channel per message type, registered on first write: topic ``/mea/<TypeName>`` (or the
  topic passed to :meth:`McapRecorder.write`), message encoding ``msgpack``; its schema is named
  after the type, with encoding ``jsonschema`` and :func:`proto.jsonschema.json_schema_text` as data.
  Message records hold exactly ``msg.encode()`` (the bytes that travel on the bus);
* metadata records: ``run`` (the recorder's ``metadata=``), ``config/<name>`` (``{"json": ...}``,
  see :meth:`McapRecorder.write_config`), any added with :meth:`McapRecorder.add_metadata`, and
  ``recording`` written on close: ``status`` (``complete`` or ``aborted``), ``messages``, times and,
  when aborted, ``error``. A file without ``recording`` was never closed (crash or kill).

Atomicity and crashes: the recorder writes ``<path>.tmp`` and renames it to ``<path>`` only once the
file is finished (summary, indexes, footer) and fsynced, so ``<path>`` is always a complete MCAP.
If the ``with`` block raises, the file is still finished and renamed (``recording.status =
aborted``, logged). A killed process leaves ``<path>.tmp``: every *chunk* already written is
readable (:func:`read_messages` falls back to a linear scan that stops at the first incomplete or
corrupt record) and :func:`recover` counts them or rewrites them into a proper file. Messages in the
chunk still open are lost; a chunk is closed when it exceeds ``chunk_size`` bytes, when a write
comes ``flush_interval_s`` after the last flush, and on :meth:`McapRecorder.flush`. Written chunks
reach the OS at once (a process crash loses nothing written); only ``close`` fsyncs.

Long recordings roll over numbered segment files (:mod:`services.common.mcap_io.segments`:
:class:`SegmentedRecorder`, :func:`recording_segments`, :func:`read_recording`), each one a complete
recording as above, the oldest deleted beyond a byte budget if one is set.

Reading never unpickles anything: payloads go through :func:`proto.codec.decode`, which validates
every field against its spec under the given :class:`~proto.msgpack_wire.Limits`.
"""

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
