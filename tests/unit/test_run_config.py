"""`mea run` settings: variants reach every service, --resume reuses the run's settings, progress/ETA."""

from __future__ import annotations

import dataclasses
import json

import pytest

from proto.control import EvalReport, Heartbeat
from proto.seeds import EVAL_SEED_BASE
from services.common import config
from services.learner.config import PRESETS as LEARNER_PRESETS
from services.plan import ChildSpec, child_specs, config_for
from services.run_config import CPU_LEARNER_PRESETS, RunConfig, resumed_config
from services.status_board import StatusBoard


def augmenter_cfg(run: RunConfig, tmp_path):
    return config_for(run, tmp_path, "augmenter", 0)


def actor_cfg(run: RunConfig, tmp_path, index: int = 0):
    return config_for(run, tmp_path, "actor", index)


def learner_cfg(run: RunConfig, tmp_path):
    return config_for(run, tmp_path, "learner", 0)


def test_variants_configure_actor_augmenter_and_learner(tmp_path):
    mea = RunConfig(variant="mea")
    assert augmenter_cfg(mea, tmp_path).augment.mea_on == "successes"  # the CPU recipe's default
    assert augmenter_cfg(RunConfig(variant="mea", learner_preset="paper"), tmp_path).augment.mea_on == "demos"
    assert augmenter_cfg(RunConfig(variant="mea", mea_on="demos"), tmp_path).augment.mea_on == "demos"
    assert augmenter_cfg(RunConfig(variant="mea", mea_on="all"), tmp_path).augment.mea_on == "all"
    assert augmenter_cfg(RunConfig(variant="equiobs"), tmp_path).augment.mea_on == "none"
    rsac = RunConfig(variant="equirsac")
    assert augmenter_cfg(rsac, tmp_path).augment.observation == "depth"
    assert augmenter_cfg(rsac, tmp_path).augment.mea_on == "none"
    assert augmenter_cfg(mea, tmp_path).augment.observation == "voxel"
    assert actor_cfg(rsac, tmp_path).depth_image and not actor_cfg(mea, tmp_path).depth_image
    assert (
        learner_cfg(rsac, tmp_path).algorithm.observation == "depth"
        and learner_cfg(mea, tmp_path).algorithm.observation == "voxel"
    )
    assert learner_cfg(RunConfig(task="block_pick"), tmp_path).algorithm.net.group == "d4"
    assert learner_cfg(RunConfig(task="block_pull"), tmp_path).algorithm.net.group == "c4"
    # rotated copies of each success: the CPU recipe's 64 in every variant, the paper's count otherwise
    for run, count in [(mea, 64), (rsac, 64), (RunConfig(learner_preset="paper"), 0),
                       (RunConfig(success_rotations=8), 8), (RunConfig(learner_preset="cpu-small-state"), 64)]:  # fmt: skip
        assert augmenter_cfg(run, tmp_path).augment.success_isometric_copies == count
    with pytest.raises(ValueError, match="success_rotations"):
        RunConfig(success_rotations=-1)
    # the launcher's CPU recipes are learner presets, and each gets the CPU defaults
    assert set(CPU_LEARNER_PRESETS) <= set(LEARNER_PRESETS)
    for name in CPU_LEARNER_PRESETS:
        assert RunConfig(learner_preset=name).resolved_mea_on() == "successes"
    assert RunConfig(learner_preset="paper").resolved_mea_on() == "demos"
    critic_input = {
        k: LEARNER_PRESETS[k].algorithm.net.critic_input for k in ("cpu-small-state", "cpu-small", "paper")
    }
    assert critic_input == {"cpu-small-state": "state", "cpu-small": "image", "paper": "image"}
    with pytest.raises(ValueError, match="mea-on"):
        RunConfig(variant="equiobs", mea_on="all")
    with pytest.raises(ValueError, match="variant"):
        RunConfig(variant="nope")


def test_the_plan_derives_every_service_config_from_the_run_and_its_learner_preset(tmp_path):
    run = RunConfig(task="drawer_open", learner_preset="cpu-small", seed=2, env_steps=3000, actors=2,
                    eval_every=500, eval_episodes=7, final_eval_episodes=11, metrics_port=0)  # fmt: skip
    specs, missing = child_specs(run, tmp_path, available=lambda s: s != "evaluator")
    assert missing == ["evaluator"]
    assert [s.instance for s in specs] == ["learner-0", "augmenter-0", "actor-0", "actor-1"]
    assert all(s.entry.endswith(":run") and s.config.service.instance_id == s.instance for s in specs)
    assert all(
        s.config.service.metrics_port == 0 and s.config.service.zenoh.connect == (run.listen,) for s in specs
    )
    learner = specs[0].config
    preset = LEARNER_PRESETS["cpu-small"]
    # the preset's own fields survive; the run sets only group, observation, budget, seed, threads, dir
    assert (learner.batch_size, learner.demo_fraction, learner.algorithm.sac) == (
        preset.batch_size,
        preset.demo_fraction,
        preset.algorithm.sac,
    )
    assert (learner.algorithm.net.group, learner.max_env_steps) == ("d4", 3000)
    assert (learner.seed, learner.threads) == (2, 1)
    assert learner.run_dir == tmp_path / "learner" and not learner.resume
    a0, a1 = specs[2].config, specs[3].config
    assert (a0.demos, a1.demos) == (run.resolved_demos(), 0) and (a0.index, a1.index) == (0, 1)
    assert a0.policy == "learned" and a0.task == "drawer_open" and a0.seed_base == a1.seed_base
    ev = config_for(run, tmp_path, "evaluator", 0)
    assert (ev.task, ev.every_env_steps, ev.episodes, ev.final_env_steps, ev.final_episodes) == (
        "drawer_open", 500, 7, 3000, 11)  # fmt: skip
    assert ev.run_dir == tmp_path and ev.seed_base == EVAL_SEED_BASE
    # without a learner, actors act at random
    assert actor_cfg(RunConfig(services=("actor",)), tmp_path).policy == "random"
    with pytest.raises(ValueError, match="unknown service"):
        config_for(run, tmp_path, "nope", 0)


