"""`mea audit` (mea_tools.audit): one JSON object with every kind the augmenter stores, each
copy either simulated or counted as not simulable."""

from __future__ import annotations

import json

import pytest

from mea_tools.audit.cli import main

pytestmark = pytest.mark.unit


@pytest.mark.timeout(120)
@pytest.mark.slow
def test_cli_prints_one_json_object(capsys):
    argv = [
        "--task",
        "block_pick",
        "--episodes",
        "1",
        "--copies",
        "1",
        "--isometric",
        "3",
        "--views",
        "1",
        "--json",
    ]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["benchmark"] == "audit" and "isometric" in out["meta"]["augmentation"]
    rows = {
        row["kind"]: row
        for row in out["results"][
            "validity per kind (raw demonstrations, isometric, MEA, MEA∘isometric copies)"
        ]
    }
    assert list(rows) == ["raw", "isometric", "mea", "mea+isometric", "all"]
    assert rows["raw"]["episodes"] == 1 and rows["mea"]["episodes"] == 1
    assert rows["isometric"]["episodes"] == 3 and rows["mea+isometric"]["episodes"] == 1
    for kind, row in rows.items():  # every copy is either simulated or reported as not simulable
        assert row["simulated"] + row["not simulable"] == row["episodes"]
        assert out["meta"]["valid_pct"][kind] == row["valid %"]
    assert rows["all"]["transitions"] == sum(
        rows[k]["transitions"] for k in ("raw", "isometric", "mea", "mea+isometric")
    )
    assert rows["raw"]["valid %"] == 100.0 and rows["mea"]["valid %"] >= 90.0
    phase_rows = out["results"]["validity per kind and phase"]
    assert [row["phase"] for row in phase_rows if row["kind"] == "mea"] == [
        "non_trivial",
        "trivial",
        "termination",
        "all",
    ]
    assert out["meta"]["tolerance_covers_floor"] is True and out["meta"]["rotated_views"] >= 1


@pytest.mark.timeout(120)
@pytest.mark.slow
def test_cli_audits_surgical_copies_against_their_noise_floor(capsys):
    argv = ["--task", "surgical_grasp_any", "--episodes", "1", "--copies", "3", "--json"]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    meta = out["meta"]
    assert (
        meta["task"] == "surgical_grasp_any"
        and meta["copies"] == 3
        and set(meta["valid_pct"]) == {"raw", "mea"}
    )
    assert meta["valid_pct"]["raw"] == 100.0 and meta["valid_pct"]["mea"] >= 90.0
    assert all(meta["tolerance_covers_floor"].values()) and meta["valid_pct_moved"] is not None
    runtime = out["results"]["copies and runtime"][0]
    assert runtime["copies made"] == 3 and runtime["moved transitions"] > 0
