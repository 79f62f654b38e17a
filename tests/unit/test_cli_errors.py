"""Bad command lines end with exit code 2 and a message naming the option and what it allows: no
traceback, and nothing written."""

from __future__ import annotations

import pytest

from services.cli import main

CASES = [
    (["demos", "--task", "nope"], "--task must be one of block_pick, block_pull"),
    (["demos", "--style", "bogus"], "--style must be alternate, probe or direct"),
    (["demos", "--n", "0"], "--n must be >= 1"),
    (["demos", "--n", "-1"], "--n must be >= 1"),
    (["demos", "--seed-base", "-5"], "--seed-base must be >= 0"),
    (["demos", "--max-attempts", "-3"], "--max-attempts must be >= 0"),
    (["audit", "--task", "nope"], "--task must be one of block_pick, block_pull"),
    (["bench", "learner", "--variants", "bad"], "--variants: unknown preset 'bad'"),
    (["bench", "learner", "--variants", "paper:c8"], "--variants: unknown group 'c8'"),
    (["run", "--variant", "nope"], "variant must be one of"),
    (["run", "--restart-limit", "-1"], "restart_limit must be >= 0"),
]


@pytest.mark.parametrize(("argv", "message"), CASES, ids=[" ".join(a) for a, _ in CASES])
def test_a_bad_option_exits_2_naming_it(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    err = " ".join(capsys.readouterr().err.replace("│", " ").split())  # unwrap tyro's box
    assert message in err and "Traceback" not in err, err
    assert not list(tmp_path.iterdir())  # nothing written


def test_demos_out_names_a_missing_directory_and_an_existing_file(capsys, tmp_path):
    with pytest.raises(SystemExit) as exit_:
        main(["demos", "--out", str(tmp_path / "missing" / "d.mcap")])
    err = " ".join(capsys.readouterr().err.replace("│", " ").split())
    assert exit_.value.code == 2 and "--out: the directory" in err and "does not exist" in err, err
    assert not (tmp_path / "missing").exists()  # not created
    (tmp_path / "d.mcap").write_bytes(b"x")
    with pytest.raises(SystemExit) as exit_:
        main(["demos", "--out", str(tmp_path / "d.mcap")])
    err = " ".join(capsys.readouterr().err.replace("│", " ").split())
    assert exit_.value.code == 2 and "pass --overwrite to replace it" in err
    assert (tmp_path / "d.mcap").read_bytes() == b"x"
