"""Watching a run (smoke, in-process): RUN_DIR/tb holds the learner's, the evaluator's and the actor's
CleanRL-style scalars at env steps (a run per instance), the run's settings (hparams, Markdown table)
and the evaluation videos, whose MP4s in RUN_DIR/eval/videos have one frame per observation of the
filmed episodes; a resume appends at increasing steps; --track writes an offline W&B run with every
TensorBoard point under the same keys, and the resume continues the same W&B run. No network:
WANDB_MODE=offline, WANDB_DIR under tmp."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from services.evaluator.history import read_history

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
MACHINE = ["--metrics-port", "0", "--final-eval-seconds", "120", "--log-format", "text", "--in-process",
           "--track"]  # fmt: skip
TAGS = {
    "losses/critic_loss", "losses/actor_loss", "losses/alpha", "perf/updates_per_second",  # learner
    "eval/success_rate", "eval/return", "eval/length", "eval/grasp_score",  # evaluator
    "charts/episodic_return", "charts/success", "perf/env_steps_per_second",  # actor
}  # fmt: skip


def mea_run(wandb_dir: Path, *args: str) -> str:
    env = dict(
        os.environ, PYTHONPATH=str(ROOT), WANDB_MODE="offline", WANDB_DIR=str(wandb_dir), WANDB_SILENT="true"
    )
    out = subprocess.run([sys.executable, "-m", "services.cli", "run", *args, *MACHINE], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert out.returncode == 0, (out.stdout + out.stderr)[-4000:]
    return out.stdout + out.stderr


def accumulator(run: Path) -> EventAccumulator:
    ea = EventAccumulator(str(run), size_guidance={"scalars": 0, "images": 0, "tensors": 0})
    ea.Reload()
    return ea


def scalars(tb: Path) -> dict[str, list[int]]:
    """Each tag's steps, over the instances' runs (RUN_DIR/tb/<instance>), in the order written."""
    out: dict[str, list[int]] = {}
    for run in sorted(d for d in tb.iterdir() if d.is_dir()):
        ea = accumulator(run)
        for t in ea.Tags()["scalars"]:
            out.setdefault(t, []).extend(e.step for e in ea.Scalars(t))
    return out


def wandb_runs(wandb_dir: Path) -> list[dict]:
    """Each offline W&B run's summary, as wandb's own reader of its .wandb log prints it."""
    cli = Path(sys.executable).parent / "wandb"
    out = []
    for d in sorted((wandb_dir / "wandb").glob("offline-run-*")):
        got = subprocess.run([str(cli), "leet", "inspect", "--summary", "--json", str(d)], capture_output=True,
                             text=True, timeout=60, env=dict(os.environ, WANDB_MODE="offline"))  # fmt: skip
        assert got.returncode == 0, got.stderr[-2000:]
        out.append(json.loads(got.stdout))
    return out


def wandb_points(wandb_dir: Path, run_id: str, sitting: int) -> dict[str, set[int]]:
    """Each key's global steps in one sitting's offline W&B run (its history records; W&B keeps one
    value per key and step, so points of one step count once)."""
    cli = Path(sys.executable).parent / "wandb"
    d = sorted((wandb_dir / "wandb").glob(f"offline-run-*-{run_id}"))[sitting]
    got = subprocess.run([str(cli), "leet", "inspect", "--json", str(d)], capture_output=True, text=True,
                         timeout=60, env=dict(os.environ, WANDB_MODE="offline"))  # fmt: skip
    assert got.returncode == 0, got.stderr[-2000:]
    out: dict[str, set[int]] = {}
    for line in got.stdout.splitlines():
        record = json.loads(line)
        if record.get("type") != "history":
            continue
        item = record["history"]["item"]
        for key, value in item.items():
            if isinstance(value, (int, float)) and not key.startswith("_") and key != "global_step":
                out.setdefault(key, set()).add(int(item["global_step"]))
    return out


@pytest.mark.timeout(600)
def test_tensorboard_videos_and_wandb_over_a_run_and_its_resume(tmp_path):
    run, wb = tmp_path / "run", tmp_path / "wandb"
    wb.mkdir()
    mea_run(wb, "--task", "block_pull", "--demos", "1", "--env-steps", "100", "--eval-every", "1000",
            "--eval-episodes", "1", "--final-eval-episodes", "2", "--learner-preset", "smoke", "--run-dir", str(run),
            "--learner-args=--tensorboard-every 1")  # fmt: skip

    first = scalars(run / "tb")
    assert set(first) >= TAGS, sorted(TAGS - set(first))
    assert sorted(d.name for d in (run / "tb").iterdir() if d.is_dir()) == [
        "actor-0", "augmenter-0", "evaluator-0", "learner-0"]  # fmt: skip
    assert max(first["eval/success_rate"]) >= 100 and min(first["eval/success_rate"]) >= 0  # env steps
    assert "eval/video" in accumulator(run / "tb" / "evaluator-0").Tags()["images"]
    root = accumulator(run / "tb")  # the launcher's: the settings
    assert "_hparams_/session_start_info" in root.PluginTagToContent("hparams")
    table = root.Tensors("config/run/text_summary")[0].tensor_proto.string_val[0].decode()
    assert "| env_steps | `100` |" in table and "| task | `block_pull` |" in table

    # the filmed evaluations (the first, and the one at the budget): one frame per observation of
    # their first two episodes, whose lengths the history recorded
    history = {r["version"]: r for r in read_history(run / "eval" / "history.jsonl")}
    videos = sorted((run / "eval" / "videos").glob("*.mp4"))
    assert len(videos) == len(history) == 2, (videos, history)
    for video in videos:
        version = int(re.match(r"v(\d+)_", video.name).group(1))
        with imageio.get_reader(video) as reader:
            frames = [f for f in reader]
        assert len(frames) == sum(n + 1 for n in history[version]["lengths"][:2]), video.name
        assert frames[0].shape == (256 + 48, 512, 3)

    # W&B: one offline run, its id kept in the run dir, with TensorBoard's keys and every point
    run_id = (run / "wandb-run-id").read_text().strip()
    (one,) = wandb_runs(wb)
    assert (one["run_id"], one["state"], one["project"]) == (run_id, "finished", "mea")
    assert set(first) <= set(one["summary"]), sorted(set(first) - set(one["summary"]))
    points = wandb_points(wb, run_id, 0)
    videos_at = {e.step for e in accumulator(run / "tb" / "evaluator-0").Images("eval/video")}
    assert points.pop("eval/video.count") == videos_at and len(videos_at) == 2  # the videos, as media
    assert {k: v for k, v in points.items() if not k.startswith("eval/video.")} == {
        t: set(s) for t, s in first.items()
    }

    # a resume appends to the same directory, at increasing env steps, and continues the W&B run
    mea_run(wb, "--resume", str(run), "--env-steps", "200")
    both = scalars(run / "tb")
    assert both["eval/success_rate"] == sorted(both["eval/success_rate"])
    assert max(both["eval/success_rate"]) >= 200 > max(first["eval/success_rate"])
    for tag in TAGS:  # each service's points of the second sitting come after the first's
        assert len(both[tag]) > len(first[tag]) and both[tag] == sorted(both[tag]), tag
    assert "charts/weights_lag" in both  # learned episodes pulled newer weights
    runs = wandb_runs(wb)
    # the same W&B run goes on past the first sitting (its last synced step may trail the budget)
    assert [r["run_id"] for r in runs] == [run_id, run_id]
    assert runs[1]["summary"]["global_step"] > max(first["eval/success_rate"])
    second = {t: set(s[len(first.get(t, [])) :]) for t, s in both.items()}  # the second sitting's
    points = {k: v for k, v in wandb_points(wb, run_id, 1).items() if not k.startswith("eval/video.")}
    assert points == {t: s for t, s in second.items() if s}
