"""`mea play`: a run's sealed weights render to an MP4 that imageio reads back with one frame per
observation of each episode (the episodes the evaluator's runner plays on those seeds); a recorded
demonstration replays exactly from its seed; a robot session renders its requests; bad input is one
line, exit code 2, nothing written."""

from __future__ import annotations

import json
import shutil
import time

import imageio.v2 as imageio
import numpy as np
import pytest

from proto.inference import ActReply, ActRequest, ResetRequest
from proto.weights import WeightsBlob
from services.cli import main
from services.common import run_key, weights_file
from services.common.mcap_io import McapRecorder
from services.evaluator.video import CAPTION
from tests.helpers.tree import snapshot

pytestmark = pytest.mark.integration
SIZE = 128
SEED = 1_000_000_000


def _frames(path) -> list[np.ndarray]:
    with imageio.get_reader(path) as reader:  # its len() is inf for an MP4: iterate
        return [f for f in reader]


def play(capsys, *args) -> tuple[int, str, str]:
    try:
        code = main(["play", *map(str, args)])
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def blob() -> WeightsBlob:
    import torch

    from services.algorithms.networks import PRESETS, build_actor
    from services.algorithms.policy import PolicySpec, actor_tensors

    torch.manual_seed(0)
    spec = PolicySpec(PRESETS["cpu-small"])
    return WeightsBlob.create(5, "equi_rsac", "run-1", actor_tensors(build_actor(spec.net)), spec.to_json())


def _run_dir(tmp_path, blob: WeightsBlob):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"task": "block_pull"}))
    key = run_key.create(run / run_key.FILE_NAME)
    for version in (3, blob.version):  # sealed, as `mea run` writes them
        weights_file.write(run / weights_file.LEARNER, WeightsBlob.create(
            version, blob.algorithm, blob.run_id, blob.tensors, blob.config_json), key)  # fmt: skip
    return run


@pytest.mark.timeout(300)
def test_a_runs_policy_renders_one_frame_per_observation(tmp_path, capsys, blob):
    from services.algorithms.policy import PolicyRuntime
    from services.evaluator.evaluation import EpisodeRunner
    from services.tasks import make_env

    run = _run_dir(tmp_path, blob)
    out = tmp_path / "policy.mp4"
    code, stdout, err = play(capsys, run, "--episodes", 2, "--size", SIZE, "--out", out)
    assert code == 0 and err == "", err
    assert stdout.startswith(
        f"mea play: wrote {out}: 2 episodes of v5 (block_pull, seeds {SEED}..{SEED + 1})"
    )

    env = make_env("block_pull")  # the same episodes, played by the evaluator's runner
    try:
        runtime = PolicyRuntime(deterministic=True, seed=SEED)
        runtime.load(blob)
        lengths = [
            r.length for r in EpisodeRunner(env, "block_pull", "x").episodes(runtime, (SEED, SEED + 1))
        ]
    finally:
        env.close()
    frames = _frames(out)
    assert len(frames) == sum(n + 1 for n in lengths) and frames[0].shape == (SIZE + CAPTION, 2 * SIZE, 3)
    assert f"{len(frames)} frames" in stdout


@pytest.mark.timeout(300)
def test_a_fixed_start_run_is_filmed_from_the_public_start(tmp_path, capsys, blob, monkeypatch):
    import services.play

    starts = []

    def make_env(task, settings):  # the real env; the settings play asked for are kept
        starts.append(settings.gripper_start)
        return real_make_env(task, settings)

    real_make_env = services.play.make_env
    monkeypatch.setattr(services.play, "make_env", make_env)
    run = _run_dir(tmp_path, blob)
    for start in ("fixed", "random"):
        (run / "config.json").write_text(json.dumps({"task": "block_pull", "gripper_start": start}))
        out = tmp_path / f"{start}.mp4"
        code, _, err = play(capsys, run, "--episodes", 1, "--size", SIZE, "--out", out)
        assert code == 0 and err == "" and out.exists(), err
    assert starts == ["fixed", "random"]


def _demo_episode():
    from services.actor.config import ActorConfig
    from services.actor.rollout import RolloutActor

    actor = RolloutActor(ActorConfig(task="block_pull", demos=1), "actor-0")
    try:
        b = actor.expert_episode(0)
    finally:
        actor.env.close()
    return b.finish(actor.episode_id(b))