def test_resume_reuses_the_saved_settings_with_new_seeds_and_no_demos(tmp_path):
    first = RunConfig(task="drawer_open", variant="equiobs", seed=3, demos=2, env_steps=5000, run_dir=tmp_path,
                      listen="tcp/127.0.0.1:1111")  # fmt: skip
    config.save(first, tmp_path / "config.json")
    cli = RunConfig(resume=tmp_path, listen="tcp/127.0.0.1:2222", duration_seconds=9.0, task="block_pull")
    cfg = resumed_config(cli)
    assert (cfg.task, cfg.variant, cfg.seed, cfg.env_steps) == ("drawer_open", "equiobs", 3, 5000)
    assert cfg.listen == "tcp/127.0.0.1:2222" and cfg.duration_seconds == 9.0  # this machine's
    assert cfg.resumes == 1 and cfg.run_dir == tmp_path and cfg.resume == tmp_path
    a0, a1 = actor_cfg(first, tmp_path), actor_cfg(cfg, tmp_path)
    assert a0.demos == 2 and a1.demos == 0
    assert a0.seed_base != a1.seed_base
    assert learner_cfg(cfg, tmp_path).resume and not learner_cfg(first, tmp_path).resume
    config.save(cfg, tmp_path / "config.json")
    assert resumed_config(dataclasses.replace(cli)).resumes == 2
    with pytest.raises(ValueError, match="no such run directory"):
        resumed_config(RunConfig(resume=tmp_path / "missing"))


def test_recording_limits_default_to_256_mib_or_an_hour_keep_everything_and_are_saved(tmp_path):
    d = RunConfig()
    assert (d.recording_segment_bytes, d.recording_segment_seconds, d.recording_max_bytes) == (
        2**28,
        3600.0,
        0,
    )
    for field in ("recording_segment_bytes", "recording_segment_seconds", "recording_max_bytes"):
        with pytest.raises(ValueError, match="recording"):
            RunConfig(**{field: -1})
    first = RunConfig(run_dir=tmp_path, recording_segment_bytes=1000, recording_max_bytes=5000)
    config.save(first, tmp_path / "config.json")
    saved = json.loads((tmp_path / "config.json").read_text())
    assert (saved["recording_segment_bytes"], saved["recording_max_bytes"]) == (1000, 5000)
    cfg = resumed_config(RunConfig(resume=tmp_path))  # saved with the run, like its other settings
    assert (cfg.recording_segment_bytes, cfg.recording_segment_seconds, cfg.recording_max_bytes) == (
        1000,
        3600.0,
        5000,
    )
    for k in ("recording_segment_bytes", "recording_segment_seconds", "recording_max_bytes"):
        del saved[k]  # a run saved before these settings: the defaults
    (tmp_path / "config.json").write_text(json.dumps(saved))
    assert resumed_config(RunConfig(resume=tmp_path)).recording_segment_bytes == 2**28


def test_evaluation_defaults_20_episodes_every_1000_env_steps_and_50_at_the_budget(tmp_path):
    from services.run_config import PRESETS

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
        ChildSpec("learner", "learner-0", "x:run"),
        ChildSpec("augmenter", "augmenter-0", "x:run"),
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


def test_metrics_ports_follow_the_runs_port_base_so_two_runs_share_a_host(tmp_path):
    from services.common.metrics import DEFAULT_PORTS

    def ports(run: RunConfig) -> dict[str, int]:
        specs, _ = child_specs(run, tmp_path)
        return {s.instance: s.config.service.metrics_port for s in specs}

    default = ports(RunConfig(actors=3))
    # the default base is the documented default layout
    assert default == {"learner-0": DEFAULT_PORTS["learner"], "augmenter-0": DEFAULT_PORTS["augmenter"],
                       "evaluator-0": DEFAULT_PORTS["evaluator"], "actor-0": DEFAULT_PORTS["actor"],
                       "actor-1": DEFAULT_PORTS["actor"] + 1, "actor-2": DEFAULT_PORTS["actor"] + 2}  # fmt: skip
    other = ports(RunConfig(actors=3, metrics_port=9200))
    assert other == {k: v + 100 for k, v in default.items()}
    for run_ports, base in ((default, 9100), (other, 9200)):
        assert len(set(run_ports.values())) == len(run_ports) and base not in run_ports.values()
    assert not set(default.values()) & set(other.values())
    assert set(ports(RunConfig(actors=3, metrics_port=0)).values()) == {0}


