"""`mea play`: see what a policy does, as a video (MP4 or GIF), without writing code.

Films a run's trained policy acting in a fresh env of its task, or recorded episodes (raw episodes,
`mea demos`, a `mea robot` session), so that behaviour can be checked by eye.

Design notes: docs/architecture-notes.md, services/play.py."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError

from proto.episode import Episode, succeeded
from proto.msgpack_wire import ProtocolError
from proto.seeds import EVAL_SEED_BASE
from services.common import config, run_key, weights_file
from services.common.mcap_io import read_recording
from services.evaluator.evaluation import EpisodeRunner
from services.evaluator.history import HISTORY, read_history
from services.evaluator.video import FPS, Film, check_out, compose, outcome_of, policy_view
from services.evaluator.video import write as write_video
from services.observation.depth_image import policy_images
from services.observation.projection import segment_policy_images
from services.tasks import TASK_CLASSES, EnvSettings, make_env
from services.tasks.camera import scene_image

PROG = "mea play"


@dataclass(frozen=True)
class PlayArgs:
    run: Path | None
    recording: Path | None
    out: Path
    version: int | None
    episodes: int
    seed: int
    task: str
    size: int
    fps: float
    replay: bool


def parse(argv: Sequence[str]) -> PlayArgs:
    p = config.OneLineParser(prog=PROG, description=__doc__.split("\n\n", 1)[0] if __doc__ else None)
    p.add_argument("run", nargs="?", type=Path, metavar="RUN_DIR", help="a run directory or a weights file")
    p.add_argument("--recording", type=Path, metavar="FILE.mcap", help="render recorded episodes instead")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.mp4|FILE.gif", help="the video to write")
    p.add_argument("--version", type=int, help="weights version (default: the newest)")
    p.add_argument("--episodes", type=int, default=2, help="episodes to render (default 2)")
    p.add_argument("--seed", type=int, default=EVAL_SEED_BASE, help="first seed (default: the held-out 1e9)")
    p.add_argument("--task", default="", help="task of a bare weights file (default: the run's)")
    p.add_argument("--size", type=int, default=256, help="pixels per side of each picture (default 256)")
    p.add_argument("--fps", type=float, default=FPS, help=f"frames per second (default {FPS})")
    p.add_argument("--no-replay", dest="replay", action="store_false",
                   help="--recording: the stored images alone, no replay in the simulator")  # fmt: skip
    a = p.parse_args(list(argv))
    if (a.run is None) == (a.recording is None):
        raise ValueError("give a RUN_DIR (a trained policy) or --recording FILE.mcap, not both or neither")
    if a.episodes < 1 or a.seed < 0 or (a.version is not None and a.version < 0):
        raise ValueError("--episodes must be >= 1, --seed and --version >= 0")
    if a.size < 64 or a.size > 1024 or a.size % 16 or not 0 < a.fps <= 60:
        raise ValueError("--size must be a multiple of 16 in 64..1024, --fps in (0, 60]")
    check_out(a.out)
    return PlayArgs(a.run, a.recording, a.out, a.version, a.episodes, a.seed, a.task, a.size, a.fps, a.replay)


def _run_dir(weights: Path) -> Path | None:
    """The run directory (its config.json) a weights file belongs to, if any: RUN_DIR/learner/weights
    or RUN_DIR/eval/weights hold them."""
    return next((d for d in weights.parents[:3] if (d / "config.json").is_file()), None)


def _key(run_dir: Path | None) -> bytes | None:
    """The run's key, where the run authenticated (RUN_DIR/run.key): its weights files are sealed."""
    if run_dir is None or not (run_dir / run_key.FILE_NAME).is_file():
        return None
    return run_key.load(run_dir / run_key.FILE_NAME)


def run_setting(run_dir: Path | None, name: str, default: str) -> str:
    """Setting ``name`` of the run's config.json (``default`` outside a run or where it has none)."""
    if run_dir is None:
        return default
    try:
        saved = json.loads((run_dir / "config.json").read_text())
    except (OSError, ValueError):
        return default
    value = saved.get(name, default) if isinstance(saved, dict) else default
    return value if isinstance(value, str) else default


