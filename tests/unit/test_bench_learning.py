"""`mea bench learning` without training: presets, the `mea run` command of each run (make run's
recipe), resuming, and the comparison table / JSON built from fake run directories."""

from __future__ import annotations

import dataclasses
import json
import subprocess

import pytest

from services.bench import learning
from services.bench.learning import LearningBenchConfig, run, run_args, settings
from services.common import config
from services.evaluator.history import append_history
from services.launcher import PRESETS as RUN_PRESETS
from services.launcher import RunConfig

pytestmark = pytest.mark.unit

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
BUDGET = 20_000


def test_cpu_small_is_20k_steps_one_seed_20_and_50_eval_episodes_paper_is_40k_four_seeds():
    s = settings(LearningBenchConfig())
    assert (s.budget, s.seeds, s.learner, s.eval_every, s.eval_episodes, s.final_eval_episodes) == (
        20_000, 1, None, 1000, 20, 50)  # fmt: skip
    p = settings(LearningBenchConfig(preset="paper"))
    assert (p.budget, p.seeds, p.learner, p.eval_every) == (40_000, 4, "paper", 250)
    assert (p.eval_episodes, p.final_eval_episodes) == (20, 50)
    o = settings(
        LearningBenchConfig(env_steps=500, seeds=2, eval_every=100, eval_episodes=3, final_eval_episodes=4)
    )
    assert (o.budget, o.seeds, o.eval_every, o.eval_episodes, o.final_eval_episodes) == (500, 2, 100, 3, 4)
    with pytest.raises(SystemExit, match="preset"):
        settings(LearningBenchConfig(preset="gpu-huge"))
    with pytest.raises(SystemExit, match="variants"):
        settings(LearningBenchConfig(variants=("sac",)))


def test_a_cpu_small_run_is_make_runs_recipe_with_only_variant_seed_budget_and_run_dir(tmp_path):
    cfg = LearningBenchConfig(out=tmp_path)
    args = run_args(cfg, "equiobs", 0, settings(cfg))
    assert "--learner-preset" not in args  # no learner override: mea run's default, as `make run`
    assert args[:4] == [
        "--task",
        "block_pull",
        "--demos",
        "2",
    ]  # `make run`: mea run --task block_pull --demos 2
    parsed = config.parse(RunConfig, RUN_PRESETS, args, "mea run", "")
    expected = dataclasses.replace(
        RunConfig(), variant="equiobs", env_steps=BUDGET, demos=2, run_dir=tmp_path / "block_pull-equiobs-s0"
    )
    assert parsed == expected  # every other setting, the learner's included, is mea run's default
    assert (parsed.eval_every, parsed.eval_episodes, parsed.final_eval_episodes) == (1000, 20, 50)
    paper = LearningBenchConfig(out=tmp_path, preset="paper")
    pa = config.parse(RunConfig, RUN_PRESETS, run_args(paper, "mea-all", 3, settings(paper)), "mea run", "")
    assert (pa.learner_preset, pa.env_steps, pa.eval_every, pa.seed, pa.variant, pa.mea_on) == (
        "paper", 40_000, 250, 3, "mea", "all")  # fmt: skip


def make_run(out, variant: str, seed: int, curve, wall: float | None = None, episodes_at_budget: int = 50):
    run_dir = out / f"block_pull-{variant}-s{seed}"
    run_dir.mkdir(parents=True)
    config.save(
        RunConfig(variant=variant, seed=seed, env_steps=BUDGET, run_dir=run_dir), run_dir / "config.json"
    )
    history = run_dir / "eval" / "history.jsonl"
    append_history(
        history, {"version": 0, "env_steps": -1, "success_rate": 1.0, "episodes": 20}
    )  # unknown steps
    for version, (steps, success) in enumerate(curve, start=1):
        n = episodes_at_budget if steps >= BUDGET else 20
        append_history(
            history, {"version": version, "env_steps": steps, "success_rate": success, "episodes": n}
        )
    if wall is not None:
        (run_dir / learning.WALL_FILE).write_text(json.dumps({"seconds": wall, "sessions": 1}))
    return run_dir


def _no_training(*args, **kwargs):
    raise AssertionError(f"no run should be trained: {args}")


