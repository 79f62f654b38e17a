"""TensorBoard scalars: means over a window written at env steps, CleanRL-style tags, read back with
tensorboard's own event reader; each writer in a directory of its own (its instance), where a second
writer (a resume) appends."""

from __future__ import annotations

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from services.common.scalars import ScalarLog, tag

pytestmark = pytest.mark.unit


def read(log_dir) -> dict[str, list[tuple[int, float]]]:
    ea = EventAccumulator(str(log_dir), size_guidance={"scalars": 0})
    ea.Reload()
    return {t: [(e.step, e.value) for e in ea.Scalars(t)] for t in ea.Tags()["scalars"]}


def test_tags_follow_the_cleanrl_layout():
    assert tag("critic_loss") == "losses/critic_loss"
    assert tag("alpha") == "losses/alpha"
    assert tag("batch_demo_share") == "charts/batch_demo_share"
    assert tag("updates_per_second") == "perf/updates_per_second"
    assert tag("episode_lag_updates") == "charts/episode_lag_updates"
    assert tag("bc_grad_norm") == "diagnostics/bc_grad_norm"
    assert tag("q_rank_gap") == "diagnostics/q_rank_gap"


def test_means_every_n_and_a_resume_appends(tmp_path):
    log = ScalarLog(tmp_path, every=2, suffix="learner-0")
    assert not log.add({"critic_loss": 1.0, "alpha": float("nan")}, step=10)
    assert log.add({"critic_loss": 3.0, "alpha": 0.5}, step=20)
    assert not log.add({"critic_loss": 5.0}, step=30)
    log.close()  # the odd call out is dropped, as a window not yet full
    again = ScalarLog(tmp_path, every=1, suffix="learner-0")
    again.add({"critic_loss": 7.0}, step=40)
    again.close()
    assert [p.name for p in tmp_path.iterdir()] == ["learner-0"]  # the instance's own directory
    got = read(tmp_path / "learner-0")
    assert got["losses/critic_loss"] == [(20, 2.0), (40, 7.0)]
    assert got["losses/alpha"] == [(20, 0.5)]  # the NaN was skipped, not averaged in


def test_nothing_is_written_before_the_first_window(tmp_path):
    log = ScalarLog(tmp_path / "tb", every=5, suffix="x")
    log.add({"critic_loss": 1.0}, step=1)
    log.close()
    assert not (tmp_path / "tb").exists()
