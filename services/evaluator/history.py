"""The eval history file ``RUN_DIR/eval/history.jsonl``: one JSON object per evaluation.

Written by the evaluator service as each evaluation finishes (appended and fsynced), read back by a
restarted evaluator (cadence, improvement timestep), by ``mea plot`` and by ``mea bench learning``.
The arithmetic on the records lives in the pure ``services.evaluator.core.curves``; this module is
only the file.

A line that does not parse (typically a last line truncated by a crash) is skipped with a logged
warning naming the file and the line number, never an error; :func:`append_history` first terminates such a partial line so the next
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


def read_history(path: str | os.PathLike, problems: list[str] | None = None) -> list[dict]:
    """All records of a history file, in file order; each line that is not a JSON object is skipped
    with a warning naming the file and the line number (and appended to ``problems`` if given).

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
            why = "" if isinstance(rec, dict) else f"a JSON {type(rec).__name__}, not an object"
        except json.JSONDecodeError as exc:
            why = f"not JSON ({exc})" + (", truncated by a crash?" if i == last else "")
        if why:
            problem = f"{path}: line {i + 1} skipped: {why}"
            if problems is not None:
                problems.append(problem)
            log.warning(f"unreadable eval history line: {problem}", extra={"path": str(path), "line": i + 1})
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
