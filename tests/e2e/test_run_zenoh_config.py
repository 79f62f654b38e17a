"""`mea run --zenoh-config`: the embedded router and every service of the run over mutual TLS with
user/password authentication, from deploy/zenoh/tls-run.json5 with certificates made here, on
127.0.0.1 only; a plain-TCP client, a client without the run's password and one without a client
certificate get no session while the run trains to its budget."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from cryptography.hazmat.primitives import serialization

from mea_tools.bench.system import stop_run
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig, load_zenoh_file
from services.common.bus.zenoh_derive import client_config, loopback
from tests.e2e.test_zenoh_security import _CA, _write
from tests.helpers import find_free_port

ROOT = Path(__file__).resolve().parents[2]
BUDGET = 120
PASSWORD = "run-secret"
REFUSED_OPEN_MS = 2000


def _json(path: Path, conf: dict) -> str:
    path.write_text(json.dumps(conf, indent=2))  # JSON is JSON5
    return str(path)


def _run_file(tmp_path: Path, port: int) -> tuple[str, dict]:
    """deploy/zenoh/tls-run.json5 with its paths, password and endpoint replaced, and the PKI."""
    ca = _CA("mea test CA")
    (tmp_path / "ca.pem").write_bytes(ca.cert.public_bytes(serialization.Encoding.PEM))
    router = _write(tmp_path / "router", *ca.issue("router", server=True))
    run = _write(tmp_path / "run", *ca.issue("run", server=False))
    users = tmp_path / "users.txt"
    users.write_text(f"run:{PASSWORD}\nactor:actor-secret\n")
    conf = load_zenoh_file(str(ROOT / "deploy" / "zenoh" / "tls-run.json5"))
    values = {
        "listen/endpoints": [f"tls/127.0.0.1:{port}"],
        "transport/link/tls/listen_certificate": router[0],
        "transport/link/tls/listen_private_key": router[1],
        "transport/link/tls/root_ca_certificate": str(tmp_path / "ca.pem"),
        "transport/link/tls/connect_certificate": run[0],
        "transport/link/tls/connect_private_key": run[1],
        "transport/auth/usrpwd/dictionary_file": str(users),
        "transport/auth/usrpwd/password": PASSWORD,
    }
    for key, value in values.items():
        conf.insert_json5(key, json.dumps(value))
    pki = {"ca": str(tmp_path / "ca.pem"), "run": run}
    return _json(tmp_path / "run.json5", json.loads(str(conf))), pki


def _client(tmp_path: Path, name: str, port: int, pki: dict, *, scheme="tls", cert=True, user="run") -> str:
    tls: dict = {"root_ca_certificate": pki["ca"]}
    if cert:
        tls |= {
            "connect_certificate": pki["run"][0],
            "connect_private_key": pki["run"][1],
            "enable_mtls": True,
        }
    conf = {
        "mode": "client",
        "connect": {"endpoints": [f"{scheme}/127.0.0.1:{port}"], "timeout_ms": REFUSED_OPEN_MS},
        "transport": {"link": {"tls": tls}, "auth": {"usrpwd": {"user": user, "password": PASSWORD}}},
    }
    if user is None:
        del conf["transport"]["auth"]
    return _json(tmp_path / f"{name}.json5", conf)


def _open(path: str) -> ZenohBus:
    return ZenohBus(ZenohConfig(config_file=path, namespace="secure"))


def _refused(path: str) -> None:
    with pytest.raises(zenoh.ZError):
        _open(path).close()


@pytest.mark.e2e
@pytest.mark.timeout(240)
def test_mea_run_over_mutual_tls_with_a_password_and_plain_tcp_refused(tmp_path):
    port = find_free_port()
    router_file, pki = _run_file(tmp_path, port)
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "services.cli", "run", "--zenoh-config", router_file, "--namespace", "secure",
           "--task", "block_pull", "--variant", "equiobs", "--demos", "1", "--actors", "1",
           "--env-steps", str(BUDGET), "--services", "learner", "augmenter", "actor", "--learner-preset", "smoke",
           "--metrics-port", "0", "--run-dir", str(run_dir), "--log-format", "text"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)  # fmt: skip
    try:
        good = _client(tmp_path, "good", port, pki)
        deadline = time.monotonic() + 60
        while True:  # the run's router comes up
            try:
                client = _open(good)
                break
            except zenoh.ZError:
                assert time.monotonic() < deadline and proc.poll() is None, "mea run's router did not come up"
                time.sleep(0.5)
        with client:
            samples: list[str] = []
            sub = client.session.declare_subscriber(
                "mea/v1/secure/**", lambda s: samples.append(str(s.key_expr))
            )
            for _ in range(100):  # the run's services reach this client through the TLS router
                if samples:
                    break
                time.sleep(0.2)
            sub.undeclare()
            assert samples, "nothing from the run's services through the TLS router"
            _refused(_client(tmp_path, "plain", port, pki, scheme="tcp"))  # plain TCP to the TLS port
            _refused(_client(tmp_path, "no-password", port, pki, user=None))
            _refused(_client(tmp_path, "no-certificate", port, pki, cert=False))
        out, _ = proc.communicate(timeout=180)
    finally:
        stop_run(proc, 15)
    assert proc.returncode == 0, out[-3000:]
    assert "env-step budget reached" in out, out[-3000:]  # trained to its budget over the TLS router
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env_steps"] >= BUDGET and summary["episodes_recorded"] >= 2, summary
    client_file = run_dir / "zenoh-client.json5"
    assert stat.S_IMODE(client_file.stat().st_mode) == 0o600
    derived = json.loads(client_file.read_text())
    assert derived["mode"] == "client" and derived["connect"]["endpoints"] == [f"tls/127.0.0.1:{port}"]
    assert "listen_certificate" not in derived["transport"]["link"]["tls"] and "access_control" not in derived
    actor = json.loads((run_dir / "services" / "actor-0.json").read_text())
    assert actor["service"]["zenoh"]["config_file"] == str(client_file)


# ------------------------------------------------------------------------------------------------
# the derived client config and refusals (no network)
# ------------------------------------------------------------------------------------------------


@pytest.mark.unit
def test_the_client_config_keeps_what_a_client_presents_and_drops_what_only_a_router_uses():
    example = str(ROOT / "deploy" / "zenoh" / "tls-run.json5")
    derived = client_config(example, ["tls/0.0.0.0:7447"])
    assert derived["mode"] == "client" and derived["connect"] == {"endpoints": ["tls/127.0.0.1:7447"]}
    assert derived["transport"]["link"] == {
        "protocols": ["tls"],
        "tls": {
            "root_ca_certificate": "/etc/mea/zenoh/ca.pem",
            "enable_mtls": True,
            "connect_certificate": "/etc/mea/zenoh/run.pem",
            "connect_private_key": "/etc/mea/zenoh/run.key",
        },
    }
    assert derived["transport"]["auth"] == {"usrpwd": {"user": "run", "password": "change-me"}}
    assert not {"listen", "access_control", "plugins", "id"} & derived.keys()
    assert (
        loopback("tcp/[::]:7447") == "tcp/[::1]:7447" and loopback("tls/10.0.0.5:7447") == "tls/10.0.0.5:7447"
    )


@pytest.mark.unit
@pytest.mark.parametrize(
    ("conf", "says"),
    [
        ({"transport": {"link": {"tls": {"enable_mtls": True, "listen_certificate": "/r.pem"}}}},
         "connect_certificate and connect_private_key"),
        ({"transport": {"auth": {"usrpwd": {"dictionary_file": "/users.txt"}}}}, "usrpwd/user and password"),
        ({"listen": {"endpoints": ["tcp/127.0.0.1:0"]}}, "fixed listen port"),
    ],
)  # fmt: skip
def test_a_router_file_the_runs_services_could_not_join_is_refused_before_anything(
    tmp_path, capsys, conf, says
):
    from services.cli import main

    path = _json(tmp_path / "router.json5", {"mode": "router", **conf})
    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        main(["run", "--zenoh-config", path, "--run-dir", str(run_dir), "--metrics-port", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert "--zenoh-config" in err[0] and says in err[0] and "Traceback" not in err[0], err
    assert not run_dir.exists()


@pytest.mark.unit
def test_zenoh_config_is_refused_with_in_process_and_for_a_missing_file(tmp_path):
    from services.run_config import RunConfig

    example = str(ROOT / "deploy" / "zenoh" / "tls-run.json5")
    assert RunConfig(zenoh_config=example).zenoh_config == example
    with pytest.raises(ValueError, match="--zenoh-config configures the Zenoh router; --in-process"):
        RunConfig(zenoh_config=example, in_process=True)
    with pytest.raises(ValueError, match=r"--zenoh-config: Zenoh config file .*nope.json5: no such file"):
        RunConfig(zenoh_config=str(tmp_path / "nope.json5"))
    with pytest.raises(ValueError, match="contradicts listen/endpoints"):
        RunConfig(zenoh_config=example, listen="tcp/127.0.0.1:9999")
