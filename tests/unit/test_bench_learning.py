"""`mea bench learning` without training: presets and protocols, the `mea run` command of each run
(make run's recipe), resuming, refusals, and the comparison tables / JSON / PNGs built from fake run
directories (their statistics themselves: test_bench_stats.py)."""

from __future__ import annotations

import dataclasses
import json
import signal
import subprocess
import sys
import threading
import time

import pytest
import torch

from mea_tools.bench import learning
from mea_tools.bench.learning import LearningBenchConfig, run, run_args, settings
from services.common import config
from services.evaluator.history import append_history
from services.launcher import PRESETS as RUN_PRESETS
from services.launcher import RunConfig

pytestmark = pytest.mark.unit

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
BUDGET = 20_000
REPS = 300  # bootstrap resamples: enough for the verdicts below, fast on a shared CPU


def test_cpu_small_is_20k_steps_three_seeds_20_and_50_eval_episodes_paper_is_40k_four_seeds():
    s = settings(LearningBenchConfig())
    assert (s.budget, s.seeds, s.learner, s.eval_every, s.eval_episodes, s.final_eval_episodes) == (
        20_000, 3, None, 2000, 20, 50)  # fmt: skip
    assert s.seed_list == (0, 1, 2) and s.random_steps is None and s.protocol is None
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
        RunConfig(), variant="equiobs", env_steps=BUDGET, demos=2, eval_every=2_000,
        run_dir=tmp_path / "block_pull-equiobs-s0",
    )  # fmt: skip
    assert parsed == expected  # every other setting, the learner's included, is mea run's default
    assert (parsed.eval_every, parsed.eval_episodes, parsed.final_eval_episodes) == (2000, 20, 50)
    paper = LearningBenchConfig(out=tmp_path, preset="paper")
    pa = config.parse(RunConfig, RUN_PRESETS, run_args(paper, "mea-all", 3, settings(paper)), "mea run", "")
    assert (pa.learner_preset, pa.env_steps, pa.eval_every, pa.seed, pa.variant, pa.mea_on) == (
        "paper", 40_000, 250, 3, "mea", "all")  # fmt: skip


def make_run(
    out,
    variant: str,
    seed: int,
    curve,
    wall: float | None = None,
    episodes_at_budget: int = 50,
    budget: int = BUDGET,
    **run_cfg,
):
    """A run directory as `mea run` leaves it: config.json and eval/history.jsonl (and the bench's wall file)."""
    run_dir = out / f"block_pull-{variant}-s{seed}"
    run_dir.mkdir(parents=True)
    config.save(
        RunConfig(variant=variant, seed=seed, env_steps=budget, run_dir=run_dir, **run_cfg),
        run_dir / "config.json",
    )
    history = run_dir / "eval" / "history.jsonl"
    append_history(
        history, {"version": 0, "env_steps": -1, "success_rate": 1.0, "episodes": 20}
    )  # unknown steps
    for version, (steps, success) in enumerate(curve, start=1):
        n = episodes_at_budget if steps >= budget else 20
        append_history(
            history, {"version": version, "env_steps": steps, "success_rate": success, "episodes": n}
        )
    if wall is not None:
        (run_dir / learning.WALL_FILE).write_text(json.dumps({"seconds": wall, "sessions": 1}))
    return run_dir


def _no_training(*args, **kwargs):
    raise AssertionError(f"no run should be trained: {args}")


