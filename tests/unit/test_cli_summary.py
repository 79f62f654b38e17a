"""The summary `mea run` prints when it ends: final success with its 95% Wilson interval, the best
evaluation, counts, wall time, where the curves, recording and weights are, and how to serve them."""

from __future__ import annotations

import pytest
from scipy.stats import binomtest

from services.common import weights_file
from services.evaluator.history import append_history
from services.status_board import end_of_run, wilson_interval
from tests.helpers import build_weights


@pytest.mark.parametrize("n", [1, 2, 5, 20, 50, 137])
def test_the_wilson_interval_is_scipys(n):
    for k in sorted({0, 1, n // 3, n // 2, n - 1, n}):
        ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert wilson_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-12), (k, n)
    assert wilson_interval(0, n)[0] == pytest.approx(0.0, abs=1e-15) and wilson_interval(n, n)[
        1
    ] == pytest.approx(1.0)
    with pytest.raises(ValueError):
        wilson_interval(n + 1, n)


def record(version: int, env_steps: int, successes: list[bool], at_budget: bool = False) -> dict:
    return {"version": version, "env_steps": env_steps, "success_rate": sum(successes) / len(successes),
            "episodes": len(successes), "successes": successes, "at_budget": at_budget}  # fmt: skip


def test_the_end_of_run_summary_says_what_the_run_achieved_and_where_it_is(tmp_path):
    run = tmp_path / "my run"
    for r in (record(2, 1000, [True] * 3 + [False] * 17), record(5, 2000, [True] * 9 + [False] * 11),
              record(8, 3000, [True] * 14 + [False] * 36, at_budget=True)):  # fmt: skip
        append_history(run / "eval" / "history.jsonl", r)
    for v in (7, 8):
        weights_file.write(run / weights_file.LEARNER, build_weights(v))
    (run / "episodes").mkdir()
    (run / "episodes" / "raw-0-0000.mcap").write_bytes(b"x" * 2**20)
    (run / "curves.png").write_bytes(b"png")
    summary = {"elapsed_seconds": 90.0, "env_steps": 3050, "updates": 700,
               "total": {"sittings": 2, "elapsed_seconds": 300.0, "env_steps": 3050, "updates": 700}}  # fmt: skip
    text = end_of_run(run, summary, "env-step budget reached")
    lo, hi = wilson_interval(14, 50)
    lines = text.splitlines()
    assert lines[0] == f"mea run: stopped (env-step budget reached). Summary of {run}:"
    assert lines[1].split() == ["final", "success", "28%", "(14", "of", "50", "episodes", "at", "3,000", "env",
                                "steps,", "weights", "v8);", "95%", "CI", f"{lo:.0%}-{hi:.0%}", "(Wilson)"]  # fmt: skip
    assert (f"{lo:.0%}", f"{hi:.0%}") == ("17%", "42%")
    assert (
        " ".join(lines[2].split())
        == "best evaluation 45% (9 of 20) at 2,000 env steps, weights v5 (3 evaluations)"
    )
    assert " ".join(lines[3].split()) == (
        "env steps 3,050 · updates 700 · wall time 1.5 min (this sitting; 5.0 min over 2 sittings)"
    )
    assert " ".join(lines[4].split()) == f"curves {run / 'curves.png'}"
    assert " ".join(lines[5].split()) == f"recording {run / 'episodes'} (1 file, 1.0 MiB)"
    assert (
        " ".join(lines[6].split()) == f"weights {run / 'learner/weights/weights-00000008.blob'} (newest of 2)"
    )
    assert " ".join(lines[7].split()) == (
        f"serve it mea serve --weights '{run}' --service.run-key-file '{run / 'run.key'}'"
    )
    plain = end_of_run(run, summary, "duration reached", authenticated=False)
    assert plain.splitlines()[-1].endswith(f"mea serve --weights '{run}'")  # no key to give


def test_a_run_stopped_before_any_evaluation_says_so(tmp_path):
    text = end_of_run(tmp_path, {"elapsed_seconds": 12.0, "env_steps": None}, "interrupted")
    lines = [" ".join(line.split()) for line in text.splitlines()]
    assert lines[1] == "evaluations none"
    assert lines[2] == "env steps — · updates — · wall time 0.2 min"
    assert lines[4:] == ["recording none", "weights none written", "serve it (no weights yet)"]
    # no evaluation at the budget yet: the newest is reported as such
    append_history(tmp_path / "eval" / "history.jsonl", record(1, 500, [False, True]))
    assert " ".join(end_of_run(tmp_path, {}, "x").splitlines()[1].split()).startswith(
        "newest success 50% (1 of 2 episodes at 500 env steps"
    )
