"""README.md and docs/: every relative link points at a file that exists (and a `#anchor` at one of
its headings), and every `mea ...` command shown in a code block parses with the command's own parser.

Commands are parsed, never run: the parsers every `mea` command goes through (tyro for the config
commands, `OneLineParser` / argparse for `play`, `plot`, `recording`) are wrapped so that a parse
that succeeds stops the command right there. Code blocks tagged `text` hold output (a transcript of
refused commands, a summary a run prints) and are not read as commands; a `...` token elides
options and is dropped.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
import unicodedata
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
import tyro

from services.cli import main
from services.common import config

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]

FENCE = re.compile(r"^(\s*)(`{3,}|~{3,})\s*([\w+-]*)")
LINK = re.compile(r"!?\[(?:[^\]\\]|\\.)*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REF_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$")
INLINE_CODE = re.compile(r"(`+)(?:(?!\1).)+?\1")
COMMAND_BLOCKS = {"", "bash", "sh", "shell", "console"}
MEA_WORD = re.compile(r"(?:^|[\s;&|/])mea(?:\s|$)")
NOT_SHELL = "<not a shell line>"
SEPARATORS = {";", "&&", "||", "|", "&"}


@dataclass(frozen=True)
class Block:
    info: str
    start: int  # line number (1-based) of its first line
    lines: tuple[str, ...]


def closes(line: str, fence: str) -> bool:
    """Whether ``line`` closes a code block opened by ``fence`` (as many fence characters or more)."""
    text = line.strip()
    return len(text) >= len(fence) and set(text) == {fence[0]}


def split_page(text: str) -> tuple[list[tuple[int, str]], list[Block]]:
    """The page's prose lines (numbered, outside code blocks) and its fenced code blocks."""
    prose: list[tuple[int, str]] = []
    blocks: list[Block] = []
    fence: str | None = None
    info, start, body = "", 0, []
    for number, line in enumerate(text.splitlines(), 1):
        m = FENCE.match(line)
        if fence is None and m:
            fence, info, start, body = m.group(2), m.group(3).lower(), number + 1, []
        elif fence is not None and closes(line, fence):
            blocks.append(Block(info, start, tuple(body)))
            fence = None
        elif fence is not None:
            body.append(line)
        else:
            prose.append((number, line))
    assert fence is None, f"a code block opened at line {start - 1} is never closed"
    return prose, blocks


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped (not `-` or `_`), spaces to `-`."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading: its text
    text = unicodedata.normalize("NFC", text.strip().lower())
    text = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    prose, _ = split_page(path.read_text(encoding="utf-8"))
    seen: dict[str, int] = {}
    out = set()
    for _, line in prose:
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        base = slug(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(path: Path) -> list[tuple[int, str]]:
    """(line, target) of every link and image outside code, inline code included."""
    prose, _ = split_page(path.read_text(encoding="utf-8"))
    out = []
    for number, line in prose:
        line = INLINE_CODE.sub("", line)
        out += [(number, m.group(1)) for m in LINK.finditer(line)]
        ref = REF_LINK.match(line)
        if ref:
            out.append((number, ref.group(1)))
    return out


def is_external(target: str) -> bool:
    return re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE) is not None  # https:, mailto:, ...


def link_problem(page: Path, target: str) -> str | None:
    """Why a relative link from ``page`` is broken, or None."""
    file_part, _, anchor = target.partition("#")
    dest = page if not file_part else (page.parent / file_part).resolve()
    if not dest.exists():
        return f"{file_part}: no such file"
    if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
        return f"#{anchor}: no such heading in {dest.name}"
    return None


def all_links() -> list[tuple[str, Path, int, str]]:
    return [
        (f"{page.relative_to(ROOT)}:{number} {target}", page, number, target)
        for page in PAGES
        for number, target in links(page)
        if not is_external(target)
    ]


def commands_in(text: str) -> list[tuple[int, list[str]]]:
    """(line, argv after `mea`) of every `mea` command in the page's command code blocks."""
    _, blocks = split_page(text)
    out = []
    for block in blocks:
        if block.info not in COMMAND_BLOCKS:
            continue
        joined: list[tuple[int, str]] = []  # continuation lines (a trailing backslash) joined
        pending, first = "", 0
        for offset, line in enumerate(block.lines):
            if not pending:
                first = block.start + offset
            if line.rstrip().endswith("\\"):
                pending += line.rstrip()[:-1] + " "
                continue
            joined.append((first, pending + line))
            pending = ""
        for number, line in joined:
            line = line.strip()
            if line.startswith("$ "):
                line = line[2:]
            out += [(number, argv) for argv in mea_argvs(line)]
    return out