@pytest.mark.slow
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
    cfg = LearningBenchConfig(out=out, seeds=2, json=True, bootstrap_reps=REPS)
    result = run(cfg)
    printed = json.loads(capsys.readouterr().out)  # exactly one JSON object on stdout
    assert printed == json.loads((out / "result-block_pull.json").read_text())
    assert printed["benchmark"] == "learning" and printed["meta"]["budget"] == BUDGET
    assert (printed["meta"]["eval_episodes"], printed["meta"]["final_eval_episodes"]) == (20, 50)
    assert printed["meta"]["seed list (every arm)"] == [0, 1]
    assert printed["meta"]["bootstrap"]["reps"] == REPS
    for png in ("curves-block_pull.png", "profile-block_pull.png"):  # next to the result
        assert (out / png).read_bytes().startswith(PNG_MAGIC)

    rows = {r["variant"]: r for r in result["results"]["comparison"]}
    speed = {r["variant"]: r for r in result["results"]["learning speed"]}
    assert list(rows) == list(speed) == ["equirsac", "equiobs", "mea"]
    expect = {  # success at budget mean, std; AUC mean, std; improvement mean over seeds, seeds improved
        "equirsac": (0.0, 0.0, 0.025, 0.025, None, 0),
        "equiobs": (0.5, 0.1, 0.25, 0.0, 7500.0, 2),
        "mea": (0.8, 0.1, 0.4375, 0.0375, 5000.0, 2),
    }
    for variant, (s_mean, s_std, a_mean, a_std, improvement, improved) in expect.items():
        r, sp = rows[variant], speed[variant]
        assert r["seeds"] == r["seeds at budget"] == 2
        assert r["success at budget (mean)"] == pytest.approx(s_mean) and r[
            "success at budget (std)"
        ] == pytest.approx(s_std)
        assert r["success at budget (IQM)"] == pytest.approx(s_mean)  # two runs: nothing trimmed
        lo, hi = r["success at budget (95% CI)"]
        assert (
            lo <= s_mean <= hi and lo == pytest.approx(s_mean - s_std) and hi == pytest.approx(s_mean + s_std)
        )
        assert sp["AUC (mean)"] == pytest.approx(a_mean) and sp["AUC (std)"] == pytest.approx(a_std)
        assert sp["AUC (95% CI)"] == pytest.approx([a_mean - a_std, a_mean + a_std])  # 2 runs: min and max
        assert sp["improvement timestep (mean over seeds)"] == (improvement and pytest.approx(improvement))
        assert sp["seeds improved"] == improved
    assert speed["equirsac"]["improvement timestep (95% CI)"] is None
    assert speed["equiobs"]["improvement timestep (95% CI)"] == [5000, 10_000]
    assert speed["mea"]["improvement timestep of the mean curve"] == 0  # mean curve .05, .3, .8: > 0 from 0
    assert speed["equiobs"]["improvement timestep of the mean curve"] == 5000
    assert speed["equirsac"]["wall (min, all seeds)"] == pytest.approx(8000 / 60)
    assert speed["equiobs"]["wall (min, all seeds)"] == pytest.approx(4000 / 60)
    assert speed["mea"]["wall (min, all seeds)"] is None

    # against the first arm: equiobs [.4, .6] and mea [.7, .9] both beat equirsac [0, 0] in every pair;
    # mea against equirsac is separated, and so is equiobs (its CI [.4, .6] misses [0, 0])
    against = {r["variant"]: r for r in result["results"]["against the first arm"]}
    assert list(against) == ["equiobs", "mea"] and {r["against"] for r in against.values()} == {"equirsac"}
    assert against["mea"]["P(improvement)"] == pytest.approx(1.0)
    assert against["mea"]["success at budget"].startswith("separated")
    assert against["equiobs"]["success at budget"].startswith("separated")

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
    assert text.index("learning: comparison") < text.index("learning: against the first arm") < text.index(
        "training loop against the public") < text.index("against the public Equi-RSAC code on a 2-core CPU")  # fmt: skip
    assert "AUC (mean)" in text and "[0.4, 0.6]" in text  # intervals print as [lo, hi]


@pytest.mark.slow
def test_arms_within_noise_are_said_to_be_and_the_bootstrap_seed_reproduces_the_result(tmp_path, monkeypatch):
    monkeypatch.setattr(subprocess, "Popen", _no_training)
    out = tmp_path / "bench"
    for seed, (a, b) in enumerate([(0.3, 0.4), (0.5, 0.3), (0.4, 0.6)]):  # paired by seed, overlapping
        make_run(out, "equiobs", seed, [(0, 0.0), (20_000, a)])
        make_run(out, "mea", seed, [(0, 0.0), (20_000, b)])
    cfg = LearningBenchConfig(out=out, variants=("equiobs", "mea"), json=True, bootstrap_reps=REPS)
    first = run(cfg)["results"]
    (row,) = first["against the first arm"]
    assert row["success at budget"].startswith("within noise")
    assert 0.0 < row["P(improvement)"] < 1.0
    assert run(cfg)["results"] == first  # same runs, same bootstrap seed: the same intervals
    one_seed = run(dataclasses.replace(cfg, seeds=1))["results"]["against the first arm"]
    assert one_seed[0]["success at budget"] == "one seed: no interval to compare"


