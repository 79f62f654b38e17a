"""Every `mea` command refuses bad input in one line naming the option, exit code 2, and leaves the
disk as it was (checksums before and after); OS errors are one line too. docs/cli.md has the rules."""

from __future__ import annotations

import importlib.metadata
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from services.common import config
from services.run_config import RunConfig
from tests.helpers import port_is_free
from tests.helpers.cli import run_cli
from tests.helpers.tree import snapshot

ROOT = Path(__file__).resolve().parents[2]


class WouldStartError(AssertionError):
    """`mea run` accepted the command line and was about to start the stack."""


def would_start(*_args, **_kw):
    raise WouldStartError


@pytest.fixture
def here(tmp_path, monkeypatch) -> Path:
    """A working directory holding a file, a saved run, and two runs whose config.json is damaged;
    `mea run` cannot start a stack here (a case accepted by mistake fails instead of training)."""
    import services.launcher

    monkeypatch.setattr(services.launcher, "run", would_start)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("not a directory\n")
    config.save(
        RunConfig(task="drawer_open", env_steps=300, run_dir=tmp_path / "run"),
        tmp_path / "run" / "config.json",
    )
    (tmp_path / "list").mkdir()
    (tmp_path / "list" / "config.json").write_text("[1, 2]\n")
    (tmp_path / "task42").mkdir()
    (tmp_path / "task42" / "config.json").write_text(json.dumps({"task": 42, "resumes": 0}) + "\n")
    return tmp_path


REFUSED = [
    (["run", "--task", "nope"], "mea run: --task must be one of block_pull, block_pick, drawer_open"),
    (["run", "--learner-preset", "nope"], "mea run: --learner-preset must be one of paper, cpu-small, smoke"),
    (["run", "--run-dir", "afile"], "mea run: --run-dir afile: afile is a file, not a directory"),
    (["run", "--run-dir", "afile/run"], "mea run: --run-dir afile/run: afile is a file, not a directory"),
    (
        ["run", "--run-dir", "run"],
        "mea run: --run-dir run holds a run already: continue it with --resume run",
    ),
    (["run", "--resume", "list"], "mea run: --resume list: config.json holds a list, not a run's settings"),
    (["run", "--resume", "task42"], "mea run: --resume task42: config.json is damaged: its task is 42"),
    (["run", "--resume", "missing"], "mea run: --resume missing: no such run directory"),
    (["run", "--resume", "afile"], "mea run: --resume afile: no such run directory"),
    (["run", "--resume", "run", "--task", "block_pull"], "mea run: --task cannot change on --resume"),
    (
        ["run", "--resume", "run", "--seed", "1", "--no-record"],
        "mea run: --record, --seed cannot change on --resume",
    ),
    (
        ["run", "--actors", "x"],
        "mea run: --actors INT|{auto}: no type matching INT|{auto} could be instantiated",
    ),
    (["run", "--actors", "-1"], "mea run: --actors must be >= 0 or auto, not -1"),
    (["run", "--bogus"], "mea run: unrecognized option(s) --bogus (see mea run --help)"),
    (["run", "--preset", "nope"], "mea run: argument --preset: invalid choice: 'nope'"),
    (["serve", "--weights", "missing/run"], "mea serve: --weights missing/run: the path does not exist"),
    (["demos", "--out", "afile/d.mcap"], "mea demos: --out: 'afile' is a file, not a directory"),
    (["plot"], "mea plot: the following arguments are required: RUN_DIR"),
    (["nope"], "mea: unknown command 'nope'; choose from run, router"),
    (["learner", "--preset", "cpu-small", "--batch-size", "-"], "mea learner: --batch-size INT:"),
    # the algorithm's own config: its checks, and another algorithm's flags
    (["learner", "--algorithm", "gasv2"], "mea learner: --algorithm 'gasv2' starts from a gasv2 preset"),
    (["learner", "--preset", "gasv2", "--chunk-length", "0"], "mea learner: chunk_length must be >= 1"),
    (["learner", "--dreamer.deter", "3"], "mea learner: unrecognized option(s) --dreamer.deter 3"),
]


@pytest.mark.parametrize(("argv", "message"), REFUSED, ids=[" ".join(a) for a, _ in REFUSED])
def test_bad_input_is_one_line_naming_the_option_exit_2_and_nothing_on_disk_changes(
    argv, message, here, capsys
):
    before = snapshot(here)
    code, out, err = run_cli(argv, capsys)
    assert code == 2, (out, err)
    assert err.splitlines() == [err.strip()] and err.startswith(message), err
    assert "Traceback" not in out + err
    assert snapshot(here) == before


def _busy_port_above_free_ones(free_below: int) -> socket.socket:
    """A listening socket on a port whose ``free_below`` ports under it are free: an ephemeral port
    alone may sit just above another process's, and the run would then name that one."""
    for _ in range(50):
        busy = socket.socket()
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        if all(port_is_free(port - k) for k in range(1, free_below + 1)):
            return busy
        busy.close()
    raise RuntimeError(f"no ephemeral port with {free_below} free ports under it in 50 tries")


