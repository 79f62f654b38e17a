"""The import contracts in pyproject.toml break when an import crosses them.

`make lint` shows they are kept on the real tree; these tests show the same contracts catch a
planted violation, on a copy of the packages, so a contract that silently checks nothing fails here.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _copy_tree(dst: Path) -> None:
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for package in ("proto", "services", "mea_tools"):
        shutil.copytree(ROOT / package, dst / package, ignore=ignore)
    shutil.copy(ROOT / "pyproject.toml", dst / "pyproject.toml")


def _lint(tree: Path) -> subprocess.CompletedProcess[str]:
    assert LINT_IMPORTS.exists(), f"{LINT_IMPORTS} missing: install the dev extra (pip install -e '.[dev]')"
    # PYTHONPATH puts the copy ahead of the editable install, so grimp reads the planted files.
    env = {**os.environ, "PYTHONPATH": str(tree)}
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache"], cwd=tree, env=env, capture_output=True, text=True, timeout=120
    )


def _verdicts(report: str) -> dict[str, str]:
    """Contract name -> KEPT or BROKEN, from the summary (names wrap across lines there)."""
    summary = report.split("Contracts\n---------", 1)[1].split("Contracts:", 1)[0]
    summary = summary.split("\n\n", 1)[1] if "Analyzed" in summary else summary
    flat = " ".join(line.strip() for line in summary.splitlines() if line.strip() and set(line) != {"-"})
    flat = re.sub(r"^Analyzed [^.]*\.\s*", "", flat)
    return {name.strip(): verdict for name, verdict in re.findall(r"(.*?)\s(KEPT|BROKEN)", flat)}


def _plant(tree: Path, module: str, line: str) -> None:
    path = tree / (module.replace(".", "/") + ".py")
    path.write_text(path.read_text() + f"\n{line}  # planted\n")


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    dst = tmp_path_factory.mktemp("contracts")
    _copy_tree(dst)
    return dst


def test_the_copy_keeps_every_contract(tree):
    result = _lint(tree)
    assert result.returncode == 0, result.stdout[-3000:]
    verdicts = _verdicts(result.stdout)
    assert len(verdicts) == 7 and set(verdicts.values()) == {"KEPT"}, verdicts


@pytest.mark.parametrize(
    ("module", "line", "broken"),
    [
        # The evaluator reaching into the actor package: what the independence contract forbids.
        (
            "services.evaluator.history",
            "import services.actor.config",
            "Service packages are independent of each other",
        ),
        # A service library importing a benchmark: tools sit above the services.
        ("services.learner.checkpoint", "import mea_tools", "Tools sit above the services"),
        # A pure algorithm module importing the transport.
        ("services.algorithms.registry", "import zenoh", "Pure algorithm modules"),
    ],
)
def test_a_planted_import_breaks_its_contract(tree, tmp_path, module, line, broken):
    planted = tmp_path / "tree"
    shutil.copytree(tree, planted)
    _plant(planted, module, line)
    result = _lint(planted)
    assert result.returncode != 0
    verdicts = _verdicts(result.stdout)
    named = [verdict for name, verdict in verdicts.items() if name.startswith(broken)]
    assert named == ["BROKEN"], verdicts