def test_the_success_at_budget_is_the_budget_evaluation_not_a_later_one(tmp_path, monkeypatch):
    monkeypatch.setattr(subprocess, "Popen", _no_training)
    out = tmp_path / "bench"
    run_dir = make_run(out, "mea", 0, [(0, 0.0), (20_000, 0.6)])
    append_history(
        run_dir / "eval" / "history.jsonl", {"version": 9, "env_steps": 21_000, "success_rate": 0.1}
    )
    result = run(LearningBenchConfig(out=out, variants=("mea",), seeds=1, json=True, bootstrap_reps=REPS))
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
    run(LearningBenchConfig(out=out, variants=("equiobs", "mea"), seeds=1, json=True, bootstrap_reps=REPS,
                            learner_threads=2))  # fmt: skip
    resume_cmd, new_cmd = FakeProc.commands
    assert resume_cmd[resume_cmd.index("run") + 1 :][:2] == ["--resume", str(unfinished)]
    assert "--variant" not in resume_cmd  # the saved settings, not new ones
    # the learner device is the machine's: a resume names it as a new run does
    assert resume_cmd[resume_cmd.index("--learner-device") + 1] == "cpu"
    assert new_cmd[new_cmd.index("--learner-device") + 1] == "cpu"
    # and so are the learner's torch threads
    assert (
        resume_cmd[resume_cmd.index("--learner-threads") + 1]
        == new_cmd[new_cmd.index("--learner-threads") + 1]
        == "2"
    )
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


@pytest.mark.parametrize(
    ("made_with", "named"),
    [
        ({"demos": 15}, "demos"),
        ({"random_steps": 1_000}, "random_steps"),
        ({"learner_preset": "paper"}, "learner_preset"),
    ],
)
def test_a_run_directory_made_with_other_data_or_learner_is_refused_and_nothing_is_written(
    tmp_path, monkeypatch, made_with, named
):
    monkeypatch.setattr(subprocess, "Popen", _no_training)
    out = tmp_path / "bench"
    old = make_run(out, "mea", 0, [(0, 0.0), (20_000, 0.5)], **made_with)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(SystemExit, match=f"{named}.*delete it"):
        run(LearningBenchConfig(out=out, variants=("equiobs", "mea")))
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
    # asked for with the settings it was made with, it is reused as it is
    same = LearningBenchConfig(
        out=out, variants=("mea",), seeds=1, json=True, bootstrap_reps=REPS, env_steps=BUDGET,
        demos=made_with.get("demos", 0), preset="paper" if named == "learner_preset" else "cpu-small",
        extra=("--random-steps", "1000") if named == "random_steps" else (),
    )  # fmt: skip
    (row,) = run(same)["results"]["runs"]
    assert row["run"] == old.name and row["success at budget"] == pytest.approx(0.5)


def test_public80_trains_equirsac_and_equiobs_on_80_demos_and_1000_random_steps_two_seeds(tmp_path):
    cfg = LearningBenchConfig(out=tmp_path, protocol="public80")
    s = settings(cfg)
    assert (s.variants, s.budget, s.seeds, s.demos, s.random_steps) == (
        ("equirsac", "equiobs"),
        40_000,
        2,
        80,
        1_000,
    )
    assert learning.run_dir_of(cfg, "equiobs", 1) == tmp_path / "public80" / "block_pull-equiobs-s1"
    parsed = config.parse(RunConfig, RUN_PRESETS, run_args(cfg, "equirsac", 1, s), "mea run", "")
    expected = dataclasses.replace(
        RunConfig(), variant="equirsac", seed=1, env_steps=40_000, demos=80, random_steps=1_000,
        learner_preset="cpu-small", eval_every=2_500, run_dir=tmp_path / "public80" / "block_pull-equirsac-s1",
    )  # fmt: skip
    assert parsed == expected
    p15 = settings(LearningBenchConfig(out=tmp_path, protocol="public15"))
    assert (p15.variants, p15.budget, p15.seeds, p15.demos, p15.random_steps, p15.eval_every) == (
        ("equirsac", "equiobs", "mea"), 25_000, 3, 15, None, 2_500)  # fmt: skip
    assert settings(LearningBenchConfig(protocol="public15", variants=("equiobs",), seeds=5)).seeds == 5


