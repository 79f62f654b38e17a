"""`mea recording check PATH...`: what each MCAP recording holds and whether it is whole.

Per file: messages, channels, log-time range and whether it is whole or damaged (the byte offset where
its readable part ends, what was recovered before it, messages that did not decode). A directory
stands for its recording segments (``raw-<n>-<k>.mcap``, unfinished ``.tmp`` ones included).
Exit status: 0 every file whole, 1 one or more damaged, 2 bad usage or a path that is missing,
unreadable or not MCAP.
"""

from __future__ import annotations

import datetime
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from mcap.exceptions import InvalidMagic

from services.common.config import OneLineParser
from services.common.mcap_io import recording_segments
from services.common.mcap_io.check import RecordingReport, check_recording

PROG = "mea recording"


def _time(ns: int) -> str:
    when = datetime.datetime.fromtimestamp(ns / 1e9, datetime.UTC)
    return when.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def describe(r: RecordingReport) -> list[str]:
    """The report of one file as lines of text."""
    n_ch = len(r.channels)
    what = f"{r.messages} messages on {n_ch} channel{'s' * (n_ch != 1)}"
    if r.first_ns is not None and r.last_ns is not None:
        what += f", {_time(r.first_ns)} to {_time(r.last_ns)} ({(r.last_ns - r.first_ns) / 1e9:.3f} s)"
    closed = f"status {r.status}" if r.status else "never closed (no recording status)"
    if r.whole:
        head = f"{r.path}: whole, {what}, {r.size} bytes, {closed}"
    else:
        parts = []
        if r.damage is not None:
            d = r.damage
            parts.append(f"damaged at byte {d.offset} of {d.size}: {d.problem}; recovered before it: {what}")
        else:
            parts.append(what)
        if r.bad_records:
            parts.append(f"{r.bad_records} messages that do not decode, skipped (first: {r.errors[0]})")
        head = f"{r.path}: DAMAGED, " + "; ".join(parts) + f"; {closed}"
    lines = [head]
    lines += [f"  {topic}: {count}" for topic, count in sorted(r.channels.items())]
    if r.ignored:
        lines.append(f"  ({r.ignored} messages on channels that are not msgpack, not read)")
    return lines


def _files(path: Path) -> list[Path]:
    if path.is_dir():
        found = recording_segments(path)
        if not found:
            raise FileNotFoundError(f"{path}: a directory without recording segments (raw-<n>-<k>.mcap)")
        return found
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    return [path]


def check(paths: Sequence[Path]) -> int:
    """Print a report per file; the exit status (module docstring)."""
    code = 0
    for path in paths:
        try:
            for f in _files(path):
                report = check_recording(f)
                print("\n".join(describe(report)))
                code = max(code, 0 if report.whole else 1)
        except FileNotFoundError as exc:
            print(f"{PROG} check: {exc}", file=sys.stderr)
            code = 2
        except InvalidMagic:
            print(f"{PROG} check: {path}: not an MCAP file", file=sys.stderr)
            code = 2
        except OSError as exc:
            print(f"{PROG} check: {path}: cannot read it ({exc.strerror or exc})", file=sys.stderr)
            code = 2
    return code


def main(argv: Sequence[str]) -> int:
    parser = OneLineParser(  # bad input: one line, exit code 2 (docs/cli.md); its subparsers too
        prog=PROG, description="Inspect MCAP recordings (raw episodes, demos, robot logs)."
    )
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    p = sub.add_parser(
        "check",
        help="messages, channels, time range, whole or damaged (exit 0 whole, 1 damaged, 2 bad input)",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
    )
    p.add_argument(
        "paths", nargs="+", type=Path, metavar="PATH", help="an .mcap file, or a directory of segments"
    )
    args = parser.parse_args(list(argv))
    logging.disable(logging.WARNING)  # the damage is in the report; no second copy on stderr
    try:
        return check(args.paths)
    finally:
        logging.disable(logging.NOTSET)
