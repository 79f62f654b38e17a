"""Training scalars for TensorBoard: means over a window of updates (or episodes), written with torch's
``SummaryWriter`` (the tensorboard package) against env steps, CleanRL-style tags.

A service keeps one ``ScalarLog``; ``add`` is cheap (Python floats summed) and writes every ``every``
calls, so a write never happens per update or env step. Each writer has a directory of its own in the
run's (RUN_DIR/tb/<instance>: a TensorBoard run per service instance), because TensorBoard's live
reload and wandb's TensorBoard sync follow one growing event file per directory and leave a file once
a newer one appears there; a resumed run adds its files to the same directories. Besides scalars:
text (the launcher's settings table), the hparams plugin's records, and animations (evaluation
videos, as animated GIFs)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

TAG_PREFIXES = (
    ("batch_", "charts/"),
    ("episode_lag", "charts/"),
    ("updates_per_second", "perf/"),
    ("grad_norm", "diagnostics/"),
    ("bc_accept", "diagnostics/"),
    ("crr_keep", "diagnostics/"),
    ("bc_weight", "diagnostics/"),
    ("q_rank_gap", "diagnostics/"),
    ("q_reverse_gap", "diagnostics/"),
    ("q_demo_minus_pi", "diagnostics/"),
)


def tag(name: str) -> str:
    """The TensorBoard tag of an info key: a key with a ``/`` is a tag already (``eval/return``);
    else ``charts/``, ``perf/``, ``diagnostics/`` by the rules of ``TAG_PREFIXES`` (first that
    matches), ``losses/`` for every other training number."""
    if "/" in name:
        return name
    for needle, prefix in TAG_PREFIXES:
        if needle in name:
            return prefix + name
    return "losses/" + name


class ScalarLog:
    """Means of named scalars over ``every`` calls of ``add``, written at an env step into
    ``log_dir/suffix`` (``suffix``: the writer's instance; empty: ``log_dir`` itself)."""

    def __init__(self, log_dir: Path, every: int, suffix: str) -> None:
        self.log_dir, self.suffix = (log_dir / suffix if suffix else log_dir), suffix
        self.every = max(1, every)
        self._writer: Any = None  # opened at the first write: importing tensorboard takes seconds
        self._sums: dict[str, float] = {}
        self._counts: dict[str, int] = {}
        self._calls = 0

    def add(self, values: Mapping[str, float], step: int) -> bool:
        """Accumulate ``values`` (non-finite ones skipped); every ``every`` calls write their means at
        ``step`` and return True."""
        for k, v in values.items():
            if isinstance(v, (int, float)) and math.isfinite(v):
                self._sums[k] = self._sums.get(k, 0.0) + float(v)
                self._counts[k] = self._counts.get(k, 0) + 1
        self._calls += 1
        if self._calls % self.every:
            return False
        self.write(step)
        return True

    @property
    def due(self) -> bool:
        """Will the next ``add`` write? (a caller adds a number measured over the window only then)"""
        return (self._calls + 1) % self.every == 0

    @property
    def writer(self) -> Any:
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter  # deferred: a slow import, off start-up

            self._writer = SummaryWriter(
                str(self.log_dir), filename_suffix=f".{self.suffix}" if self.suffix else ""
            )
        return self._writer

    def write(self, step: int) -> None:
        for k, total in self._sums.items():
            self.writer.add_scalar(tag(k), total / self._counts[k], step)
        self._sums.clear()
        self._counts.clear()
        self.writer.flush()

    def add_text(self, tag_: str, text: str, step: int = 0) -> None:
        """Markdown ``text`` under ``tag_`` (TensorBoard's text plugin renders tables)."""
        self.writer.add_text(tag_, text, step)
        self.writer.flush()

    def add_hparams(self, values: Mapping[str, Any], metrics: Sequence[tuple[str, str]]) -> None:
        """The hparams plugin's records of this directory's run (tensorboard's own ``summary_v2``):
        ``values`` (bool, int, float or str; anything else as its text) against ``metrics``, (run,
        tag) pairs whose values TensorBoard reads from the scalars of the run in that subdirectory
        (``evaluator-0``, ``eval/success_rate``). Written into this writer's own file: torch's
        ``add_hparams`` would open a run of its own and knows no metric in another run."""
        from tensorboard.plugins.hparams import summary_v2 as hp  # deferred: tensorboard, a slow import

        plain = {k: v if isinstance(v, (bool, int, float, str)) else str(v) for k, v in values.items()}
        config = hp.hparams_config_pb(
            [hp.HParam(k) for k in plain], [hp.Metric(t, group=g) for g, t in metrics]
        )
        for summary in (config, hp.hparams_pb(plain)):
            self.writer.file_writer.add_summary(summary)
        self.writer.flush()

    def add_animation(self, tag_: str, frames: Sequence[Any], step: int, fps: float) -> None:
        """``frames`` (H, W, 3) uint8 as an animated GIF in TensorBoard's image plugin: what
        ``SummaryWriter.add_video`` writes, encoded with imageio (pillow) instead of moviepy."""
        import imageio.v3 as iio  # deferred: only the evaluator's animations need it
        from tensorboard.compat.proto.summary_pb2 import Summary  # deferred: tensorboard, a slow import

        gif = iio.imwrite("<bytes>", list(frames), extension=".gif", duration=1000.0 / fps, loop=0)
        height, width = frames[0].shape[:2]
        image = Summary.Image(height=height, width=width, colorspace=3, encoded_image_string=gif)
        self.writer.file_writer.add_summary(Summary(value=[Summary.Value(tag=tag_, image=image)]), step)
        self.writer.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
