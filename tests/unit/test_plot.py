"""`mea plot`: histories of several run dirs -> a PNG and a summary table; clear errors for bad input."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from services.evaluator.history import append_history
from services.evaluator.plot import group_runs, load_run, main, summary_row

pytestmark = pytest.mark.unit

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def make_run(root, name: str, curve: list[tuple[int, float]], variant: str | None = None):
    run_dir = root / name
    run_dir.mkdir()
    if variant is not None:
        (run_dir / "config.json").write_text(json.dumps({"task": "block_pull", "variant": variant}))
    for version, (steps, success) in enumerate(curve, start=1):
        append_history(run_dir / "eval" / "history.jsonl",
                       {"version": version, "env_steps": steps, "success_rate": success, "episodes": 10})  # fmt: skip
    return run_dir


def test_two_seeds_of_one_variant_and_a_baseline_render_to_a_png_with_a_table(tmp_path, capsys):
    a = make_run(tmp_path, "mea-s0", [(0, 0.0), (250, 0.1), (500, 0.4)], variant="mea")
    b = make_run(tmp_path, "mea-s1", [(0, 0.0), (250, 0.3), (500, 0.6)], variant="mea")
    c = make_run(tmp_path, "base-s0", [(0, 0.0), (250, 0.0), (500, 0.0)])  # no config: labelled by dir
    out = tmp_path / "plots" / "curves.png"
    assert main([str(a), str(b), str(c), "--out", str(out)]) == 0
    data = out.read_bytes()
    assert len(data) > 1000 and data.startswith(PNG_MAGIC)
    text = capsys.readouterr().out
    lines = text.splitlines()
    mea_row = next(line for line in lines if line.startswith("mea "))
    assert mea_row.split()[1:3] == ["2", "6"]  # 2 runs, 6 evaluations
    assert "0.50 ± 0.10" in mea_row  # final success of the seeds: 0.4 and 0.6
    assert "250 (2/2)" in mea_row  # both seeds improve at 250 steps
    base_row = next(line for line in lines if line.startswith("base-s0"))
    assert "0.00 ± 0.00" in base_row and "— (0/1)" in base_row
    assert str(out) in text


def test_group_means_match_the_histories(tmp_path):
    a = make_run(tmp_path, "a", [(0, 0.0), (100, 0.5), (200, 1.0)], variant="x")
    b = make_run(tmp_path, "b", [(50, 0.2), (150, 0.4)], variant="x")
    (g,) = group_runs([load_run(a, "variant"), load_run(b, "variant")])
    assert g.label == "x" and len(g.runs) == 2
    assert g.grid.tolist() == [0, 50, 100, 150, 200]
    np.testing.assert_allclose(g.mean, [0.0, 0.1, 0.35, 0.45, 1.0])
    row = summary_row(g)
    assert row["improvement_of_mean"] == 50 and row["improvement_mean"] == pytest.approx(75.0)  # 100 and 50
    # --label-by reaches other keys; a missing key falls back to the directory name
    assert load_run(a, "task").label == "block_pull" and load_run(a, "nope.deeper").label == "a"


def test_linear_interpolation_option_renders_too(tmp_path):
    a = make_run(tmp_path, "a", [(0, 0.0), (100, 1.0)])
    out = tmp_path / "lin.png"
    assert main([str(a), "--out", str(out), "--interp", "linear", "--title", "t"]) == 0
    assert out.read_bytes().startswith(PNG_MAGIC)


def test_a_run_dir_without_history_exits_2_naming_the_path(tmp_path, capsys):
    good = make_run(tmp_path, "good", [(0, 0.0)])
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "never.png"
    assert main([str(good), str(empty), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(empty / "eval" / "history.jsonl") in err and "no evaluation history" in err
    assert not out.exists()


def test_a_history_with_no_usable_evaluation_exits_2(tmp_path, capsys):
    run_dir = tmp_path / "unknown-steps"
    append_history(run_dir / "eval" / "history.jsonl", {"version": 1, "env_steps": -1, "success_rate": 0.5})
    assert main([str(run_dir), "--out", str(tmp_path / "x.png")]) == 2
    assert str(run_dir / "eval" / "history.jsonl") in capsys.readouterr().err


def test_plot_is_registered_in_the_cli():
    from services.cli import COMMANDS, available

    assert COMMANDS["plot"][0] == "services.evaluator.plot" and available("plot")


def test_the_table_has_the_auc_beside_final_success(tmp_path, capsys):
    # a: (0+1)/2*100 + 1*100 = 150 over 200 -> 0.75; b: (0+.5)/2*200 = 50 over 200 -> 0.25
    a = make_run(tmp_path, "a", [(0, 0.0), (100, 1.0), (200, 1.0)], variant="x")
    b = make_run(tmp_path, "b", [(0, 0.0), (200, 0.5)], variant="x")
    (g,) = group_runs([load_run(a, "variant"), load_run(b, "variant")])
    row = summary_row(g)
    assert row["auc_mean"] == pytest.approx(0.5) and row["auc_std"] == pytest.approx(0.25)
    # the mean curve (hold): [0, .5, .75] at [0, 100, 200]: (0+.5)/2*100 + (.5+.75)/2*100 = 87.5 over 200
    assert row["auc_of_mean"] == pytest.approx(0.4375)
    assert main([str(a), str(b), "--out", str(tmp_path / "c.png")]) == 0
    head, _, body = capsys.readouterr().out.splitlines()[:3]
    assert head.index("final success") < head.index("AUC") < head.index("improvement")
    cells = re.split(r"\s{2,}", body)
    assert cells[:5] == ["x", "2", "5", "0.75 ± 0.25", "0.50 ± 0.25"]  # final success (1, .5), AUC (.75, .25)
    assert body.index("0.50 ± 0.25") == head.index("AUC")  # under its heading