def test_the_comparison_from_finished_runs_is_hand_computed_and_nothing_is_trained(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setattr(subprocess, "Popen", _no_training)
    out = tmp_path / "bench"
    # equirsac: never succeeds at the budget; AUC s1 = ((0+.1)/2*10000 + (.1+0)/2*10000)/20000 = .05
    make_run(out, "equirsac", 0, [(0, 0.0), (10_000, 0.0), (20_000, 0.0)], wall=3600)
    make_run(out, "equirsac", 1, [(0, 0.0), (10_000, 0.1), (20_000, 0.0)], wall=4400)
    # equiobs: AUC s0 = (.1*5000 + .3*15000)/20000 = .25, s1 = (.1*10000 + .4*10000)/20000 = .25
    make_run(out, "equiobs", 0, [(0, 0.0), (5_000, 0.2), (20_000, 0.4)], wall=4000)
    make_run(out, "equiobs", 1, [(0, 0.0), (10_000, 0.2), (20_000, 0.6)])  # no wall file: not timed
    # mea: AUC s0 = (.25*10000 + .7*10000)/20000 = .475, s1 = (.1+.7)/2 = .4 (uneven: one segment)
    make_run(out, "mea", 0, [(0, 0.0), (10_000, 0.5), (20_000, 0.9)])
    make_run(out, "mea", 1, [(0, 0.1), (20_000, 0.7)])
    cfg = LearningBenchConfig(out=out, seeds=2, json=True)
    result = run(cfg)
    printed = json.loads(capsys.readouterr().out)  # exactly one JSON object on stdout
    assert printed == json.loads((out / "result-block_pull.json").read_text())
    assert printed["benchmark"] == "learning" and printed["meta"]["budget"] == BUDGET
    assert (printed["meta"]["eval_episodes"], printed["meta"]["final_eval_episodes"]) == (20, 50)
    assert (out / "curves-block_pull.png").read_bytes().startswith(PNG_MAGIC)

    rows = {r["variant"]: r for r in result["results"]["comparison"]}
    assert list(rows) == ["equirsac", "equiobs", "mea"]
    expect = {  # success at budget mean, std; AUC mean, std; improvement mean over seeds, seeds improved
        "equirsac": (0.0, 0.0, 0.025, 0.025, None, 0),
        "equiobs": (0.5, 0.1, 0.25, 0.0, 7500.0, 2),
        "mea": (0.8, 0.1, 0.4375, 0.0375, 5000.0, 2),
    }
    for variant, (s_mean, s_std, a_mean, a_std, improvement, improved) in expect.items():
        r = rows[variant]
        assert r["seeds"] == r["seeds at budget"] == 2
        assert r["success at budget (mean)"] == pytest.approx(s_mean) and r[
            "success at budget (std)"
        ] == pytest.approx(s_std)
        assert r["AUC (mean)"] == pytest.approx(a_mean) and r["AUC (std)"] == pytest.approx(a_std)
        assert r["improvement timestep (mean over seeds)"] == (improvement and pytest.approx(improvement))
        assert r["seeds improved"] == improved
    assert rows["mea"]["improvement timestep of the mean curve"] == 0  # mean curve .05, .3, .8: > 0 from 0
    assert rows["equiobs"]["improvement timestep of the mean curve"] == 5000
    assert rows["equirsac"]["wall (min, all seeds)"] == pytest.approx(8000 / 60)
    assert rows["equiobs"]["wall (min, all seeds)"] == pytest.approx(4000 / 60)
    assert rows["mea"]["wall (min, all seeds)"] is None

    per_run = {r["run"]: r for r in result["results"]["runs"]}
    assert len(per_run) == 6 and per_run["block_pull-mea-s1"]["AUC"] == pytest.approx(0.4)
    assert {r["episodes at budget"] for r in per_run.values()} == {50}
    assert per_run["block_pull-equiobs-s0"]["env steps/s"] == pytest.approx(5.0)

    loop = {r["variant"]: r for r in result["results"]["training loop against the public Equi-RSAC code"]}
    public = 1 / 11.1
    assert loop["equirsac"]["env steps/s (whole stack, wall)"] == pytest.approx(40_000 / 8000)
    assert loop["equirsac"]["ratio (vs the faster public end)"] == pytest.approx(5.0 / public)
    assert loop["equiobs"]["runs timed"] == 1 and loop["mea"]["env steps/s (whole stack, wall)"] is None
    assert loop["equiobs"]["learner preset"].startswith(RunConfig().learner_preset)
    assert [r["target"] for r in result["reference_ratios"]] == ["update_seconds", "env_steps_per_second",
                                                                 "replay_bytes_per_1e5"]  # fmt: skip

    # the same as tables: every section, then the targets against the public code
    run(dataclasses.replace(cfg, json=False))
    text = capsys.readouterr().out
    assert text.index("learning: comparison") < text.index("training loop against the public") < text.index(
        "against the public Equi-RSAC code on a 2-core CPU")  # fmt: skip
    assert "AUC (mean)" in text


def test_the_success_at_budget_is_the_budget_evaluation_not_a_later_one(tmp_path, monkeypatch):
    monkeypatch.setattr(subprocess, "Popen", _no_training)
    out = tmp_path / "bench"
    run_dir = make_run(out, "mea", 0, [(0, 0.0), (20_000, 0.6)])
    append_history(
        run_dir / "eval" / "history.jsonl", {"version": 9, "env_steps": 21_000, "success_rate": 0.1}
    )
    result = run(LearningBenchConfig(out=out, variants=("mea",), json=True))
    (row,) = result["results"]["comparison"]
    assert row["success at budget (mean)"] == pytest.approx(0.6)


class FakeProc:
    commands: list[list[str]] = []

    def __init__(self, cmd, **kwargs) -> None:
        FakeProc.commands.append(list(cmd))
        self.returncode = 0

    def wait(self, timeout=None) -> int:
        return 0


def test_interrupted_runs_are_resumed_new_ones_started_and_their_wall_time_added_up(tmp_path, monkeypatch):
    FakeProc.commands = []
    monkeypatch.setattr(subprocess, "Popen", FakeProc)
    out = tmp_path / "bench"
    unfinished = make_run(out, "equiobs", 0, [(0, 0.0), (10_000, 0.2)], wall=100.0)  # stopped half way
    run(LearningBenchConfig(out=out, variants=("equiobs", "mea"), json=True))
    resume_cmd, new_cmd = FakeProc.commands
    assert resume_cmd[resume_cmd.index("run") + 1 :][:2] == ["--resume", str(unfinished)]
    assert "--variant" not in resume_cmd  # the saved settings, not new ones
    assert new_cmd[new_cmd.index("--variant") + 1] == "mea" and "--resume" not in new_cmd
    assert new_cmd[new_cmd.index("--run-dir") + 1] == str(out / "block_pull-mea-s0")
    wall = json.loads((unfinished / learning.WALL_FILE).read_text())
    assert wall["sessions"] == 2 and wall["seconds"] >= 100.0
    assert json.loads((out / "block_pull-mea-s0" / learning.WALL_FILE).read_text())["sessions"] == 1


def test_a_run_directory_made_with_another_budget_is_refused_before_training(tmp_path, monkeypatch):
    monkeypatch.setattr(subprocess, "Popen", _no_training)
    out = tmp_path / "bench"
    old = out / "block_pull-mea-s0"
    config.save(RunConfig(variant="mea", env_steps=8_000, run_dir=old), old / "config.json")
    with pytest.raises(SystemExit, match="env_steps.*delete it"):
        run(LearningBenchConfig(out=out, variants=("equirsac", "mea")))


def test_surgical_grasp_any_compares_gasv2_with_mea_gasv2_on_ten_demos(tmp_path):
    cfg = LearningBenchConfig(out=tmp_path, task="surgical_grasp_any")
    s = settings(cfg)
    assert s.variants == ("gasv2", "mea-gasv2") and s.demos == 10 and s.seeds == 1
    parsed = config.parse(RunConfig, RUN_PRESETS, run_args(cfg, "mea-gasv2", 0, s), "mea run", "")
    assert (parsed.task, parsed.variant, parsed.demos, parsed.env_steps) == (
        "surgical_grasp_any",
        "mea-gasv2",
        10,
        s.budget,
    )
    paper = settings(LearningBenchConfig(out=tmp_path, task="surgical_grasp_any", preset="paper"))
    assert (paper.budget, paper.seeds, paper.eval_every, paper.learner) == (420_000, 3, 10_000, "paper")
    with pytest.raises(SystemExit, match="does not run on"):
        settings(LearningBenchConfig(task="surgical_grasp_any", variants=("mea",)))
    with pytest.raises(SystemExit, match="does not run on"):
        settings(LearningBenchConfig(task="block_pull", variants=("gasv2",)))