def run_env_settings(run_dir: Path | None, observation: str) -> EnvSettings:
    """The env a run's policy is played in: its observation's image and the run's own start pose (a
    --gripper-start fixed run starts from the public start). ValueError naming config.json."""
    try:
        return EnvSettings(
            depth_image=observation == "depth", gripper_start=run_setting(run_dir, "gripper_start", "random")
        )
    except ValueError as exc:
        raise ValueError(f"{run_dir}/config.json: {exc}") from None


def _env_steps(run_dir: Path | None, version: int) -> int:
    """The env steps the run's evaluator recorded for ``version`` (-1: none)."""
    if run_dir is None or not (run_dir / HISTORY).is_file():
        return -1
    steps = [r.get("env_steps", -1) for r in read_history(run_dir / HISTORY) if r.get("version") == version]
    return int(steps[-1]) if steps else -1


def play_policy(a: PlayArgs) -> str:
    """Film the run's policy; returns the line to print. ValueError on bad input, before writing."""
    assert a.run is not None
    if not a.run.exists():
        raise ValueError(f"{a.run}: no such run directory or weights file")
    try:
        path = weights_file.resolve(a.run, a.version)
        run_dir = _run_dir(path)
        blob = weights_file.read(path, _key(run_dir))
    except weights_file.WeightsFileError as exc:
        raise ValueError(str(exc)) from None
    task = a.task or run_setting(run_dir, "task", "")
    if task not in TASK_CLASSES:
        raise ValueError(f"--task must be one of {', '.join(TASK_CLASSES)} (a weights file outside a run "
                         f"directory names none), not {task!r}")  # fmt: skip
    # deferred: torch (seconds to import), needed only to film a policy, not for recordings or bad input
    from services.algorithms.policy import PolicyRuntime, blob_observation, check_observation

    try:
        observation = blob_observation(blob)
        check_observation(observation, observation == "depth", "`mea play`", task)
        runtime = PolicyRuntime(deterministic=True, seed=a.seed)
        runtime.load(blob)
    except ValueError as exc:
        raise ValueError(f"{path}: the weights do not load for {task}: {exc}") from None
    steps = _env_steps(run_dir, blob.version)
    title = f"v{blob.version}" + ("" if steps < 0 else f" at {steps:,} env steps")
    env = make_env(task, run_env_settings(run_dir, observation))
    try:
        film = Film(a.episodes, a.size, title)
        seeds = range(a.seed, a.seed + a.episodes)
        results = EpisodeRunner(env, task, "play").episodes(runtime, seeds, film)
    finally:
        env.close()
    write_video(a.out, film.frames, a.fps)
    wins = sum(r.success for r in results)
    return (f"{PROG}: wrote {a.out}: {len(results)} episodes of v{blob.version} ({task}, seeds {a.seed}.."
            f"{a.seed + a.episodes - 1}), {wins} successes, {len(film.frames)} frames")  # fmt: skip


def _stored_images(ep: Episode) -> np.ndarray:
    """The policy's images of an episode's T+1 observations: its stored images (depth, DSA), else
    the voxel projection of its points, as the augmenter attaches them."""
    if ep.images is None:
        return segment_policy_images(ep.points, ep.point_counts, ep.jaw)
    if ep.images.dtype == np.uint8:
        return ep.images
    return policy_images(ep.images[:, 0], ep.jaw)


def _replay(ep: Episode, size: int) -> tuple[list[np.ndarray], float]:
    """The scene at each of the episode's observations, replaying its actions from its seed, and the
    largest distance (m, or sim units) between the replayed and the recorded gripper."""
    env = make_env(ep.task)
    try:
        obs = env.reset(ep.seed)
        scenes, drift = [scene_image(env, size)], [obs.gripper_pose[:3] - ep.gripper_pose[0, :3]]
        for t, action in enumerate(ep.actions):
            obs, *_ = env.step(np.asarray(action, np.float64))
            scenes.append(scene_image(env, size))
            drift.append(obs.gripper_pose[:3] - ep.gripper_pose[t + 1, :3])
    finally:
        env.close()
    return scenes, float(np.max(np.linalg.norm(drift, axis=1)))


