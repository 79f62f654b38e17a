"""`mea bench tasks --json` through the CLI: one JSON object with the expected figures."""

from __future__ import annotations

import pytest

from tests.helpers.cli import bench_json

pytestmark = pytest.mark.integration


@pytest.mark.timeout(240)
@pytest.mark.slow
def test_bench_tasks_prints_one_json_object(capsys):
    argv = ["bench", "tasks", "--tasks", "block_pick", "--episodes", "2", "--prior-episodes", "1", "--workers", "2",
            "--json"]  # fmt: skip
    result = bench_json(argv, capsys)
    experts = result["results"]["experts"]
    assert {(r["task"], r["style"]) for r in experts} == {("block_pick", "direct"), ("block_pick", "probe")}
    for r in experts:
        assert r["episodes"] == 2 and 0 <= r["success"] <= 2 and r["env_steps_per_s"] > 0
    probe = next(r for r in experts if r["style"] == "probe")
    assert probe["touched_fixed"] == 2
    prior = result["results"]["transition_prior"][0]
    assert prior["task"] == "block_pick" and prior["samples"] > 0 and prior["translation_error_mm_mean"] < 5
    env_row = next(r for r in result["reference_ratios"] if r["target"] == "env_steps_per_second")
    assert env_row["measured"] == min(r["env_steps_per_s"] for r in experts) and env_row["ratio"] > 0
