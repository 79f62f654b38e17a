"""`mea ARGV` run in the test's own process, for tests of what the CLI prints and returns."""

from __future__ import annotations

import json

from services.cli import main


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``mea ARGV`` run in this process."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out = capsys.readouterr()
    return code, out.out, out.err


def bench_json(argv: list[str], capsys) -> dict:
    """The one JSON object ``mea bench NAME ... --json`` prints: exit code 0, nothing else on stdout,
    and its ``benchmark`` is NAME."""
    code, out, _ = run_cli(argv, capsys)
    assert code == 0, out
    lines = out.strip().splitlines()
    assert len(lines) == 1, out
    result = json.loads(lines[0])
    assert result["benchmark"] == argv[1]
    return result