def test_fixed_protocols_are_the_same_calibrations_on_the_public_start(tmp_path):
    for name in ("public15", "public80"):
        cfg, fixed_cfg = (LearningBenchConfig(out=tmp_path, protocol=p) for p in (name, f"{name}-fixed"))
        s, fixed = settings(cfg), settings(fixed_cfg)
        assert dataclasses.replace(fixed.protocol, gripper_start="random") == s.protocol
        plain = config.parse(RunConfig, RUN_PRESETS, run_args(cfg, "equiobs", 0, s), "mea run", "")
        ours = config.parse(RunConfig, RUN_PRESETS, run_args(fixed_cfg, "equiobs", 0, fixed), "mea run", "")
        assert (plain.gripper_start, ours.gripper_start) == ("random", "fixed")
        assert dataclasses.replace(ours, gripper_start="random", run_dir=plain.run_dir) == plain


def test_a_learner_preset_replaces_the_protocols_for_every_run_and_is_recorded(tmp_path):
    cfg = LearningBenchConfig(
        out=tmp_path, protocol="public15-fixed", variants=("equiobs",), learner_preset="paper"
    )
    s = settings(cfg)
    assert s.learner == "paper" and (s.demos, s.budget, s.gripper_start) == (15, 25_000, "fixed")
    parsed = config.parse(RunConfig, RUN_PRESETS, run_args(cfg, "equiobs", 0, s), "mea run", "")
    base = settings(dataclasses.replace(cfg, learner_preset=""))
    plain = config.parse(RunConfig, RUN_PRESETS, run_args(cfg, "equiobs", 0, base), "mea run", "")
    assert (plain.learner_preset, parsed.learner_preset) == ("cpu-small", "paper")
    assert dataclasses.replace(parsed, learner_preset="cpu-small") == plain  # nothing else changes


@pytest.mark.parametrize(
    ("options", "says"),
    [
        ({"protocol": "public99"}, "--protocol 'public99'.*public15"),
        ({"protocol": "public80", "task": "drawer_open"}, "block_pull protocol"),
        ({"protocol": "public15", "preset": "paper"}, "leave --preset at cpu-small"),
        ({"seeds": -1}, "--seeds must be >= 0"),
        ({"bootstrap_reps": 0}, "--bootstrap-reps must be >= 1"),
        ({"parallel": 0}, "--parallel must be >= 1, not 0"),
        ({"best_episodes": -1}, "--best-episodes must be >= 0"),
        ({"envs_per_actor": 0}, "--envs-per-actor must be >= 1, not 0"),
        ({"learner_device": "gpu"}, "--learner-device must be cpu, cuda or cuda:N, not 'gpu'"),
        ({"learner_threads": -1}, "--learner-threads must be >= 0 .*not -1"),
        ({"learner_preset": "gasv2-smoke"}, "--learner-preset 'gasv2-smoke' has no equirsac learner"),
        ({"task": "surgical_grasp_any", "learner_preset": "cpu-small-state"}, "has no gasv2 learner"),
    ],
)
def test_bad_options_are_refused_in_one_line_before_anything_is_written(tmp_path, options, says):
    out = tmp_path / "bench"
    with pytest.raises(SystemExit, match=says) as exc:
        run(LearningBenchConfig(out=out, **options))
    assert str(exc.value).startswith("mea bench learning: ") and "\n" not in str(exc.value)
    assert not out.exists()