def _episode_frames(ep: Episode, k: int, size: int, replay: bool) -> tuple[list[np.ndarray], float]:
    images = _stored_images(ep)
    scenes, drift = _replay(ep, size) if replay else ([None] * len(images), 0.0)
    outcome = outcome_of(succeeded(ep.terminated, ep.rewards))
    T, ret = len(ep.actions), float(np.sum(ep.rewards))
    frames = []
    for t, (scene, image) in enumerate(zip(scenes, images, strict=True)):
        lines = (f"{ep.task} {ep.policy_kind} v{ep.policy_version} episode {k + 1} seed {ep.seed}",
                 f"step {t}/{T}  {outcome}  return {ret:g}")  # fmt: skip
        frames.append(compose(scene, policy_view(image, size), lines, outcome))
    return frames, drift


def _sessions(messages: Iterator) -> dict[tuple[str, int], list]:
    """A robot session's requests by (session, episode), each with its reply's action (or None)."""
    requests: dict[tuple[str, int], list] = {}
    replies = {}
    for _, m in messages:
        if m.TYPE == "ActRequest":
            requests.setdefault((m.session, m.episode), []).append(m)
        elif m.TYPE == "ActReply":
            replies[(m.session, m.episode, m.step)] = m
    return {
        k: [(r, replies.get((*k, r.step))) for r in sorted(v, key=lambda r: r.step)]
        for k, v in requests.items()
    }


def _session_frames(key: tuple[str, int], steps: list, size: int) -> list[np.ndarray]:
    frames = []
    for req, reply in steps:
        if req.image is not None:
            image = req.image
        else:
            jaw = np.array([req.state[4]], np.float32)
            image = segment_policy_images(req.points[None], req.point_counts[None], jaw)[0]
        action = "no reply" if reply is None else ("held " if reply.held else "") + np.array2string(
            reply.action, precision=2, suppress_small=True)  # fmt: skip
        lines = (f"session {key[0]} ep {key[1]}", f"step {req.step}  {action}")
        frames.append(compose(None, policy_view(image, size), lines))
    return frames


def play_recording(a: PlayArgs) -> str:
    """Render a recording's first episodes; returns the line to print. ValueError on bad input."""
    assert a.recording is not None
    if not a.recording.exists():
        raise ValueError(f"--recording {a.recording}: no such file or directory")
    types = {"Episode", "ActRequest", "ActReply"}
    try:
        messages = list(read_recording(a.recording, types=types))
    except (ProtocolError, McapError, OSError, ValueError) as exc:
        raise ValueError(f"--recording {a.recording}: cannot be read ({exc})") from None
    episodes = [m for _, m in messages if m.TYPE == "Episode"][: a.episodes]
    frames: list[np.ndarray] = []
    if episodes:
        drifts = []
        for k, ep in enumerate(episodes):
            f, drift = _episode_frames(ep, k, a.size, a.replay)
            frames += f
            drifts.append(drift)
        how = f"replayed, largest gripper drift {max(drifts):.4f}" if a.replay else "stored images only"
        what = f"{len(episodes)} recorded episodes ({how})"
    else:
        sessions = list(_sessions(iter(messages)).items())[: a.episodes]
        if not sessions:
            raise ValueError(f"--recording {a.recording}: no episodes or robot requests in it")
        for key, steps in sessions:
            frames += _session_frames(key, steps, a.size)
        what = f"{len(sessions)} robot session episodes (their observations)"
    write_video(a.out, frames, a.fps)
    return f"{PROG}: wrote {a.out}: {what}, {len(frames)} frames"


def main(argv: Sequence[str]) -> int:
    try:
        a = parse(argv)
        line = play_policy(a) if a.run is not None else play_recording(a)
    except ValueError as exc:
        config.refuse(PROG, str(exc))
    print(line, file=sys.stdout)
    return 0


__all__ = ["main", "parse", "play_policy", "play_recording"]
