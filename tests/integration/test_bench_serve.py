"""`mea bench serve --json` through the CLI on a tiny budget: one JSON object, sane figures, no timing thresholds."""

from __future__ import annotations

import pytest

from mea_tools.bench.serve import (
    SECTION_ACT,
    SECTION_LOCAL,
    SECTION_MACHINE,
    SECTION_SWAP,
    SECTION_SWAPS,
    SECTION_TARGET,
)
from tests.helpers.cli import bench_json

pytestmark = pytest.mark.integration
REQUESTS, SWAPS = 30, 2


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_bench_serve_prints_one_sane_json_object(capsys):
    argv = ["bench", "serve", "--requests", str(REQUESTS), "--warmup", "5", "--presets", "cpu-small",
            "--swaps", str(SWAPS), "--observations", "40", "--episode-steps", "10", "--timeout-s", "30",
            "--json"]  # fmt: skip
    result = bench_json(argv, capsys)
    sections = result["results"]
    assert set(sections) == {
        SECTION_ACT,
        SECTION_LOCAL,
        SECTION_SWAP,
        SECTION_SWAPS,
        SECTION_TARGET,
        SECTION_MACHINE,
    }

    # act over the bus: one row per preset, every reply's version recorded, nothing held or clamped
    (act,) = sections[SECTION_ACT]
    assert act["preset"] == "cpu-small" and act["requests"] == REQUESTS and act["actor params"] > 0
    assert 0 < act["round trip p50 ms"] <= act["round trip p99 ms"] <= act["round trip max ms"]
    assert 0 < act["server p50 ms"] <= act["server p99 ms"]
    assert act["versions"] == {"1": REQUESTS}
    assert act["holds"] == 0 and act["clamps"] == 0 and act["hold reasons"] == {}

    (local,) = sections[SECTION_LOCAL]
    assert local["preset"] == "cpu-small" and local["requests"] == REQUESTS
    for what in ("act", "projection", "policy"):
        assert 0 < local[f"{what} p50 ms"] <= local[f"{what} p99 ms"]

    # swaps: versions strictly increase, each ends at the first reply of the new version
    swaps = sections[SECTION_SWAPS]
    versions = [r["version"] for r in swaps]
    assert len(swaps) == SWAPS and versions == sorted(set(versions)) and versions[0] == 2
    for r in swaps:
        seen = {int(v): n for v, n in r["replies by version"].items()}
        assert seen[r["version"]] == 1 and set(seen) <= {r["version"] - 1, r["version"]}
        assert sum(seen.values()) == r["reset+act loops"] and r["publish -> first action ms"] > 0
    (summary,) = sections[SECTION_SWAP]
    assert summary["swaps"] == SWAPS
    assert 0 < summary["publish -> first action p50 ms"] <= summary["max ms"]

    (target,) = sections[SECTION_TARGET]
    assert target["measured ms"] == act["round trip p99 ms"] and target["result"] in ("PASS", "FAIL")
    (machine,) = sections[SECTION_MACHINE]
    assert machine["cores"] >= 1 and machine["server torch threads"] == 1