def test_a_restarted_instance_repeats_no_demo_or_seed_and_a_learner_resumes(tmp_path):
    from proto.seeds import RESTART_SEED_STRIDE
    from services.plan import restarted

    specs, _ = child_specs(RunConfig(demos=2, actors=2), tmp_path)
    by = {s.instance: s for s in specs}
    a0 = by["actor-0"]
    again = restarted(a0, 1).config
    assert a0.config.demos == 2 and again.demos == 0 and again.incarnation == 1
    assert again.first_seed() == a0.config.first_seed() + RESTART_SEED_STRIDE
    # restarted actors' seed streams stay apart from each other and from the other actors'
    firsts = [restarted(s, n).config.first_seed() for s in (a0, by["actor-1"]) for n in range(10)]
    assert len(set(firsts)) == 20 and max(firsts) - min(firsts) < 2_000_000
    assert not by["learner-0"].config.resume and restarted(by["learner-0"], 1).config.resume
    assert restarted(by["augmenter-0"], 3) == by["augmenter-0"]


def test_surgical_runs_take_the_gasv2_variants_and_learner(tmp_path):
    with pytest.raises(ValueError, match="does not run on surgical_grasp_any"):
        RunConfig(task="surgical_grasp_any", variant="mea")
    with pytest.raises(ValueError, match="does not run on block_pull"):
        RunConfig(task="block_pull", variant="mea-gasv2")
    run = RunConfig(task="surgical_grasp_any", variant="mea-gasv2", run_dir=tmp_path)
    assert run.resolved_demos() == 10 and RunConfig().resolved_demos() == 2
    specs, _ = child_specs(run, tmp_path)
    by = {s.service: s.config for s in specs}
    learner, augmenter, actor = by["learner"], by["augmenter"], by["actor"]
    assert learner == dataclasses.replace(LEARNER_PRESETS["gasv2-cpu-small"], threads=1, max_env_steps=run.env_steps,
                                          seed=0, run_dir=tmp_path / "learner", tensorboard_dir=tmp_path / "tb", resume=False,
                                          service=learner.service)  # fmt: skip
    assert (
        augmenter.augment.mea_on == "successes" and actor.demos == 10 and actor.task == "surgical_grasp_any"
    )
    paper = config_for(
        dataclasses.replace(run, learner_preset="paper", variant="gasv2"), tmp_path, "learner", 0
    )
    assert (
        paper.algorithm.name == "gasv2" and paper.batch_size == 100 and paper.algorithm.dreamer.deter == 1024
    )
    plain = config_for(dataclasses.replace(run, variant="gasv2"), tmp_path, "augmenter", 0)
    assert plain.augment.mea_on == "none"
    with pytest.raises(
        ValueError, match="learner-preset must be one of paper, cpu-small, smoke with --variant mea-gasv2"
    ):
        dataclasses.replace(run, learner_preset="cpu-small-state")


def test_a_run_that_connects_to_another_hosts_router_runs_learned_actors_and_binds_metrics_where_told(
    tmp_path,
):
    alone = RunConfig(task="block_pull", services=("actor",))
    assert actor_cfg(alone, tmp_path).policy == "random"  # no learner anywhere: nothing to follow
    remote = dataclasses.replace(alone, connect=("tcp/10.0.0.5:7447",), metrics_addr="0.0.0.0")
    cfg = actor_cfg(remote, tmp_path)
    assert cfg.policy == "learned" and cfg.service.metrics_addr == "0.0.0.0"
    assert cfg.service.zenoh.connect == (remote.listen,)  # services still join the run's own router


def test_the_demos_expert_reaches_the_actor_that_records_them_and_a_bad_one_is_refused(tmp_path):
    for expert in ("observable", "privileged"):
        run = RunConfig(task="block_pull", expert=expert, metrics_port=0)
        assert config_for(run, tmp_path, "actor", 0).expert == expert
    assert RunConfig().expert == "observable"  # the demonstrations a policy can imitate, by default
    with pytest.raises(ValueError, match=r"^--expert must be one of observable, privileged, not 'planner'$"):
        RunConfig(expert="planner")


def test_the_gripper_start_reaches_every_env_of_the_run_and_is_refused_where_it_means_nothing(tmp_path):
    for start in ("random", "fixed"):
        run = RunConfig(task="block_pull", gripper_start=start, metrics_port=0)
        for service in ("actor", "evaluator"):
            cfg = config_for(run, tmp_path, service, 0)
            assert cfg.gripper_start == start and cfg.env_settings().gripper_start == start
    with pytest.raises(ValueError, match="gripper_start must be one of"):
        RunConfig(gripper_start="centre")
    with pytest.raises(ValueError, match="for the manipulation tasks"):
        RunConfig(task="surgical_grasp_any", variant="gasv2", gripper_start="fixed")
