"""`mea run --resume RUN`: the saved settings go on; the budget, evaluation cadence, actor count and
final-evaluation size may change (recorded in config.json's history), anything else is refused by
name; a finished run says so and does nothing; summary.json keeps every sitting and their totals."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from services.cli import main
from services.common import config
from services.evaluator.config import EvaluatorConfig
from services.evaluator.history import append_history
from services.launcher import given_fields, prepare
from services.plan import ChildSpec, config_for
from services.run_config import RESUMABLE, RunConfig, read_resume
from services.status_board import StatusBoard, reached_env_steps, totals
from services.tasks import DEPTH_IMAGE_REVISION
from tests.helpers.tree import snapshot


def saved_run(run_dir: Path, **kw) -> Path:
    config.save(RunConfig(run_dir=run_dir, **kw), run_dir / "config.json")
    return run_dir


def finish(run_dir: Path, env_steps: int, at: int) -> None:
    """The files a run that reached ``env_steps`` and was evaluated at ``at`` leaves behind."""
    (run_dir / "summary.json").write_text(json.dumps({"total": {"env_steps": env_steps}, "sittings": []}))
    append_history(run_dir / "eval" / "history.jsonl", {"version": 3, "env_steps": at, "success_rate": 0.5,
                                                        "episodes": 2, "successes": [True, False], "at_budget": True})  # fmt: skip


def test_changeable_options_are_taken_and_recorded_in_the_history(tmp_path):
    run = saved_run(tmp_path, task="drawer_open", env_steps=300, eval_every=100, actors=1, seed=4)
    cli = RunConfig(resume=run, env_steps=600, eval_every=200, actors=2, final_eval_episodes=50,
                    listen="tcp/127.0.0.1:1234")  # fmt: skip
    r = read_resume(cli, given={"env_steps", "eval_every", "actors", "final_eval_episodes", "listen"})
    c = r.config
    assert (c.task, c.seed, c.env_steps, c.eval_every, c.actors, c.resumes) == (
        "drawer_open",
        4,
        600,
        200,
        2,
        1,
    )
    assert c.listen == "tcp/127.0.0.1:1234"
    # final_eval_episodes was given with its saved value: not a change
    assert r.history == ({"resume": 1, "changed": {"env_steps": [300, 600], "eval_every": [100, 200],
                                                    "actors": [1, 2]}},)  # fmt: skip
    # options not given keep the saved settings even when the command line's defaults differ
    assert read_resume(RunConfig(resume=run), given=set()).config.env_steps == 300
    # the next resume appends to the history config.json carries
    config.save({**config.to_jsonable(c), "history": list(r.history)}, run / "config.json")
    again = read_resume(RunConfig(resume=run, env_steps=900), given={"env_steps"})
    assert again.config.resumes == 2
    assert again.history == (*r.history, {"resume": 2, "changed": {"env_steps": [600, 900]}})


@pytest.mark.parametrize(
    ("given", "names"),
    [
        ({"task"}, "--task"),
        ({"seed", "learner_preset"}, "--learner-preset, --seed"),
        ({"run_dir"}, "--run-dir"),
        ({"demos", "env_steps"}, "--demos"),
        ({"record"}, "--record"),
    ],  # fmt: skip
)
def test_any_other_option_with_resume_is_refused_by_name(tmp_path, given, names):
    run = saved_run(tmp_path)
    with pytest.raises(ValueError, match=f"^{names} cannot change on --resume") as refused:
        read_resume(RunConfig(resume=run), given=given)
    for option in RESUMABLE:
        assert f"--{option.replace('_', '-')}" in str(refused.value)  # says what may change


def test_the_run_settings_named_on_a_command_line():
    argv = ["--env-steps", "5", "--no-record", "--eval-every=3", "x", "--resume", "r", "--bogus", "-h"]
    assert given_fields(argv) == {"env_steps", "record", "eval_every", "resume"}


def test_a_finished_run_says_so_and_a_larger_budget_trains_on(tmp_path):
    run = saved_run(tmp_path / "run", env_steps=300, learner_preset="smoke", metrics_port=0)
    assert not prepare(RunConfig(resume=run)).finished  # nothing reached yet
    finish(run, env_steps=320, at=310)
    assert reached_env_steps(run) == 320
    done = prepare(RunConfig(resume=run))
    assert done.finished.startswith(
        f"{run} is finished: 320 env steps of its 300-step budget, evaluated at 310"
    )
    on = prepare(RunConfig(resume=run, env_steps=600), given={"env_steps"})
    assert not on.finished and on.cfg.env_steps == 600
    learner = next(s.config for s in on.specs if s.service == "learner")
    evaluator = next(s.config for s in on.specs if s.service == "evaluator")
    assert learner.max_env_steps == 600 and learner.resume and evaluator.final_env_steps == 600
    # the evaluator waits for the learner's first gate: never an evaluation at env steps -1
    assert evaluator.first_gate_wait == math.inf
    alone = config_for(RunConfig(services=("evaluator", "actor")), tmp_path, "evaluator", 0)
    assert (
        alone.first_gate_wait == EvaluatorConfig.first_gate_wait < math.inf
    )  # no learner, no gate to wait for
    assert on.history[-1] == {"resume": 1, "changed": {"env_steps": [300, 600]}}
    # a budget already passed is finished too
    assert prepare(RunConfig(resume=run, env_steps=200), given={"env_steps"}).finished


def test_steps_at_the_budget_without_its_evaluation_are_not_finished(tmp_path):
    run = saved_run(tmp_path / "run", env_steps=300, learner_preset="smoke")
    (run / "summary.json").write_text(json.dumps({"total": {"env_steps": 320}}))
    assert not prepare(RunConfig(resume=run)).finished  # the final evaluation is still to come
    no_evaluator = saved_run(tmp_path / "plain", env_steps=300, services=("learner", "augmenter", "actor"))
    (no_evaluator / "summary.json").write_text(json.dumps({"total": {"env_steps": 320}}))
    assert prepare(RunConfig(resume=no_evaluator)).finished


def test_resuming_a_finished_run_exits_0_without_touching_it(tmp_path, monkeypatch, capsys):
    import services.launcher

    def would_start(*_a, **_kw):
        raise AssertionError("a finished run was started again")

    monkeypatch.setattr(services.launcher, "run", would_start)
    run = saved_run(tmp_path / "run", env_steps=300, learner_preset="smoke")
    finish(run, env_steps=320, at=310)
    before = snapshot(tmp_path)
    assert main(["run", "--resume", str(run), "--metrics-port", "0"]) == 0
    out = capsys.readouterr()
    assert out.out.startswith(f"mea run: {run} is finished: 320 env steps") and out.err == ""
    assert snapshot(tmp_path) == before


def test_a_depth_image_run_of_another_image_revision_is_refused_without_touching_it(tmp_path, capsys):
    """An equirsac run saved before the depth image drew the floor (no revision in its config.json)
    would fill one replay with two observations: refused in one line, nothing written. Runs on the
    voxel image go on; a run saved with this revision resumes."""
    old = saved_run(tmp_path / "old", variant="equirsac", env_steps=300, learner_preset="smoke")
    before = snapshot(tmp_path)
    with pytest.raises(SystemExit) as refused:
        main(["run", "--resume", str(old), "--metrics-port", "0"])
    assert refused.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"mea run: --resume {old}: its depth images are of revision 1, this version renders revision "
        f"{DEPTH_IMAGE_REVISION} (the floor drawn): its replay would mix two observations; start a new run"
    ], err
    assert snapshot(tmp_path) == before
    voxel = saved_run(tmp_path / "voxel", variant="mea", env_steps=300)
    assert read_resume(RunConfig(resume=voxel)).config.variant == "mea"
    new = tmp_path / "new"
    config.save({**config.to_jsonable(RunConfig(run_dir=new, variant="equirsac")),
                 "depth_image_revision": DEPTH_IMAGE_REVISION}, new / "config.json")  # fmt: skip
    assert read_resume(RunConfig(resume=new)).config.variant == "equirsac"


def board(env_steps: float, updates: float, episodes: int) -> StatusBoard:
    from proto.control import Heartbeat

    b = StatusBoard([ChildSpec("learner", "learner-0", "x:run")])
    b.update(Heartbeat(service="learner", instance_id="learner-0", pid=1, state="running", started_at=0.0,
                       created_at=1.0, policy_version=1, counters={"env_steps": env_steps, "updates": updates}))  # fmt: skip
    b.reports = episodes // 2
    return b


def test_summary_json_keeps_every_sitting_and_their_totals(tmp_path):
    path = tmp_path / "summary.json"
    # a summary written before sittings were kept counts as the sitting before
    path.write_text(
        json.dumps({"elapsed_seconds": 10.0, "evaluations": 1, "episodes_recorded": 3, "instances": {}})
    )
    first = board(100, 20, 4)
    first.started -= 60
    s1 = first.save_summary(path, episodes_recorded=4, sitting=1)
    assert [s["sitting"] for s in s1["sittings"]] == [0, 1]
    second = board(250, 55, 6)
    second.started -= 30
    s2 = second.save_summary(path, episodes_recorded=6, sitting=2)
    assert json.loads(path.read_text()) == s2
    assert (s2["sitting"], s2["env_steps"], s2["updates"], s2["episodes_recorded"]) == (
        2,
        250,
        55,
        6,
    )  # this sitting
    assert [s["sitting"] for s in s2["sittings"]] == [0, 1, 2]
    total = s2["total"]
    assert (total["sittings"], total["evaluations"], total["episodes_recorded"]) == (3, 1 + 2 + 3, 3 + 4 + 6)
    assert total["env_steps"] == 250 and total["updates"] == 55  # the learner's own running counts
    assert total["elapsed_seconds"] == pytest.approx(10 + 60 + 30, abs=1.0)
    assert reached_env_steps(tmp_path) == 250
    assert totals([]) == {"sittings": 0, "elapsed_seconds": None, "evaluations": None, "episodes_recorded": None,
                          "env_steps": None, "updates": None}  # fmt: skip
