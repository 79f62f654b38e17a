"""`mea serve` and `mea robot --sim` as separate processes over Zenoh on 127.0.0.1, authenticated with a
run key: the robot, with injected latency and jitter, runs the evaluator's episodes (same seeds, same
actions), its session is recorded to MCAP, and the server's /metrics count what it served. A robot
without the run's key gets no action."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from proto.inference import ResetRequest
from proto.topics import SERVE_RESET
from proto.weights import WeightsBlob
from services.algorithms.networks import PRESETS, build_actor
from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors
from services.common import run_key, weights_file
from services.common.bus.base import Credentials
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig
from services.common.mcap_io import read_messages, read_metadata
from services.evaluator.config import EvaluatorConfig
from services.evaluator.evaluation import EpisodeRunner
from services.inference.adapter import sim_limits
from services.tasks import make_env
from tests.helpers import find_free_port, stop_process

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
EPISODES = 3


def _cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "services.cli", *args]


@pytest.mark.timeout(240)
def test_sim_robot_over_zenoh_matches_the_evaluator_and_strangers_get_nothing(tmp_path, zenoh_router):
    key_file = tmp_path / "run.key"
    key = run_key.create(key_file)
    torch.manual_seed(1)
    spec = PolicySpec(PRESETS["cpu-small"])
    blob = WeightsBlob.create(7, "equi_rsac", "run-e2e", actor_tensors(build_actor(spec.net)), spec.to_json())
    weights_file.write(tmp_path / "weights", blob, key, "learner-0")
    env = make_env("block_pull", EvaluatorConfig().env_settings())
    lim = dataclasses.asdict(sim_limits(env))
    limits = tmp_path / "limits.json"
    limits.write_text(
        json.dumps({"default": {k: list(v) if isinstance(v, tuple) else v for k, v in lim.items()}})
    )
    common = ["--service.zenoh.mode", "client", "--service.zenoh.connect", zenoh_router,
              "--service.run-key-file", str(key_file), "--service.log-format", "text"]  # fmt: skip
    metrics_port = find_free_port()
    env_vars = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    serve = subprocess.Popen(
        _cmd("serve", "--weights", str(tmp_path / "weights"), "--limits-file", str(limits), *common,
             "--service.instance-id", "inference-0", "--service.metrics-port", str(metrics_port)),
        cwd=ROOT, env=env_vars, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        record, out = tmp_path / "robot.mcap", tmp_path / "robot.json"
        robot = subprocess.run(
            _cmd("robot", "--sim", "--task", "block_pull", "--episodes", str(EPISODES), "--latency-ms", "3",
                 "--jitter-ms", "2", "--record", str(record), "--out", str(out), "--wait-for-server", "90",
                 *common, "--service.instance-id", "robot-0", "--service.metrics-port", "0"),
            cwd=ROOT, env=env_vars, capture_output=True, text=True, timeout=200,
        )  # fmt: skip
        assert robot.returncode == 0, (robot.stdout + robot.stderr)[-4000:]
        summary = json.loads(out.read_text())
        with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=5) as r:
            metrics = r.read().decode()

        # a client without the run's key: its reset is refused and counted by the server
        stranger = ZenohBus(ZenohConfig(mode="client", connect=(zenoh_router,)))
        try:
            stranger.authenticate(Credentials(bytes(32), "robot", "robot-x"))
            req = ResetRequest(session="intruder", task="block_pull", created_at=time.time())
            assert stranger.call(SERVE_RESET, req, timeout=3.0, source="inference-0") is None
        finally:
            stranger.close()
        with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=5) as r:
            after = r.read().decode()
    finally:
        stop_process(serve)
        log = serve.stdout.read() if serve.stdout else ""
    assert serve.returncode == 0, log[-4000:]

    # the evaluator's episodes on the same seeds, action for action, on one torch thread as the
    # evaluator and the server run (another thread count sums convolutions in another order)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    runtime = PolicyRuntime(deterministic=True)
    runtime.load(weights_file.read(weights_file.resolve(tmp_path / "weights"), key))
    taken: list[np.ndarray] = []
    act = runtime.act
    runtime.act = lambda image: taken.append(act(image)) or taken[-1]  # type: ignore[method-assign]
    try:
        results = EpisodeRunner(env, "block_pull", "evaluator-0").episodes(runtime, summary["seeds"])
    finally:
        torch.set_num_threads(threads)
    assert [(r.seed, r.success, r.length, r.ret) for r in results] == [
        (e["seed"], e["success"], e["length"], e["return"]) for e in summary["episodes"]
    ]
    assert summary["seeds"] == list(
        range(EvaluatorConfig().seed_base, EvaluatorConfig().seed_base + EPISODES)
    )
    replies = [m for _, m in read_messages(record, types={"ActReply"})]
    requests = [m for _, m in read_messages(record, types={"ActRequest"})]
    assert len(replies) == len(requests) == len(taken) == sum(e["length"] for e in summary["episodes"])
    np.testing.assert_array_equal(np.stack([m.action for m in replies]), np.stack(taken))
    assert all(m.policy_version == 7 and not m.held for m in replies)
    assert read_metadata(record)["summary"]  # outcomes recorded beside the messages
    assert summary["injected_delay"]["p50_ms"] > 1.0 and summary["round_trip"]["n"] == len(replies)

    assert f'mea_inference_requests_total{{kind="act"}} {float(len(replies))}' in metrics
    assert "mea_inference_policy_version 7.0" in metrics and "mea_inference_act_seconds_count" in metrics
    assert 'mea_bus_unauthenticated_messages_total{topic="serve_reset"} 1.0' in after, after[-3000:]
