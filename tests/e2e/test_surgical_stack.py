"""`mea run --task surgical_grasp_any --variant mea-gasv2` end to end over real Zenoh on 127.0.0.1:
an oracle demo goes through discrete MEA (its copies re-rendered), the GASv2 learner trains on them
and publishes latent policies that the actor and the evaluator run, the evaluator reports success
and the grasp score, and the env-step budget stops the run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.evaluator.history import HISTORY, read_history
from services.learner import checkpoint
from tests.helpers import find_free_port

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
BUDGET = 300


@pytest.mark.timeout(300)
def test_mea_gasv2_run_trains_on_mea_copies_and_stops_at_the_budget(tmp_path):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "services.cli", "run", "--task", "surgical_grasp_any", "--variant", "mea-gasv2",
           "--demos", "1", "--env-steps", str(BUDGET), "--eval-every", "150", "--eval-episodes", "2",
           "--final-eval-episodes", "2", "--learner-preset", "smoke", "--listen", f"tcp/127.0.0.1:{find_free_port()}",
           "--metrics-port", "0", "--run-dir", str(run_dir), "--final-eval-seconds", "90"]  # fmt: skip
    out = subprocess.run(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True,
                         text=True, timeout=280)  # fmt: skip
    log = out.stdout + out.stderr
    assert out.returncode == 0 and "env-step budget reached" in log, log[-4000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    learner = summary["instances"]["learner-0"]["counters"]
    assert learner["env_steps"] >= BUDGET and learner["updates"] > 0 and learner["rejected"] == 0
    # the demo's MEA copies reached the replay: many more transitions than env steps
    assert learner["replay_transitions"] > 5 * learner["env_steps"], learner
    assert summary["instances"]["actor-0"]["counters"]["episodes"] >= 3  # the demo and learned episodes
    records = read_history(run_dir / HISTORY)
    final = [r for r in records if r["at_budget"]]
    assert final and final[-1]["version"] > 0 and "grasp_score" in final[-1]
    assert 0.0 <= final[-1]["grasp_score"] <= 1.0 and 0.0 <= final[-1]["success_rate"] <= 1.0
    saved = json.loads((run_dir / "learner" / "learner.json").read_text())
    assert saved["algorithm"]["name"] == "gasv2" and saved["algorithm"]["observation"] == "dsa"
    _, replay, meta = checkpoint.load(run_dir / "learner" / "checkpoints")
    assert meta["version"] >= final[-1]["version"]
