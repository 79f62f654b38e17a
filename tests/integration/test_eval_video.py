"""Evaluation videos: a filmed 2-episode evaluation has one frame per observation of each episode, each
the scene beside the policy's image over a caption with the outcome drawn in its colour, reads back
from its MP4 at that count and size, and its episodes are the unfilmed ones exactly; the evaluator
films its 1st evaluation, every 5th after it and the one at the budget, and none with videos 0."""

from __future__ import annotations

import imageio.v2 as imageio
import numpy as np
import pytest

from services.evaluator.config import EvaluatorConfig
from services.evaluator.evaluation import EpisodeRunner
from services.evaluator.video import CAPTION, COLOURS, Film, compose, outcome_of, write
from services.tasks import EnvSettings, make_env
from services.tasks.camera import CameraSettings

pytestmark = pytest.mark.integration
SIZE = 128
SEEDS = (1_000_000_000, 1_000_000_001)


def _runtime():
    import torch

    from proto.weights import WeightsBlob
    from services.algorithms.networks import PRESETS, build_actor
    from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors

    torch.manual_seed(0)
    spec = PolicySpec(PRESETS["cpu-small"])
    blob = WeightsBlob.create(3, "equi_rsac", "run-1", actor_tensors(build_actor(spec.net)), spec.to_json())
    runtime = PolicyRuntime(deterministic=True, seed=0)
    runtime.load(blob)
    return runtime


@pytest.mark.timeout(180)
def test_a_filmed_two_episode_evaluation(tmp_path):
    env = make_env("block_pull", EnvSettings(camera=CameraSettings(points_per_segment=64)))
    try:
        runner, runtime = EpisodeRunner(env, "block_pull", "evaluator-0"), _runtime()
        plain = runner.episodes(runtime, SEEDS)
        film = Film(2, SIZE, "v3 at 1,000 env steps")
        filmed = runner.episodes(runtime, SEEDS, film)
    finally:
        env.close()
    assert filmed == plain  # filming changes neither the episodes nor their outcomes

    lengths = [r.length for r in plain]
    assert len(film.frames) == sum(n + 1 for n in lengths)  # the reset and every step, per episode
    assert {f.shape for f in film.frames} == {(SIZE + CAPTION, 2 * SIZE, 3)}
    starts = [0, lengths[0] + 1]
    for k, (start, result) in enumerate(zip(starts, plain, strict=True)):
        for frame in (film.frames[start], film.frames[start + result.length]):
            bare = compose(frame[:SIZE, :SIZE], frame[:SIZE, SIZE:], ())
            caption = frame[SIZE:].astype(int)
            assert np.abs(caption - bare[SIZE:]).sum(axis=-1).astype(bool).sum() > 200, k  # text drawn
            outcome = frame[SIZE + CAPTION // 2 :]  # the outcome line, in the outcome's colour
            assert (outcome == COLOURS[outcome_of(result.success)]).all(axis=-1).sum() > 20, k
        assert frame[:SIZE, :SIZE].std() > 10 and frame[:SIZE, SIZE:].any()  # a scene; the policy's image
    # the scene moves within an episode; the captions of two episodes differ (episode, seed)
    assert not np.array_equal(film.frames[0][:SIZE, :SIZE], film.frames[lengths[0]][:SIZE, :SIZE])
    assert not np.array_equal(film.frames[0][SIZE:], film.frames[starts[1]][SIZE:])

    path = write(tmp_path / "eval.mp4", film.frames)
    with imageio.get_reader(path) as reader:
        back = [f for f in reader]
    assert len(back) == len(film.frames) and back[0].shape == (SIZE + CAPTION, 2 * SIZE, 3)
    # H.264 is lossy, but the frames come back in order
    errors = [np.abs(b.astype(int) - f).mean() for b, f in zip(back, film.frames, strict=True)]
    assert max(errors) < 12, max(errors)


def _evaluator(tmp_path, **kw):
    from types import SimpleNamespace

    from services.common.metrics import ServiceMetrics
    from services.common.replay_gate import GateTracker
    from services.common.runtime import Shutdown
    from services.evaluator.main import Evaluator

    cfg = EvaluatorConfig(run_dir=tmp_path, keep_weights=0, **kw)
    ctx = SimpleNamespace(metrics=ServiceMetrics("evaluator", "evaluator-v"), instance="evaluator-v",
                          shutdown=Shutdown(install_signals=False), bus=None, policy_version=-1, detail="")  # fmt: skip
    gate = GateTracker(SimpleNamespace(drain=list))
    return Evaluator(cfg, ctx, gate, weights=None, env=SimpleNamespace(settings=EnvSettings()))  # type: ignore[arg-type]


def test_the_evaluator_films_the_first_every_fifth_and_the_budget(tmp_path):
    ev = _evaluator(tmp_path)
    filmed = []
    for n in range(12):
        ev.records = [{}] * n  # n evaluations in the run's history before this one
        film = ev._film(n, 100 * n, at_budget=n == 7)
        filmed.append(film is not None)
        if film is not None:
            assert film.episodes == 2 and film.title == f"v{n} at {100 * n:,} env steps"
    assert [n for n, f in enumerate(filmed) if f] == [0, 5, 7, 10]
    assert ev.videos_dir == tmp_path / "eval" / "videos"
    off = _evaluator(tmp_path, videos=0)
    assert off.videos_dir is None and off._film(1, 100, at_budget=True) is None


def test_the_run_passes_its_video_and_tensorboard_settings(tmp_path):
    from services.plan import config_for
    from services.run_config import RunConfig

    run = RunConfig(run_dir=tmp_path)
    evaluator = config_for(run, tmp_path, "evaluator", 0)
    assert (evaluator.videos, evaluator.tensorboard_dir) == (2, tmp_path / "tb")
    assert config_for(run, tmp_path, "actor", 1).tensorboard_dir == tmp_path / "tb"
    assert config_for(RunConfig(eval_videos=0), tmp_path, "evaluator", 0).videos == 0
    with pytest.raises(ValueError, match="--eval-videos must be >= 0"):
        RunConfig(eval_videos=-1)


def test_without_an_mp4_writer_the_evaluator_says_so_once_and_films_nothing(tmp_path, monkeypatch, caplog):
    import sys

    from services.evaluator.video import missing_writer

    assert missing_writer() is None  # this environment has imageio-ffmpeg
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails, as where it is not installed
    assert "imageio_ffmpeg" in missing_writer()
    with caplog.at_level("WARNING"):
        ev = _evaluator(tmp_path)
    assert ev.videos_dir is None and ev._film(0, 0, at_budget=True) is None
    assert [r.getMessage() for r in caplog.records if "videos off" in r.getMessage()] == [
        "evaluation videos off: no MP4 writer here (pip install imageio imageio-ffmpeg)"
    ]
