"""Each spawned service process gets one OpenMP/BLAS thread unless the user's environment says
otherwise (a run is many processes; a thread per core in each oversubscribes the machine)."""

from __future__ import annotations

import multiprocessing as mp
import os

import pytest

from services.launcher import CHILD_THREAD_VARS, one_thread_per_child

pytestmark = pytest.mark.unit


def test_unset_variables_become_one_and_the_users_choice_stays():
    env = {"OMP_NUM_THREADS": "4", "PATH": "/bin"}
    one_thread_per_child(env)
    assert env["OMP_NUM_THREADS"] == "4" and env["PATH"] == "/bin"
    assert all(env[v] == "1" for v in CHILD_THREAD_VARS if v != "OMP_NUM_THREADS")


def _report_threads(queue) -> None:
    import torch

    queue.put((os.environ.get("OMP_NUM_THREADS"), torch.get_num_threads()))


def test_a_spawned_child_runs_torch_on_one_thread(monkeypatch):
    for var in CHILD_THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    one_thread_per_child(os.environ)  # monkeypatch restores the environment afterwards
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    p = ctx.Process(target=_report_threads, args=(queue,))
    p.start()
    try:
        assert queue.get(timeout=60) == ("1", 1)
    finally:
        p.join(timeout=30)
