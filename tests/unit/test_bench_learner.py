"""`mea bench learner`: the paper preset is compared with the public code at the same thread count;
checkpoints are timed whole against incremental."""

from __future__ import annotations

import pytest

from mea_tools.bench.learner import LearnerBenchConfig, bench_checkpoints, bench_updates, same_threads_rows

PAPER = {"variant": "paper:c4", "s/update (median)": 2.0}


@pytest.mark.parametrize(("threads", "public"), [(1, 15.4), (2, 11.1)])
def test_the_public_figure_is_the_one_measured_at_the_same_thread_count(threads, public):
    (row,) = same_threads_rows(PAPER, threads)
    assert row["threads"] == threads and row["public s/update"] == public
    assert row["ratio"] == pytest.approx(public / 2.0)


def test_no_row_without_a_public_figure_or_a_paper_row():
    assert same_threads_rows(PAPER, 4) == []
    assert same_threads_rows(None, 1) == []


def test_the_update_benchmark_runs_each_preset_on_the_batches_it_really_sees():
    # cpu-small-state's critic reads privileged rows: the benchmark's replay must carry them
    cfg = LearnerBenchConfig(variants=("cpu-small:c4", "cpu-small-state:c4"), updates=1, episodes=8)
    rows = bench_updates(cfg)
    assert [r["critic"] for r in rows] == ["image", "state"]
    assert [r["shared encoder"] for r in rows] == [True, False]
    for row in rows:
        assert row["demo share"] == 0.5 and row["timed updates"] == 1
        assert 0.0 < row["s/update (median)"] < 60.0


def test_the_checkpoint_rows_time_the_whole_replay_against_only_the_new_episodes():
    (row,) = bench_checkpoints(LearnerBenchConfig(checkpoint_episodes=40))
    assert (row["replay episodes"], row["new since the last"]) == (42, 2)
    # the segment holds 2 of the 42 episodes: its bytes are about that share of the whole file's
    assert 0.03 < row["segments bytes"] / row["whole replay bytes"] < 0.08
    assert row["ratio (bytes)"] == pytest.approx(row["whole replay bytes"] / row["segments bytes"])
    assert bench_checkpoints(LearnerBenchConfig(checkpoint_episodes=0)) == []
    with pytest.raises(ValueError, match="checkpoint-episodes"):
        LearnerBenchConfig(checkpoint_episodes=-1)