def mea_argvs(line: str) -> list[list[str]]:
    """The `mea` commands of one shell line (after `&&`, `;`, `|`; env assignments and redirections
    dropped)."""
    if not MEA_WORD.search(line):
        return []
    lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|<>")
    lexer.whitespace_split = True
    try:
        tokens = list(lexer)
    except ValueError as exc:  # an unclosed quote: reported by the test of this line
        return [[NOT_SHELL, f"{exc}: {line}"]]
    segments: list[list[str]] = [[]]
    for token in tokens:
        if token in SEPARATORS:
            segments.append([])
        else:
            segments[-1].append(token)
    out = []
    for seg in segments:
        redirect = next((i for i, t in enumerate(seg) if t and set(t) <= set("<>&")), len(seg))
        seg = seg[:redirect]
        while seg and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", seg[0]):
            seg = seg[1:]
        if seg and (seg[0] == "mea" or seg[0].endswith("/mea")):
            out.append([t for t in seg[1:] if t != "..."])
    return out


def all_commands() -> list[tuple[str, list[str]]]:
    out = []
    for page in PAGES:
        for number, argv in commands_in(page.read_text(encoding="utf-8")):
            out.append((f"{page.relative_to(ROOT)}:{number} mea {shlex.join(argv)}"[:120], argv))
    return out


class ParsedError(Exception):
    """The command's parser accepted the command line (raised instead of running the command)."""


@pytest.fixture
def parse_only(monkeypatch, tmp_path):
    """Every parser a `mea` command uses stops the command once it has parsed. The commands parse
    as on a machine with one GPU, in a directory like the repository's root (its entries linked in,
    less `runs/`) that also holds the docs' placeholder run directory `RUN_DIR` and what their
    examples make first (`limits.json`, from `mea robot --write-limits`)."""
    inside_tyro = []
    real_tyro, real_parse_args = tyro.cli, argparse.ArgumentParser.parse_args

    def tyro_cli(*args, **kwargs):
        inside_tyro.append(True)
        try:
            real_tyro(*args, **kwargs)
        finally:
            inside_tyro.pop()
        raise ParsedError

    def parse_args(self, *args, **kwargs):
        result = real_parse_args(self, *args, **kwargs)
        if inside_tyro:
            return result
        raise ParsedError

    monkeypatch.setattr(tyro, "cli", tyro_cli)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_args)
    monkeypatch.setattr(config.OneLineParser, "parse_args", parse_args)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    for entry in ROOT.iterdir():
        if not entry.name.startswith(".") and entry.name != "runs":  # runs/: never reachable from here
            (tmp_path / entry.name).symlink_to(entry)
    (tmp_path / "RUN_DIR").mkdir()
    (tmp_path / "limits.json").write_text('{"default": {}}\n')
    monkeypatch.chdir(tmp_path)


def parses(argv: list[str]) -> tuple[bool, str]:
    """Whether `mea ARGV` parses (help and version requests count), with what it printed."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        try:
            code = main(argv)
        except ParsedError:
            return True, out.getvalue()
        except SystemExit as exc:
            code = exc.code
    return code == 0, out.getvalue()


LINKS = all_links()
COMMANDS = all_commands()


def test_the_pages_are_found_and_hold_links_and_commands():
    assert (ROOT / "README.md") in PAGES and len(PAGES) > 5
    assert len(LINKS) > 20, LINKS
    assert len(COMMANDS) > 20, COMMANDS


@pytest.mark.parametrize(("name", "page", "number", "target"), LINKS, ids=[x[0] for x in LINKS])
def test_a_relative_link_points_at_an_existing_file_and_heading(name, page, number, target):
    problem = link_problem(page, target)
    assert problem is None, f"{page.relative_to(ROOT)}:{number}: broken link {target}: {problem}"


@pytest.mark.parametrize(("name", "argv"), COMMANDS, ids=[x[0] for x in COMMANDS])
def test_a_mea_command_shown_in_the_docs_parses(name, argv, parse_only):
    assert argv[0] != NOT_SHELL, f"{name}: a code block line names `mea` but is not shell: {argv[1]}"
    ok, printed = parses(argv)
    assert ok, f"{name}: `mea {shlex.join(argv)}` does not parse:\n{printed[-2000:]}"


def test_the_checks_catch_a_broken_link_a_missing_heading_and_a_bad_command(parse_only, tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# A heading\n\n[ok](page.md#a-heading) [gone](nope.md) [bad](#no-heading)\n")
    problems = {t: link_problem(page, t) for _, t in links(page)}
    assert problems["page.md#a-heading"] is None
    assert "no such file" in problems["nope.md"]
    assert "no such heading" in problems["#no-heading"]
    block = "```bash\nFOO=1 .venv/bin/mea run --actors x \\\n  --seed 0   # a comment\nmea plot --nope\n```\n"
    [(line1, run_argv), (line2, plot_argv)] = commands_in(block)
    assert (line1, run_argv) == (2, ["run", "--actors", "x", "--seed", "0"])
    assert (line2, plot_argv) == (4, ["plot", "--nope"])
    assert parses(run_argv)[0] is False
    assert parses(plot_argv)[0] is False
    assert parses(["run", "--actors", "2"])[0] is True
    assert parses(["plot", "runs/a", "--out", "c.png"])[0] is True
