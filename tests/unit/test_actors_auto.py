"""`mea run --actors auto`: the actor count from the cores this process may use (4 left to the
learner, augmenter, evaluator and launcher; 1 to 12), resolved once in RunConfig; and the plan line
the launcher logs at start."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.common import config
from services.launcher import CHILD_THREAD_VARS, child_threads
from services.plan import ChildSpec, child_specs, describe
from services.run_config import AUTO_MAX_ACTORS, RunConfig

pytestmark = pytest.mark.unit


def cores(monkeypatch, n: int) -> None:
    """This process may run on ``n`` cores."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(n)), raising=False)


@pytest.mark.parametrize(("n", "actors"), [(1, 1), (2, 1), (5, 1), (8, 4), (16, 12), (64, AUTO_MAX_ACTORS)])
def test_auto_leaves_four_cores_to_the_rest_of_the_run_and_starts_1_to_12_actors(monkeypatch, n, actors):
    cores(monkeypatch, n)
    cfg = RunConfig(actors="auto")
    assert cfg.actors == actors
    assert config.to_jsonable(cfg)["actors"] == actors  # what config.json records: the number
    specs, _ = child_specs(cfg, Path("run"))
    assert [s.instance for s in specs if s.service == "actor"] == [f"actor-{i}" for i in range(actors)]


def test_auto_counts_the_machines_cores_where_there_is_no_affinity(monkeypatch):
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    assert RunConfig(actors="auto").actors == 12


def test_a_number_is_kept_and_anything_else_refused_naming_the_option(monkeypatch):
    cores(monkeypatch, 16)
    assert RunConfig(actors=3).actors == 3 and RunConfig(actors=0).actors == 0
    with pytest.raises(ValueError, match=r"^--actors must be >= 0 or auto, not -1$"):
        RunConfig(actors=-1)
    with pytest.raises(ValueError, match=r"^--actors must be >= 0 or auto, not 'many'$"):
        RunConfig(actors="many")  # type: ignore[arg-type]


def test_the_plan_names_every_instance_with_its_device_and_threads(tmp_path):
    specs, _ = child_specs(RunConfig(actors=4), tmp_path)
    assert describe(specs) == (
        "learner-0 (cpu, 1 torch thread), augmenter-0, evaluator-0 (1 torch thread), actor-0..3"
    )
    one, _ = child_specs(RunConfig(actors=1, services=("learner", "actor")), tmp_path)
    assert describe(one) == "learner-0 (cpu, 1 torch thread), actor-0"
    plugins = [ChildSpec("test", f"extra-{i}", "m:f") for i in range(2)]
    assert describe(plugins) == "extra-0..1"


def test_the_plan_says_which_thread_pools_the_environment_sets():
    assert child_threads({}) == "1 OpenMP, MKL and OpenBLAS thread per process (mea run's default)"
    assert child_threads({"MKL_NUM_THREADS": "4", "PATH": "/bin"}) == (
        "OMP_NUM_THREADS 1, MKL_NUM_THREADS 4 (environment), OPENBLAS_NUM_THREADS 1 per process"
    )
    assert set(CHILD_THREAD_VARS) == {"OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"}
