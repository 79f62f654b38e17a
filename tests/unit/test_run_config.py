"""`mea run` settings: variants reach every service, --resume reuses the run's settings, progress/ETA."""

from __future__ import annotations

import dataclasses
import json

import pytest

from proto.control import EvalReport, Heartbeat
from services.actor.main import launch_args as actor_args
from services.augmenter.main import launch_args as augmenter_args
from services.common import config
from services.launcher import CPU_LEARNER_PRESETS, ChildSpec, RunConfig, StatusBoard, resumed_config
from services.learner.config import PRESETS as LEARNER_PRESETS
from services.learner.main import launch_args as learner_args


def test_variants_configure_actor_augmenter_and_learner(tmp_path):
    mea = RunConfig(variant="mea")
    assert "--augment.mea-on" in augmenter_args(mea, tmp_path, 0)
    assert augmenter_args(mea, tmp_path, 0)[-1] == "successes"  # the CPU recipe's default
    assert augmenter_args(RunConfig(variant="mea", learner_preset="paper"), tmp_path, 0)[-1] == "demos"
    assert augmenter_args(RunConfig(variant="mea", mea_on="demos"), tmp_path, 0)[-1] == "demos"
    assert augmenter_args(RunConfig(variant="mea", mea_on="all"), tmp_path, 0)[-1] == "all"
    assert augmenter_args(RunConfig(variant="equiobs"), tmp_path, 0)[-1] == "none"
    rsac = RunConfig(variant="equirsac")
    assert augmenter_args(rsac, tmp_path, 0)[-2:] == ["--augment.observation", "depth"]
    assert "--depth-image" in actor_args(rsac, tmp_path, 0) and "--depth-image" not in actor_args(
        mea, tmp_path, 0
    )
    ln = learner_args(rsac, tmp_path, 0)
    assert ln[ln.index("--observation") + 1] == "depth"
    assert learner_args(RunConfig(task="block_pick"), tmp_path, 0)[3] == "d4"
    assert learner_args(RunConfig(task="block_pull"), tmp_path, 0)[3] == "c4"
    # rotated copies of each success: the CPU recipe's 64 in every variant, the paper's count otherwise
    for run, count in [(mea, "64"), (rsac, "64"), (RunConfig(learner_preset="paper"), "0"),
                       (RunConfig(success_rotations=8), "8"), (RunConfig(learner_preset="cpu-small-state"), "64")]:  # fmt: skip
        args = augmenter_args(run, tmp_path, 0)
        assert args[args.index("--augment.success-isometric-copies") + 1] == count
    with pytest.raises(ValueError, match="success_rotations"):
        RunConfig(success_rotations=-1)
    # the launcher's CPU recipes are learner presets, and each gets the CPU defaults
    assert set(CPU_LEARNER_PRESETS) <= set(LEARNER_PRESETS)
    for name in CPU_LEARNER_PRESETS:
        assert RunConfig(learner_preset=name).resolved_mea_on() == "successes"
    assert RunConfig(learner_preset="paper").resolved_mea_on() == "demos"
    assert LEARNER_PRESETS["cpu-small-state"].net.critic_input == "state"
    assert (
        LEARNER_PRESETS["cpu-small"].net.critic_input == LEARNER_PRESETS["paper"].net.critic_input == "image"
    )
    with pytest.raises(ValueError, match="mea-on"):
        RunConfig(variant="equiobs", mea_on="all")
    with pytest.raises(ValueError, match="variant"):
        RunConfig(variant="nope")


