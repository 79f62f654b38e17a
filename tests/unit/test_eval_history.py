"""The eval history file: JSON lines appended and read back, robust to a crash mid-write."""

from __future__ import annotations

import json
import logging

import pytest

from services.evaluator.history import HISTORY, append_history, read_history

pytestmark = pytest.mark.unit


def test_history_round_trip_and_a_truncated_last_line_is_skipped_with_a_warning(tmp_path, caplog):
    path = tmp_path / "eval" / "history.jsonl"
    a = {"version": 1, "env_steps": 0, "success_rate": 0.0, "seeds": [1_000_000_000]}
    b = {"version": 2, "env_steps": 250, "success_rate": 0.5, "seeds": [1_000_000_000]}
    append_history(path, a)  # creates the folder
    append_history(path, b)
    assert read_history(path) == [a, b]
    with open(path, "a") as f:  # a crash in the middle of writing the next record
        f.write('{"version": 3, "env_steps": 500, "succ')
    with caplog.at_level(logging.WARNING, logger="services.evaluator.history"):
        assert read_history(path) == [a, b]
    assert any("unreadable" in r.getMessage() for r in caplog.records)
    # the next append starts on a fresh line: the partial line stays isolated, nothing is lost
    c = {"version": 4, "env_steps": 750, "success_rate": 1.0}
    append_history(path, c)
    assert read_history(path) == [a, b, c]
    lines = path.read_text().splitlines()
    assert len(lines) == 4 and lines[2].startswith('{"version": 3') and json.loads(lines[3]) == c


def test_history_skips_blank_lines_and_non_objects_and_requires_the_file(tmp_path):
    path = tmp_path / "h.jsonl"
    path.write_text('\n{"env_steps": 1, "success_rate": 0.5}\n\n[1, 2]\n"x"\n')
    assert read_history(path) == [{"env_steps": 1, "success_rate": 0.5}]
    with pytest.raises(FileNotFoundError):
        read_history(tmp_path / "missing.jsonl")
    with pytest.raises(ValueError):  # NaN is not valid JSON: refused on write, not discovered on read
        append_history(path, {"success_rate": float("nan")})


def test_the_history_lives_in_the_run_dirs_eval_folder():
    # one home for the path: the evaluator writes it, `mea plot` and `mea bench learning` read it
    assert HISTORY.as_posix() == "eval/history.jsonl" and not HISTORY.is_absolute()
