"""Videos of episodes: each frame a third-person picture of the scene (``services.tasks.camera``)
beside the policy's own image (upscaled), over a caption with the version, env step, episode, step
and outcome; written as MP4 (imageio's ffmpeg plugin, the binary from the imageio-ffmpeg wheel) or
GIF (imageio's pillow plugin).

What the evaluator films (``Film``) and what `mea play` renders; apart from transport and storage
but for ``write`` (the file itself).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from services.tasks.camera import scene_image

CAPTION = 48
"""Pixels of the caption below the pictures (two lines of text)."""
FPS = 10
FORMATS = (".mp4", ".gif")
COLOURS = {"success": (60, 200, 60), "failure": (235, 70, 60), "": (230, 230, 230)}
"""Caption text colour (RGB) by outcome."""


def policy_view(image: np.ndarray, size: int) -> np.ndarray:
    """The policy's input (C, H, W) uint8 as an RGB picture ``size`` pixels high: a 3-channel image
    (the DSA image) as it is, else its first channel (the projection or depth codes; the others
    hold the jaw) in grey; upscaled without smoothing, so each of the policy's pixels stays visible."""
    x = np.asarray(image)
    rgb = np.moveaxis(x[:3], 0, -1) if x.shape[0] == 3 else np.repeat(x[0][..., None], 3, axis=-1)
    return cv2.resize(np.ascontiguousarray(rgb, np.uint8), (size, size), interpolation=cv2.INTER_NEAREST)


def compose(
    scene: np.ndarray | None, policy: np.ndarray, lines: Sequence[str], outcome: str = ""
) -> np.ndarray:
    """One frame: ``scene`` (absent: a recording without a simulator) beside ``policy`` (both RGB,
    the same height), over a caption of up to two ``lines``, the last in the outcome's colour."""
    h = policy.shape[0]
    pictures = [p for p in (scene, policy) if p is not None]
    top = np.concatenate(pictures, axis=1)
    frame = np.zeros((h + CAPTION, top.shape[1], 3), np.uint8)
    frame[:h] = top
    for i, line in enumerate(lines[-2:]):
        last = i == len(lines[-2:]) - 1
        colour = COLOURS.get(outcome if last else "", COLOURS[""])
        cv2.putText(frame, line, (6, h + 19 + 22 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    return frame


def outcome_of(success: bool) -> str:
    return "success" if success else "failure"


class Film:
    """Frames of the first ``episodes`` episodes of one evaluation (or of `mea play`): ``capture``
    at every observation keeps the scene and the policy's image, ``cut`` labels an episode once
    its outcome is known. The env's state is never changed (``services.tasks.camera.scene_image``)."""

    def __init__(self, episodes: int, size: int = 256, title: str = "") -> None:
        self.episodes, self.size, self.title = episodes, size, title
        self.frames: list[np.ndarray] = []
        self._scene: list[np.ndarray] = []
        self._policy: list[np.ndarray] = []

    def wants(self, k: int) -> bool:
        """Is the ``k``-th episode (from 0) filmed?"""
        return k < self.episodes

    def capture(self, env, policy_image: np.ndarray) -> None:
        self._scene.append(scene_image(env, self.size))
        self._policy.append(policy_view(policy_image, self.size))

    def cut(self, k: int, seed: int, success: bool, episode_return: float) -> None:
        """Label the captured frames as episode ``k`` (seed, step t/T, outcome) and keep them."""
        T = len(self._scene) - 1
        outcome = outcome_of(success)
        for t, (scene, policy) in enumerate(zip(self._scene, self._policy, strict=True)):
            lines = (f"{self.title}  episode {k + 1} seed {seed}",
                     f"step {t}/{T}  {outcome}  return {episode_return:g}")  # fmt: skip
            self.frames.append(compose(scene, policy, lines, outcome))
        self._scene, self._policy = [], []


def check_out(path: Path) -> None:
    """ValueError naming the problem unless a video can be written to ``path`` (.mp4 or .gif, in an
    existing directory); checked before anything runs or is written."""
    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"--out {path}: the video must end in .mp4 or .gif")
    if not path.parent.is_dir():
        raise ValueError(f"--out {path}: no such directory {path.parent}")
    if path.is_dir():
        raise ValueError(f"--out {path}: is a directory")


def missing_writer() -> str | None:
    """Why MP4s cannot be written here (imageio or its ffmpeg binary absent), or None if they can."""
    try:
        import imageio.v2  # noqa: F401 - deferred like ``write``
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as exc:
        return f"{exc.__class__.__name__}: {exc}".splitlines()[0]
    return None


def write(path: Path, frames: Sequence[np.ndarray], fps: float = FPS) -> Path:
    """``frames`` (H, W, 3) uint8 as ``path``: MP4 (H.264, yuv420p) or GIF by its suffix, written
    beside it first and moved into place, so no half-written video is left behind."""
    import imageio.v2 as imageio  # deferred: only where videos are written

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        if path.suffix.lower() == ".gif":
            imageio.mimwrite(tmp, list(frames), format="GIF", duration=1000.0 / fps, loop=0)
        else:
            with imageio.get_writer(tmp, format="FFMPEG", fps=fps, codec="libx264", quality=7,
                                    macro_block_size=16, ffmpeg_log_level="error") as w:  # fmt: skip
                for f in frames:
                    w.append_data(f)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


__all__ = ["FORMATS", "Film", "check_out", "compose", "missing_writer", "policy_view", "write"]
