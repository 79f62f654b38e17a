"""`mea run --resume` on a real (smoke, in-process) run: a finished run says so and is left as it
was, a changed --task is refused by name, a larger --env-steps trains on to the new budget (learner,
status and final evaluation), no evaluation is recorded at env steps -1, summary.json adds the
sittings up, and each sitting ends with the printed summary."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.evaluator.history import read_history
from tests.helpers.cli import run_cli
from tests.helpers.tree import snapshot

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
MACHINE = ["--metrics-port", "0", "--final-eval-seconds", "120", "--log-format", "text", "--in-process"]


def mea_run(*args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "services.cli", "run", *args, *MACHINE]
    out = subprocess.run(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True,
                         text=True, timeout=300)  # fmt: skip
    assert out.returncode == 0, (out.stdout + out.stderr)[-4000:]
    return out


@pytest.mark.timeout(600)
def test_resume_a_finished_run_refuse_a_changed_task_then_extend_its_budget(tmp_path, capsys):
    run = tmp_path / "run"
    first = mea_run("--task", "block_pull", "--demos", "1", "--env-steps", "100", "--eval-every", "1000",
                    "--eval-episodes", "1", "--final-eval-episodes", "2", "--learner-preset", "smoke",
                    "--run-dir", str(run))  # fmt: skip
    summary_lines = first.stdout.splitlines()
    assert summary_lines[0] == f"mea run: stopped (env-step budget reached). Summary of {run}:", first.stdout
    assert summary_lines[1].split()[:2] == ["final", "success"] and "95% CI" in summary_lines[1]
    assert f"mea serve --weights {run}" in first.stdout and str(run / "curves.png") in first.stdout

    # finished: said so, exit 0, nothing trained, evaluated or written
    before = snapshot(run)
    code, out, err = run_cli(["run", "--resume", str(run), *MACHINE], capsys)
    assert code == 0 and out.startswith(f"mea run: {run} is finished: ") and err == "", (out, err)
    # a changed task is refused by name, and the run is left as it was
    code, out, err = run_cli(["run", "--resume", str(run), "--task", "drawer_open", *MACHINE], capsys)
    assert code == 2 and err.startswith("mea run: --task cannot change on --resume") and out == "", err
    assert snapshot(run) == before

    # a larger budget trains on to it
    second = mea_run("--resume", str(run), "--env-steps", "200")
    saved = json.loads((run / "config.json").read_text())
    assert saved["env_steps"] == 200 and saved["resumes"] == 1
    assert saved["history"] == [{"resume": 1, "changed": {"env_steps": [100, 200]}}]
    learner = json.loads((run / "services" / "learner-0.json").read_text())
    assert learner["max_env_steps"] == 200 and learner["resume"] is True
    assert "/200" in second.stderr  # the status line counts to the new budget
    history = read_history(run / "eval" / "history.jsonl")
    assert all(r["env_steps"] >= 0 for r in history), [r["env_steps"] for r in history]
    at_budget = [r["env_steps"] for r in history if r["at_budget"]]
    assert len(at_budget) == 2 and 100 <= at_budget[0] < 200 <= at_budget[1], at_budget
    summary = json.loads((run / "summary.json").read_text())
    one, two = summary["sittings"]
    assert (one["sitting"], two["sitting"], summary["sitting"]) == (0, 1, 1)
    total = summary["total"]
    assert total["sittings"] == 2 and total["env_steps"] >= 200 > one["env_steps"] >= 100
    assert total["episodes_recorded"] == one["episodes_recorded"] + two["episodes_recorded"] > 2
    assert total["evaluations"] == one["evaluations"] + two["evaluations"] >= 2
    assert total["elapsed_seconds"] == pytest.approx(one["elapsed_seconds"] + two["elapsed_seconds"], abs=0.2)
    assert "over 2 sittings" in second.stdout and f"at {at_budget[1]:,} env steps" in second.stdout
