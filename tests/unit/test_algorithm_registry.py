"""The algorithm registry is the one place that tells algorithms apart by name: no module under
services/ compares a value with an algorithm's name (``==``, ``!=``, ``in``, ``match``), the names
are the wire's (``proto.weights.ALGORITHMS``), and every learner preset's config is its name's."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from proto.weights import ALGORITHMS as WIRE_ALGORITHMS
from services.algorithms.registry import ALGORITHMS, lookup
from services.learner.config import PRESETS

pytestmark = pytest.mark.unit

SERVICES = Path(__file__).resolve().parents[2] / "services"
TOOLS = Path(__file__).resolve().parents[2] / "mea_tools"
REGISTRY = SERVICES / "learner" / "core" / "registry.py"
COMPARISONS = (ast.Eq, ast.NotEq, ast.In, ast.NotIn)


def _names_in(node: ast.AST) -> set[str]:
    """Algorithm names written as string literals in ``node`` (a constant, or a tuple/list/set of them)."""
    if isinstance(node, ast.Constant) and node.value in ALGORITHMS:
        return {node.value}
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return set().union(*(_names_in(e) for e in node.elts))
    return set()


def algorithm_comparisons(root: Path, skip: Path | None = REGISTRY) -> list[str]:
    """ "path:line name" of every comparison with an algorithm's name as a literal under ``root``."""
    found = []
    for path in sorted(root.rglob("*.py")):
        if skip is not None and path == skip:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names: set[str] = set()
            if isinstance(node, ast.Compare) and any(isinstance(op, COMPARISONS) for op in node.ops):
                names = set().union(*(_names_in(n) for n in (node.left, *node.comparators)))
            elif isinstance(node, ast.MatchValue):
                names = _names_in(node.value)
            found += [f"{path.relative_to(root)}:{node.lineno} {n}" for n in sorted(names)]
    return found


def test_no_module_compares_with_an_algorithm_name_outside_the_registry():
    assert algorithm_comparisons(SERVICES) == []
    assert algorithm_comparisons(TOOLS) == []


@pytest.mark.parametrize(
    ("code", "where"),
    [
        ('if cfg.algorithm == "gasv2":\n    pass\n', "pkg/planted.py:2"),
        ('ok = "rsac" != blob.algorithm\n', "pkg/planted.py:2"),
        ('ok = name in ("equi_rsac", "rsac")\n', "pkg/planted.py:2"),
        ('match name:\n    case "gasv2":\n        pass\n', "pkg/planted.py:3"),
    ],
)
def test_the_check_finds_a_planted_comparison(tmp_path, code, where):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "planted.py").write_text('x = "gasv2"  # naming one is fine\n' + code)
    assert {found.split()[0] for found in algorithm_comparisons(tmp_path)} == {where}


def test_the_registry_names_the_wire_s_algorithms_and_each_preset_s_config_is_its_name_s():
    assert set(ALGORITHMS) == set(WIRE_ALGORITHMS)
    for name, cfg in PRESETS.items():
        assert isinstance(cfg.algorithm, lookup(cfg.algorithm.name).config), name
    with pytest.raises(ValueError, match="unknown algorithm 'sac'; the learners are equi_rsac, rsac, gasv2"):
        lookup("sac")