@pytest.mark.timeout(300)
def test_a_recording_replays_its_episode_and_a_robot_session_renders_its_requests(tmp_path, capsys):
    episode = _demo_episode()
    recording = tmp_path / "demos.mcap"
    with McapRecorder(recording) as rec:
        rec.write(episode)
    out = tmp_path / "demo.gif"
    code, stdout, err = play(capsys, "--recording", recording, "--size", SIZE, "--out", out)
    assert code == 0 and err == "", err
    assert "1 recorded episodes (replayed, largest gripper drift 0.0000)" in stdout  # the same motion
    frames = _frames(out)
    assert len(frames) == len(episode.actions) + 1 and frames[0].shape == (SIZE + CAPTION, 2 * SIZE, 3)
    stored = tmp_path / "stored.mp4"
    code, stdout, _ = play(capsys, "--recording", recording, "--no-replay", "--size", SIZE, "--out", stored)
    assert code == 0 and "stored images only" in stdout
    assert [f.shape for f in _frames(stored)] == [(SIZE + CAPTION, SIZE, 3)] * (len(episode.actions) + 1)

    session = tmp_path / "robot.mcap"  # a robot session: its requests' observations, the replies' actions
    rng = np.random.default_rng(0)
    with McapRecorder(session) as rec:
        rec.write(ResetRequest(session="arm-1", task="block_pull", created_at=time.time()))
        for step in range(4):
            image = rng.integers(0, 255, (2, 84, 84), np.uint8)
            state = np.array([0.5, 0.0, 0.2, 0.0, 1.0], np.float32)
            rec.write(
                ActRequest(session="arm-1", episode=1, step=step, stamp=time.time(), state=state, image=image)
            )
            rec.write(ActReply(session="arm-1", episode=1, step=step, action=np.zeros(5, np.float32),
                               policy_version=5, held=step == 3, reasons=[], compute_seconds=0.01))  # fmt: skip
    code, stdout, err = play(capsys, "--recording", session, "--size", SIZE, "--out", tmp_path / "robot.mp4")
    assert code == 0 and "1 robot session episodes" in stdout, err
    assert len(_frames(tmp_path / "robot.mp4")) == 4


def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys, blob):
    run = _run_dir(tmp_path, blob)
    empty = tmp_path / "empty.mcap"
    with McapRecorder(empty) as rec:
        rec.write(ResetRequest(session="arm-1", task="block_pull", created_at=time.time()))
    other = tmp_path / "other"  # sealed with another run's key
    other.mkdir()
    (other / "config.json").write_text(json.dumps({"task": "block_pull"}))
    run_key.create(other / run_key.FILE_NAME)
    (other / weights_file.LEARNER).mkdir(parents=True)
    name = weights_file.file_name(5)
    (run / weights_file.LEARNER / name).rename(other / weights_file.LEARNER / name)
    odd = tmp_path / "odd"  # a run whose config.json names no start pose this code knows
    shutil.copytree(run, odd)
    (odd / "config.json").write_text(json.dumps({"task": "block_pull", "gripper_start": "centre"}))
    out = tmp_path / "v.mp4"
    before = snapshot(tmp_path)
    cases = [
        ((run, "--out", tmp_path / "v.avi"), "--out"),
        ((tmp_path / "nowhere", "--out", out), "no such run directory"),
        ((run, "--version", 99, "--out", out), "no weights file for version 99"),
        ((run, "--recording", empty, "--out", out), "not both or neither"),
        (("--out", out), "not both or neither"),
        ((run, "--episodes", 0, "--out", out), "--episodes must be >= 1"),
        ((other, "--out", out), "seal does not verify"),
        (("--recording", empty, "--out", out), "no episodes or robot requests"),
        (("--recording", tmp_path / "none.mcap", "--out", out), "no such file"),
        ((run, "--version", 3, "--task", "unknown", "--out", out), "--task must be one of"),
        ((run, "--out", out, "--size", 100), "--size must be a multiple of 16"),
        ((odd, "--out", out), "gripper_start must be one of"),
    ]
    for args, problem in cases:
        code, stdout, err = play(capsys, *args)
        assert code == 2 and stdout == "" and err.startswith("mea play: ") and problem in err, (args, err)
        assert len(err.strip().splitlines()) == 1, err
    assert snapshot(tmp_path) == before
