"""`mea bench compare` on fake run directories: arms from different benches side by side with
hand-computed numbers, what differs between them, an earlier comparison point, and every refusal in
one line with nothing written."""

from __future__ import annotations

import json

import pytest

from mea_tools.bench.compare import CompareBenchConfig, run
from tests.unit.test_bench_learning import BUDGET, PNG_MAGIC, REPS, make_run

pytestmark = pytest.mark.unit


def arms(tmp_path):
    """Box: 0.2 / 0.4 / 0.3 at the budget; disc (its own bench, another learner flag): 0.6 / 0.8 / 0.7."""
    box, disc = tmp_path / "bench-box", tmp_path / "bench-disc"
    for seed, (mid, end) in enumerate([(0.1, 0.2), (0.3, 0.4), (0.2, 0.3)]):
        make_run(box, "mea", seed, [(0, 0.0), (10_000, mid), (BUDGET, end)], demos=2)
    for seed, (mid, end) in enumerate([(0.5, 0.6), (0.7, 0.8), (0.6, 0.7)]):
        make_run(disc, "mea", seed, [(0, 0.0), (10_000, mid), (BUDGET, end)], demos=2,
                 learner_args="--net.xy-range=disc")  # fmt: skip
    return box, disc


def test_two_benches_compared_with_hand_computed_numbers_and_what_differs(tmp_path, capsys):
    box, disc = arms(tmp_path)
    out = tmp_path / "cmp"
    cfg = CompareBenchConfig(arms=(f"box={box}", f"disc={disc}"), out=out, json=True, bootstrap_reps=REPS)
    run(cfg)
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads((out / "result-block_pull.json").read_text())
    assert (out / "curves-block_pull.png").read_bytes().startswith(PNG_MAGIC)
    r = printed["results"]
    assert r["what differs between the arms"] == [
        {"setting": "learner_args", "box": "", "disc": "--net.xy-range=disc"}
    ]
    assert [a["seeds"] for a in r["arms"]] == [[0, 1, 2], [0, 1, 2]]
    means = {row["variant"]: row["success at budget (mean)"] for row in r["comparison"]}
    assert means == pytest.approx({"box": 0.3, "disc": 0.7})
    # AUC (trapezoid over 0-20K): box s0 = (0.1/2 + (0.1 + 0.2)/2) / 2 = 0.1, s1 0.25, s2 0.175;
    # disc s0 = (0.5/2 + 1.1/2) / 2 = 0.4, s1 0.55, s2 0.475
    aucs = {row["variant"]: row["AUC (mean)"] for row in r["learning speed"]}
    assert aucs["box"] == pytest.approx(0.175) and aucs["disc"] == pytest.approx(0.475)
    (against,) = r["against the first arm"]
    assert (against["variant"], against["against"]) == ("disc", "box")
    assert against["P(improvement)"] == pytest.approx(1.0)  # every disc run above every box run
    assert against["success at budget"].startswith("separated")
    assert printed["meta"]["shared settings"]["env_steps"] == BUDGET
    assert printed["meta"]["baseline"] == "box"


def test_an_earlier_point_compares_the_evaluations_there(tmp_path, capsys):
    box, disc = arms(tmp_path)
    run(
        CompareBenchConfig(
            arms=(f"box={box}", f"disc={disc}"), at_env_steps=10_000, json=True, bootstrap_reps=REPS
        )
    )
    printed = json.loads(capsys.readouterr().out)
    means = {row["variant"]: row["success at budget (mean)"] for row in printed["results"]["comparison"]}
    assert means == pytest.approx({"box": 0.2, "disc": 0.6})
    assert printed["meta"]["success at env steps"] == 10_000


def test_a_run_saved_before_a_setting_existed_reads_its_default(tmp_path, capsys):
    box, disc = arms(tmp_path)
    cfg_file = box / "block_pull-mea-s0" / "config.json"
    saved = json.loads(cfg_file.read_text())
    assert saved.pop("gripper_start") == "random"
    cfg_file.write_text(json.dumps(saved))
    run(CompareBenchConfig(arms=(f"box={box}", f"disc={disc}"), json=True, bootstrap_reps=REPS))
    assert json.loads(capsys.readouterr().out)["meta"]["shared settings"]["gripper_start"] == "random"


@pytest.mark.parametrize(
    ("case", "says"),
    [
        ("one arm", "at least two --arms"),
        ("no label", "LABEL=DIR"),
        ("label twice", "given twice"),
        ("not a run", "neither a run directory"),
        ("other budget", "env_steps 30000"),
        ("mixed arm", "mixes runs with learner_args"),
        ("run in two arms", "in two arms"),
        ("out is a file", "is a file"),
        ("negative point", "--at-env-steps must be >= 0"),
    ],
)
def test_bad_arms_are_refused_in_one_line_and_nothing_is_written(tmp_path, case, says):
    box, disc = arms(tmp_path)
    out = tmp_path / "cmp"
    specs = (f"box={box}", f"disc={disc}")
    kw = {}
    if case == "one arm":
        specs = specs[:1]
    elif case == "no label":
        specs = (str(box), f"disc={disc}")
    elif case == "label twice":
        specs = (f"box={box}", f"box={disc}")
    elif case == "not a run":
        (tmp_path / "empty").mkdir()
        specs = (f"box={box}", f"disc={tmp_path / 'empty'}")
    elif case == "other budget":
        make_run(tmp_path / "bench-long", "mea", 0, [(0, 0.0), (30_000, 0.5)], budget=30_000, demos=2)
        specs = (f"box={box}", f"long={tmp_path / 'bench-long'}")
    elif case == "mixed arm":
        specs = (f"box={box / 'block_pull-mea-s1'}", f"both={disc},{box / 'block_pull-mea-s0'}")
    elif case == "run in two arms":
        specs = (f"box={box}", f"again={box / 'block_pull-mea-s1'}")
    elif case == "out is a file":
        out.write_text("keep me")
    elif case == "negative point":
        kw["at_env_steps"] = -1
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(SystemExit) as exc:
        run(CompareBenchConfig(arms=specs, out=out, bootstrap_reps=REPS, **kw))
    message = str(exc.value.code)
    assert message.startswith("mea bench compare: ") and says in message and "\n" not in message
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
