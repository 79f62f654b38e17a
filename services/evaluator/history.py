"""The eval history file ``RUN_DIR/eval/history.jsonl``: one JSON object per evaluation.

Written by the evaluator service as each evaluation finishes (appended and fsynced), read back by a
restarted evaluator (cadence, improvement timestep), by ``mea plot`` and by ``mea bench learning``.
The arithmetic on the records lives in the pure ``services.evaluator.core.metrics``; this module is
only the file.

A line that does not parse (typically a last line truncated by a crash) is skipped with a logged
warning, never an error; :func:`append_history` first terminates such a partial line so the next
record starts on its own line.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path

log = logging.getLogger(__name__)

HISTORY = Path("eval") / "history.jsonl"
"""Where the eval history lives inside a run directory."""


def read_history(path: str | os.PathLike) -> list[dict]:
    """All records of a history file, in file order; unparsable lines are skipped with a warning.

    Raises FileNotFoundError if the file does not exist."""
    records: list[dict] = []
    with open(path, encoding="utf-8", errors="replace") as f:
        lines = f.read().split("\n")
    last = max((i for i, line in enumerate(lines) if line.strip()), default=-1)
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as exc:
            where = "last line (truncated?)" if i == last else f"line {i + 1}"
            log.warning("skipping unreadable eval history line",
                        extra={"path": str(path), "line": i + 1, "where": where, "error": str(exc)})  # fmt: skip
            continue
        if not isinstance(rec, dict):
            log.warning("skipping eval history line that is not an object",
                        extra={"path": str(path), "line": i + 1})  # fmt: skip
            continue
        records.append(rec)
    return records


def append_history(path: str | os.PathLike, record: Mapping) -> None:
    """Append one record as a JSON line (creating the file and its folder), flushed to disk.

    If the file ends in a partial line (a crash mid-write), a newline is written first so the
    partial line stays isolated (and skipped by :func:`read_history`)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    line = json.dumps(dict(record), sort_keys=True, allow_nan=False) + "\n"
    with open(p, "ab+") as f:
        if f.tell() > 0:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":
                line = "\n" + line
        f.write(line.encode())
        f.flush()
        os.fsync(f.fileno())


__all__ = ["HISTORY", "append_history", "read_history"]
