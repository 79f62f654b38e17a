"""`mea bench learning --best-episodes`: which weights a run's evaluations select, the fresh seeds
they then play (never the evaluator's), the result kept in the run directory, and the columns the
tables gain. The playing itself is faked here; the evaluator's ``EpisodeRunner`` is tested elsewhere."""

from __future__ import annotations

import json

import pytest

from mea_tools.bench import best_policy, learning
from mea_tools.bench.learning import LearningBenchConfig, run
from proto.seeds import EVAL_SEED_BASE
from services.evaluator.history import HISTORY, append_history
from tests.unit.test_bench_learning import REPS, make_run

pytestmark = pytest.mark.unit


def record(version, steps, success, episodes=20):
    return {"version": version, "env_steps": steps, "success_rate": success, "episodes": episodes}


def test_the_best_evaluation_is_the_highest_success_and_the_latest_of_equals():
    records = [record(0, -1, 1.0), record(3, 1_000, 0.4), record(7, 2_000, 0.9), record(9, 3_000, 0.9),
               record(12, 4_000, 0.5), {"version": "x", "env_steps": 5_000, "success_rate": 1.0}]  # fmt: skip
    assert best_policy.best_record(records)["version"] == 9  # unknown steps and bad records never chosen
    assert best_policy.best_record([record(0, -1, 1.0)]) is None
    assert best_policy.best_record([]) is None


class FakePlay:
    def __init__(self, success: float):
        self.success, self.calls = success, []

    def __call__(self, run_dir, version, first_seed, episodes):
        self.calls.append((run_dir.name, version, first_seed, episodes))
        return self.success


def test_the_chosen_weights_play_fresh_seeds_once_and_again_when_a_better_version_comes(tmp_path):
    run_dir = make_run(tmp_path, "equirsac", 0, [(1_000, 0.3), (2_000, 0.95), (3_000, 0.6)], budget=3_000)
    play = FakePlay(0.88)
    got = best_policy.measure(run_dir, 50, play)
    # version 2 (0.95 at 2K); seeds past every evaluation's (the evaluator's start at EVAL_SEED_BASE)
    assert play.calls == [(run_dir.name, 2, EVAL_SEED_BASE + best_policy.FRESH_SEED_OFFSET, 50)]
    assert got == {"version": 2, "episodes": 50, "first seed": EVAL_SEED_BASE + 1_000_000, "env steps": 2_000,
                   "selected by": 0.95, "success": 0.88}  # fmt: skip
    assert json.loads((run_dir / best_policy.CACHE).read_text()) == got
    assert best_policy.measure(run_dir, 50, play) == got and len(play.calls) == 1  # kept, not played again
    best_policy.measure(run_dir, 20, play)  # other episodes: played again
    append_history(run_dir / HISTORY, record(4, 3_500, 1.0))
    again = best_policy.measure(run_dir, 20, play)
    assert [c[1] for c in play.calls] == [2, 2, 4] and again["version"] == 4
    (run_dir / best_policy.CACHE).write_text("not json")  # a damaged cache is played again, not trusted
    assert best_policy.measure(run_dir, 20, play)["version"] == 4 and len(play.calls) == 4
    assert best_policy.measure(make_run(tmp_path, "equirsac", 1, []), 50, play) is None


def test_the_bench_adds_each_runs_best_weights_and_their_mean_per_arm_only_when_asked(tmp_path, monkeypatch):
    out = tmp_path / "bench"
    for seed, peak in enumerate((0.9, 1.0)):
        make_run(out, "equiobs", seed, [(10_000, peak), (20_003, 0.6)])
    monkeypatch.setattr(
        learning, "train", lambda cfg, variant, seed, s: learning.run_dir_of(cfg, variant, seed)
    )
    play = FakePlay(0.8)
    monkeypatch.setattr(best_policy, "play_fresh_seeds", play)
    cfg = dict(out=out, variants=("equiobs",), seeds=2, json=True, bootstrap_reps=REPS)
    plain = run(LearningBenchConfig(**cfg))
    assert play.calls == [] and "best weights on fresh seeds" not in plain["results"]["runs"][0]
    result = run(LearningBenchConfig(**cfg, best_episodes=50))
    assert sorted(c[:2] for c in play.calls) == [("block_pull-equiobs-s0", 1), ("block_pull-equiobs-s1", 1)]
    rows = result["results"]["runs"]
    assert [(r["best weights (env steps)"], r["best weights on fresh seeds"]) for r in rows] == [
        (10_000, 0.8)
    ] * 2
    assert [r["success at budget"] for r in rows] == [0.6, 0.6]  # the budget's own column is unchanged
    arm = result["results"]["comparison"][0]
    assert arm["best weights on fresh seeds (mean)"] == pytest.approx(0.8)
    assert result["meta"]["best_episodes"] == 50