def test_resume_reuses_the_saved_settings_with_new_seeds_and_no_demos(tmp_path):
    first = RunConfig(task="drawer_open", variant="equiobs", seed=3, demos=2, env_steps=5000, run_dir=tmp_path,
                      listen="tcp/127.0.0.1:1111")  # fmt: skip
    config.save(first, tmp_path / "config.json")
    cli = RunConfig(resume=tmp_path, listen="tcp/127.0.0.1:2222", duration_seconds=9.0, task="block_pull")
    cfg = resumed_config(cli)
    assert (cfg.task, cfg.variant, cfg.seed, cfg.env_steps) == ("drawer_open", "equiobs", 3, 5000)
    assert cfg.listen == "tcp/127.0.0.1:2222" and cfg.duration_seconds == 9.0  # this machine's
    assert cfg.resumes == 1 and cfg.run_dir == tmp_path and cfg.resume == tmp_path
    args0, args1 = actor_args(first, tmp_path, 0), actor_args(cfg, tmp_path, 0)
    assert "--demos" in args0 and "--demos" not in args1
    assert args0[args0.index("--seed-base") + 1] != args1[args1.index("--seed-base") + 1]
    assert "--resume" in learner_args(cfg, tmp_path, 0) and "--resume" not in learner_args(first, tmp_path, 0)
    config.save(cfg, tmp_path / "config.json")
    assert resumed_config(dataclasses.replace(cli)).resumes == 2
    with pytest.raises(SystemExit, match="config.json"):
        resumed_config(RunConfig(resume=tmp_path / "missing"))


def test_evaluation_defaults_20_episodes_every_1000_env_steps_and_50_at_the_budget(tmp_path):
    from services.launcher import PRESETS

    d = RunConfig()
    assert (d.eval_every, d.eval_episodes, d.final_eval_episodes, d.env_steps) == (1000, 20, 50, 40_000)
    assert d.final_eval_seconds >= 600  # 50 episodes on a loaded CPU need the time
    cfg = config.parse(
        RunConfig, PRESETS, ["--eval-episodes", "25", "--final-eval-episodes", "60"], "mea run", ""
    )
    assert (cfg.eval_episodes, cfg.final_eval_episodes) == (25, 60)
    for bad in ({"final_eval_episodes": 0}, {"eval_episodes": 0}):
        with pytest.raises(ValueError, match="final_eval_episodes"):
            RunConfig(**bad)
    # a resumed run keeps its evaluation sizes; one saved before --final-eval-episodes existed gets 50
    config.save(
        RunConfig(eval_episodes=30, final_eval_episodes=70, run_dir=tmp_path), tmp_path / "config.json"
    )
    assert resumed_config(RunConfig(resume=tmp_path)).final_eval_episodes == 70
    old = json.loads((tmp_path / "config.json").read_text())
    del old["final_eval_episodes"]
    (tmp_path / "config.json").write_text(json.dumps(old))
    resumed = resumed_config(RunConfig(resume=tmp_path, final_eval_episodes=5))
    assert (resumed.eval_episodes, resumed.final_eval_episodes) == (30, 50)


def beat(service: str, instance: str, t: float, **counters: float) -> Heartbeat:
    return Heartbeat(service=service, instance_id=instance, pid=1, state="running", started_at=0.0, created_at=t,
                     policy_version=1, counters=counters)  # fmt: skip


def test_progress_line_counts_and_eta():
    specs = [
        ChildSpec("learner", "learner-0", "x:main", ()),
        ChildSpec("augmenter", "augmenter-0", "x:main", ()),
    ]
    board = StatusBoard(specs, budget=1000)
    board.update(beat("learner", "learner-0", 1.0, env_steps=100, updates=20, version=4))
    board.update(beat("augmenter", "augmenter-0", 1.0, transitions_out=1100))
    assert board.progress(started=0.0, now=10.0)["eta"] is None  # one sample: no rate yet
    board.update(beat("learner", "learner-0", 2.0, env_steps=200, updates=40, version=8))
    p = board.progress(started=0.0, now=20.0)  # 100 steps in 10 s -> 800 left at 10/s
    assert p["env_steps"] == 200 and p["updates"] == 40 and p["version"] == 8 and p["augmented"] == 1100
    assert p["eta"] == pytest.approx(80.0)
    board.add_report(EvalReport(evaluator_id="evaluator-0", run_id="r", task="block_pull", policy_version=8,
                                env_steps=200, episodes=10, success_rate=0.3, mean_return=0.3, mean_length=40.0,
                                grasp_score=0.1, created_at=1.0))  # fmt: skip
    line = board.progress_line(started=0.0)
    assert "200/1,000" in line and "30%" in line and "v8" in line
