"""`mea run --actors auto` end to end without training: the resolved count lands in config.json and
the services' configs, the launcher logs its plan before anything starts, and `--resume` keeps the
saved count (or resolves auto again on the machine it resumes on)."""

from __future__ import annotations

import json
import os

import pytest

import services.launcher
from services.common import logs
from services.launcher import CHILD_THREAD_VARS, main

pytestmark = pytest.mark.integration


class Started:
    """A service instance that was "started": it runs until stopped (nothing is spawned)."""

    pid = None
    exitcode = None

    def is_alive(self) -> bool:
        return False

    def join(self, timeout: float | None = None) -> None:
        pass

    def kill(self) -> None:
        pass


@pytest.fixture
def stack(monkeypatch):
    """``mea run`` with its instances recorded instead of started (a list of their names per run)."""
    monkeypatch.setattr(logs, "_shared", False)  # --in-process shares the logs; undone after the test
    for var in CHILD_THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    runs: list[list[str]] = []

    def starter(cfg, router, shutdown):
        runs.append([])
        return lambda spec: runs[-1].append(spec.instance) or Started()

    monkeypatch.setattr(services.launcher, "_starter", starter)
    return runs


def plan_record(err: str) -> dict:
    (plan,) = [r for r in map(json.loads, err.splitlines()) if r.get("msg") == "plan"]
    return plan


def cores(monkeypatch, n: int) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(n)), raising=False)


def test_auto_is_saved_as_a_number_planned_and_kept_on_resume(stack, tmp_path, monkeypatch, capsys):
    cores(monkeypatch, 16)
    run_dir = tmp_path / "run"
    common = ["--in-process", "--duration-seconds", "0.2", "--metrics-port", "0", "--log-format", "json"]
    assert main(["--actors", "auto", "--run-dir", str(run_dir), "--no-record", *common]) == 0
    assert json.loads((run_dir / "config.json").read_text())["actors"] == 12
    actors = [f"actor-{i}" for i in range(12)]
    assert stack[-1] == ["learner-0", "augmenter-0", "evaluator-0", *actors]
    assert sorted(p.stem for p in (run_dir / "services").glob("actor-*.json")) == sorted(actors)
    plan = plan_record(capsys.readouterr().err)
    assert plan["instances"] == (
        "learner-0 (cpu, 1 torch thread), augmenter-0, evaluator-0 (1 torch thread), actor-0..11"
    )
    assert plan["cores"] == 16 and plan["threads"] == "one process, a thread per instance"

    cores(monkeypatch, 2)  # resumed on a smaller machine: the saved number, not auto again
    assert main(["--resume", str(run_dir), *common]) == 0
    assert len(stack[-1]) == 3 + 12 and json.loads((run_dir / "config.json").read_text())["actors"] == 12
    assert plan_record(capsys.readouterr().err)["cores"] == 2
    # --actors auto on resume: resolved on this machine, recorded as a change
    assert main(["--resume", str(run_dir), "--actors", "auto", *common]) == 0
    saved = json.loads((run_dir / "config.json").read_text())
    assert saved["actors"] == 1 and saved["history"][-1]["changed"] == {"actors": [12, 1]}
    assert stack[-1] == ["learner-0", "augmenter-0", "evaluator-0", "actor-0"]