@pytest.mark.parametrize("offset", [0, 1])  # the launcher's own port, the learner's (base + 1)
def test_a_taken_metrics_port_is_one_line_before_anything_starts(offset, tmp_path, monkeypatch, capsys):
    import services.launcher

    here = tmp_path
    monkeypatch.chdir(here)
    monkeypatch.setattr(services.launcher, "_router", would_start)  # the check comes before the router
    with _busy_port_above_free_ones(offset) as busy:
        port = busy.getsockname()[1]
        base = port - offset
        before = snapshot(here)
        code, out, err = run_cli(["run", "--metrics-port", str(base), "--run-dir", "fresh"], capsys)
    who = "the launcher" if offset == 0 else "learner-0"
    assert code == 2, (out, err)
    assert err.splitlines() == [
        f"mea run: --metrics-port {base}: port {port} ({who}'s /metrics) on 127.0.0.1 is unavailable "
        "(Address already in use; another run on this host?): give this run another base, e.g. "
        "--metrics-port 9200, or 0 for none"
    ], err
    assert snapshot(here) == before


def test_a_refused_resume_leaves_the_run_as_it_was(here, capsys):
    saved = (here / "run" / "config.json").read_text()
    for argv in (["--task", "block_pull"], ["--learner-preset", "paper"], ["--env-steps", "-5"], ["--actors", "x"],
                 ["--eval-every", "0"], ["--env-steps", "400", "--demos", "3"]):  # fmt: skip
        code, _, err = run_cli(["run", "--resume", "run", *argv], capsys)
        assert code == 2 and "Traceback" not in err, err
    assert (here / "run" / "config.json").read_text() == saved
    assert sorted(p.name for p in (here / "run").iterdir()) == ["config.json"]


def test_an_os_error_is_one_line_with_exit_code_1_and_writes_nothing(here, capsys):
    # /sys refuses new files even to root: the permission error a user gets in a read-only directory
    assert not os.access("/sys/mea-cli-test", os.F_OK)
    before = snapshot(here)
    code, out, err = run_cli(["demos", "--n", "1", "--out", "/sys/d.mcap"], capsys)
    assert code == 1, (out, err)
    assert err.strip().splitlines()[-1] == "mea demos: Permission denied: /sys/d.mcap.tmp", err
    assert "Traceback" not in out + err
    assert snapshot(here) == before and not Path("/sys/d.mcap.tmp").exists()


@pytest.mark.slow
def test_a_busy_listen_port_is_one_line_and_leaves_no_run_directory(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        out = subprocess.run([sys.executable, "-m", "services.cli", "run", "--listen", f"tcp/127.0.0.1:{port}",
                              "--metrics-port", "0", "--run-dir", str(tmp_path / "run")], cwd=ROOT,
                             env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True, text=True,
                             timeout=120)  # fmt: skip
    assert out.returncode == 2, out.stderr
    assert out.stdout == ""
    assert out.stderr.splitlines() == [
        f"mea run: --listen tcp/127.0.0.1:{port}: cannot start the Zenoh router there: "
        "Address already in use (os error 98)"
    ], out.stderr
    assert list(tmp_path.iterdir()) == []


def test_version_bare_mea_and_help(capsys):
    code, out, err = run_cli(["--version"], capsys)
    assert (code, out, err) == (0, f"mea {importlib.metadata.version('mea-rl')}\n", "")
    code, out, err = run_cli([], capsys)
    assert code == 2 and out == "" and err.startswith("usage: mea COMMAND") and "  run " in err
    code, out, err = run_cli(["--help"], capsys)
    assert code == 0 and out.startswith("usage: mea COMMAND") and err == ""


def test_every_help_names_the_presets_correctly(capsys):
    code, out, _ = run_cli(["learner", "--help"], capsys)
    assert code == 0
    text = " ".join(out.split())
    assert ("Presets (--preset NAME, read before the other flags): paper, cpu-small, smoke, cpu-small-state, "
            "gasv2, gasv2-cpu-small, gasv2-smoke; default paper.") in text  # fmt: skip
    for command in ("run", "demos", "serve", "evaluator"):  # one preset: nothing to choose, no line
        code, out, _ = run_cli([command, "--help"], capsys)
        assert code == 0 and out.startswith(f"usage: mea {command}") and "Presets" not in out
        assert "default; default default" not in out
    assert config.presets_line({"a": 1, "b": 2}) == (
        "Presets (--preset NAME, read before the other flags): a, b; default a."
    )


@pytest.mark.slow
def test_pybullet_banner_never_reaches_the_terminal():
    """pybullet prints its build time from C when imported; `mea` output shows only its own lines."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", "import services.tasks, pybullet; print('ok')"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert (out.stdout, out.stderr) == ("ok\n", "")
    out = subprocess.run([sys.executable, "-m", "services.cli", "run", "--actors", "x"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode == 2 and out.stdout == ""
    assert (
        out.stderr
        == "mea run: --actors INT|{auto}: no type matching INT|{auto} could be instantiated from ['x'].\n"
    )
    # the banner is there to hide: pybullet imported on its own prints it
    raw = subprocess.run(
        [sys.executable, "-c", "import pybullet"], capture_output=True, text=True, timeout=120
    )
    assert "pybullet build time" in raw.stdout + raw.stderr
