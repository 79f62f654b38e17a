"""`mea bench learner`: the paper preset is compared with the public code at the same thread count."""

from __future__ import annotations

import pytest

from services.bench.learner import same_threads_rows

PAPER = {"variant": "paper:c4", "s/update (median)": 2.0}


@pytest.mark.parametrize(("threads", "public"), [(1, 15.4), (2, 11.1)])
def test_the_public_figure_is_the_one_measured_at_the_same_thread_count(threads, public):
    (row,) = same_threads_rows(PAPER, threads)
    assert row["threads"] == threads and row["public s/update"] == public
    assert row["ratio"] == pytest.approx(public / 2.0)


def test_no_row_without_a_public_figure_or_a_paper_row():
    assert same_threads_rows(PAPER, 4) == []
    assert same_threads_rows(None, 1) == []