def test_public15_prints_ours_beside_the_public_reproduction_at_each_5k(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(subprocess, "Popen", _no_training)
    out = tmp_path / "bench" / "public15"
    curves = {  # equiobs at 5K..25K per seed; the reference: .00 .27 .37 .53 .77
        0: [0.0, 0.3, 0.3, 0.6, 0.8],
        1: [0.0, 0.2, 0.4, 0.5, 0.8],
        2: [0.0, 0.4, 0.2, 0.6, 0.9],
    }
    for seed, values in curves.items():
        points = [(0, 0.0), *((5_000 * (i + 1) + 3, v) for i, v in enumerate(values))]  # 5,003, 10,003, ...
        make_run(out, "equiobs", seed, points, budget=25_000, demos=15)
        make_run(out, "mea", seed, points[:3], budget=25_000, demos=15)  # stopped at 10K: no later points
        make_run(out, "equirsac", seed, [(0, 0.0), (25_003, 0.5)], budget=25_000, demos=15)
    monkeypatch.setattr(
        learning, "train", lambda cfg, variant, seed, s: learning.run_dir_of(cfg, variant, seed)
    )
    result = run(
        LearningBenchConfig(out=tmp_path / "bench", protocol="public15", json=True, bootstrap_reps=REPS)
    )
    assert json.loads(capsys.readouterr().out)["meta"]["reference"].startswith("public reproduction")
    rows = {(r["variant"], r["env steps"]): r for r in result["results"]["against the public reference"]}
    assert [k[1] for k in rows if k[0] == "equiobs"] == [5_000, 10_000, 15_000, 20_000, 25_000]
    eq = {k[1]: r for k, r in rows.items() if k[0] == "equiobs"}
    assert [eq[s]["reference"] for s in sorted(eq)] == [0.0, 0.27, 0.37, 0.53, 0.77]
    assert [eq[s]["ours (mean)"] for s in sorted(eq)] == pytest.approx([0.0, 0.3, 0.3, 17 / 30, 2.5 / 3])
    assert [eq[s]["verdict"] for s in sorted(eq)] == [
        "at/above", "at/above", "below (reference inside the CI)", "at/above", "at/above"]  # fmt: skip
    lo, hi = eq[15_000]["ours (95% CI)"]
    assert lo <= 0.3 <= hi and hi >= 0.37
    # the reproduction's baseline saw the public code's depth image: equirsac is held to its curve
    rsac = {k[1]: r for k, r in rows.items() if k[0] == "equirsac"}
    assert [rsac[s]["reference"] for s in sorted(rsac)] == [0.0, 0.27, 0.37, 0.53, 0.77]
    assert rsac[25_000]["ours (mean)"] == pytest.approx(0.5) and rsac[25_000]["verdict"] == "below"
    mea = {k[1]: r for k, r in rows.items() if k[0] == "mea"}
    assert mea[10_000]["reference"] == 0.33 and mea[10_000]["verdict"] == "below (reference inside the CI)"
    assert mea[15_000]["verdict"] == "not reached" and mea[15_000]["seeds"] == 0
    assert (out / "result-block_pull.json").exists() and (out / "curves-block_pull.png").exists()
    far_below = run(LearningBenchConfig(out=tmp_path / "bench", protocol="public15", variants=("equiobs",),
                                        seeds=1, json=True, bootstrap_reps=REPS))  # fmt: skip
    one = {r["env steps"]: r["verdict"] for r in far_below["results"]["against the public reference"]}
    assert one[15_000] == "below"  # one seed at .3: its interval is [.3, .3]


def test_envs_per_actor_and_the_learner_device_reach_each_run_as_mea_run_reads_them(tmp_path):
    cfg = LearningBenchConfig(out=tmp_path, variants=("mea",), envs_per_actor=4, learner_device="cpu")
    parsed = config.parse(RunConfig, RUN_PRESETS, run_args(cfg, "mea", 2, settings(cfg)), "mea run", "")
    assert (parsed.envs_per_actor, parsed.learner_device, parsed.seed) == (4, "cpu", 2)


def test_a_gpu_this_machine_lacks_is_refused_before_anything_is_written(tmp_path):
    out = tmp_path / "bench"
    # no CUDA here: any cuda device; with CUDA: the index one past the last GPU
    device = f"cuda:{torch.cuda.device_count()}" if torch.cuda.is_available() else "cuda"
    with pytest.raises(SystemExit, match=f"--learner-device '{device}'") as exc:
        run(LearningBenchConfig(out=out, learner_device=device))
    assert "\n" not in str(exc.value)
    assert not out.exists()


def test_extra_mea_run_arguments_reach_every_new_run(tmp_path, monkeypatch):
    FakeProc.commands = []
    monkeypatch.setattr(subprocess, "Popen", FakeProc)
    cfg = LearningBenchConfig(out=tmp_path, variants=("equirsac", "equiobs"), seeds=2, json=True,
                              bootstrap_reps=REPS, extra=("--actors", "2"))  # fmt: skip
    run(cfg)
    assert len(FakeProc.commands) == 4
    seeds = {}
    for cmd in FakeProc.commands:
        args = cmd[cmd.index("run") + 1 :]
        assert args[args.index("--actors", args.index("--run-dir")) + 1] == "2"  # after the bench's own
        seeds.setdefault(args[args.index("--variant") + 1], []).append(int(args[args.index("--seed") + 1]))
    assert seeds == {"equirsac": [0, 1], "equiobs": [0, 1]}  # paired by seed


def test_each_extra_flag_adds_one_argument_none_is_dropped(tmp_path):
    argv = ["--out", str(tmp_path), "--extra=--success-rotations=4", "--extra=--learner-args=--batch-size 16"]
    cfg = config.cli(LearningBenchConfig, argv, "mea bench learning", "")
    assert cfg.extra == ("--success-rotations=4", "--learner-args=--batch-size 16")
    parsed = config.parse(RunConfig, RUN_PRESETS, run_args(cfg, "equiobs", 0, settings(cfg)), "mea run", "")
    assert (parsed.success_rotations, parsed.learner_args) == (4, "--batch-size 16")


def test_surgical_grasp_any_compares_gasv2_with_mea_gasv2_on_ten_demos(tmp_path):
    cfg = LearningBenchConfig(out=tmp_path, task="surgical_grasp_any")
    s = settings(cfg)
    assert s.variants == ("gasv2", "mea-gasv2") and s.demos == 10 and s.seeds == 3
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


def test_parallel_2_trains_two_runs_at_once_and_still_makes_the_comparison(tmp_path, monkeypatch):
    out = tmp_path / "bench"
    together = threading.Barrier(2, timeout=10)  # broken (an error) unless two runs are in flight at once
    spans: dict[str, tuple[float, float]] = {}

    def two_at_once(cfg, variant, seed, s):
        t0 = time.monotonic()
        together.wait()
        run_dir = make_run(out, variant, seed, [(0, 0.0), (BUDGET, 0.2 + 0.4 * (variant == "mea"))])
        spans[f"{variant}-{seed}"] = (t0, time.monotonic())
        return run_dir

    monkeypatch.setattr(learning, "train", two_at_once)
    cfg = LearningBenchConfig(out=out, variants=("equiobs", "mea"), seeds=2, json=True, bootstrap_reps=REPS,
                              parallel=2)  # fmt: skip
    result = run(cfg)
    assert sorted(spans) == ["equiobs-0", "equiobs-1", "mea-0", "mea-1"]
    # seed by seed across the arms: both seed-0 runs were in flight together, then both seed-1 runs
    (a0, a1), (b0, b1) = spans["equiobs-0"], spans["mea-0"]
    assert max(a0, b0) < min(a1, b1)
    rows = {r["variant"]: r for r in result["results"]["comparison"]}
    assert list(rows) == ["equiobs", "mea"] and {r["seeds at budget"] for r in rows.values()} == {2}
    assert rows["mea"]["success at budget (mean)"] == pytest.approx(0.6)
    assert [r["run"] for r in result["results"]["runs"]] == [
        "block_pull-equiobs-s0", "block_pull-equiobs-s1", "block_pull-mea-s0", "block_pull-mea-s1"]  # fmt: skip
    assert result["meta"]["parallel"] == 2
    assert (out / "curves-block_pull.png").read_bytes().startswith(PNG_MAGIC)


def test_runs_in_flight_never_share_a_listen_port(monkeypatch):
    offered = iter([7001, 7001, 7001, 7002, 7001])  # the OS may offer a port again before it is bound
    monkeypatch.setattr(learning, "free_port", lambda: next(offered))
    ports = learning.ListenPorts()
    with ports.hold() as first, ports.hold() as second:
        assert (first, second) == (7001, 7002)
    with ports.hold() as again:  # released: free for the next run
        assert again == 7001


def test_ctrl_c_ends_the_benchmark_in_one_line_with_status_130(tmp_path, monkeypatch, capsys):
    from mea_tools.bench import cli

    def interrupted(cfg):
        raise KeyboardInterrupt

    monkeypatch.setattr(learning, "run", interrupted)
    assert cli.main(["learning", "--out", str(tmp_path / "bench")]) == 130
    assert capsys.readouterr().err.strip() == "mea bench learning: interrupted"


WAITER = [sys.executable, "-c", "import signal; signal.pause()"]
"""A child that runs until a signal ends it, as a training run does."""


@pytest.fixture
def children(monkeypatch):
    """The processes the bench starts; any still alive at the end (a failed test) is killed."""
    started: list[subprocess.Popen] = []
    real = subprocess.Popen

    def popen(*args, **kwargs):
        started.append(real(*args, **kwargs))
        return started[-1]

    monkeypatch.setattr(subprocess, "Popen", popen)
    yield started
    for proc in started:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


class _Registry(set):
    """The bench's set of live runs, telling each registration (a readiness signal to wait on)."""

    def __init__(self) -> None:
        super().__init__()
        self.registered = threading.Semaphore(0)

    def add(self, proc) -> None:
        super().add(proc)
        self.registered.release()


def _signal_main(sig: int) -> None:
    """``sig`` to the main thread: a signal sent to the process may land on this one, and the main
    thread then sleeps on in its wait until something else wakes it."""
    signal.pthread_kill(threading.main_thread().ident, sig)


def _when_running(monkeypatch, n: int, then) -> threading.Thread:
    """A thread that calls ``then`` once ``n`` children are registered as running (or after 20 s each)."""
    registry = _Registry()
    monkeypatch.setattr(learning, "_LIVE", registry)

    def watch() -> None:
        for _ in range(n):
            registry.registered.acquire(timeout=20)
        then()

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


def test_an_interrupted_bench_stops_the_run_it_was_waiting_on(tmp_path, monkeypatch, children):
    interrupted = threading.Event()

    def ctrl_c(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGUSR1, ctrl_c)
    try:
        watcher = _when_running(monkeypatch, 1, lambda: (interrupted.set(), _signal_main(signal.SIGUSR1)))
        with open(tmp_path / "log", "w") as logf, pytest.raises(KeyboardInterrupt):
            learning.run_child(WAITER, logf, None, "run")
        watcher.join()
    finally:
        signal.signal(signal.SIGUSR1, previous)
    (proc,) = children
    assert interrupted.is_set() and proc.returncode is not None  # ended, not left running
    assert not learning._LIVE


def test_a_killed_parallel_bench_stops_every_run_in_flight(tmp_path, monkeypatch, children, capsys):
    from mea_tools.bench import cli

    def waiting_run(cfg, variant, seed, s):
        with open(tmp_path / f"{variant}.log", "w") as logf:
            return learning.run_child(WAITER, logf, None, variant)

    rescued = threading.Event()

    def rescue() -> None:  # a bench that does not stop its runs would wait on them for ever
        rescued.set()
        for proc in children:
            proc.kill()

    monkeypatch.setattr(learning, "train", waiting_run)
    killer = _when_running(monkeypatch, 2, lambda: _signal_main(signal.SIGTERM))
    rescuer = threading.Timer(60, rescue)
    rescuer.start()
    code = cli.main(["learning", "--out", str(tmp_path / "bench"), "--variants", "equiobs", "mea",
                     "--seeds", "1", "--parallel", "2", "--json"])  # fmt: skip
    rescuer.cancel()
    killer.join()
    assert not rescued.is_set() and code == 130 and "interrupted" in capsys.readouterr().err
    assert len(children) == 2 and all(p.returncode is not None for p in children)
    assert not learning._LIVE
    assert (
        signal.getsignal(signal.SIGTERM) is not cli._interrupt
    )  # the handler is the bench's only while it runs
