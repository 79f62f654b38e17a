"""What a recording looks like on disk: profile, encodings, topic and metadata names, the ``.tmp``
path of an unfinished file, and the MCAP magic (see the package docstring for the whole layout)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

PROFILE = "mea"
LIBRARY = "mea-rl"
MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
TOPIC_PREFIX = "/mea/"
RUN_METADATA = "run"
RECORDING_METADATA = "recording"
CONFIG_METADATA_PREFIX = "config/"
TMP_SUFFIX = ".tmp"

MAGIC = b"\x89MCAP0\r\n"

PathLike = str | os.PathLike[str]


def default_topic(type_name: str) -> str:
    """The topic a message type is recorded on unless told otherwise: ``/mea/<TypeName>``."""
    return TOPIC_PREFIX + type_name


def tmp_path_for(path: PathLike) -> Path:
    """Where a recording of ``path`` lives until it is closed: ``<path>.tmp``."""
    p = Path(path)
    return p.with_name(p.name + TMP_SUFFIX)


def fsync_dir(directory: Path) -> None:
    """Make a rename inside ``directory`` durable, where the platform supports it."""
    with contextlib.suppress(OSError):  # not supported everywhere; the rename is done either way
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
