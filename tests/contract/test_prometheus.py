"""The Prometheus configs and rules in deploy/prometheus: promtool accepts them and their unit tests pass,
and every metric they use is one the services export (names derived from the code by
``tests.helpers.metric_names``, not listed here)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from services.common.metrics import DEFAULT_PORTS
from tests.helpers.metric_names import exported_metric_names, undefined

pytestmark = pytest.mark.contract

ROOT = Path(__file__).resolve().parents[2]
PROM = ROOT / "deploy" / "prometheus"
CONFIGS = ("prometheus.yml", "prometheus-local.yml")
RULES = PROM / "rules" / "mea.yml"
RULE_TESTS = PROM / "tests" / "mea_test.yml"

PROMTOOL = shutil.which("promtool")
needs_promtool = pytest.mark.skipif(
    PROMTOOL is None,
    reason="promtool not on PATH: install the distribution's prometheus package "
    "(apt-get install prometheus); .ci/run does where apt is available",
)

_STRING = re.compile(r'"(?:[^"\\]|\\.)*"|\'(?:[^\'\\]|\\.)*\'|`[^`]*`')
_METRIC = re.compile(r"(?<![A-Za-z0-9_:])((?:mea|process)_[a-z0-9_]+)(?![A-Za-z0-9_:])")
_RECORDED = re.compile(r"(?<![A-Za-z0-9_:])(mea:[a-z0-9_:]+)")
_JOB = re.compile(r'\bjob\s*(=~|=)\s*"([^"]*)"')


def _promtool(*args: str) -> str:
    assert PROMTOOL is not None
    r = subprocess.run([PROMTOOL, *args], cwd=ROOT, capture_output=True, text=True, timeout=120)
    out = r.stdout + r.stderr
    assert r.returncode == 0, f"promtool {' '.join(args)} failed:\n{out}"
    return out


def _rules() -> list[dict]:
    doc = yaml.safe_load(RULES.read_text(encoding="utf-8"))
    return [rule for group in doc["groups"] for rule in group["rules"]]


def _config(name: str) -> dict:
    return yaml.safe_load((PROM / name).read_text(encoding="utf-8"))


def _metric_names(expr: str) -> set[str]:
    return set(_METRIC.findall(_STRING.sub('""', expr)))


# ------------------------------------------------------------------ promtool


@needs_promtool
@pytest.mark.parametrize("name", CONFIGS)
def test_promtool_check_config(name: str) -> None:
    out = _promtool("check", "config", f"deploy/prometheus/{name}")
    assert "SUCCESS" in out and "rule files found" in out, out


@needs_promtool
def test_promtool_check_rules() -> None:
    out = _promtool("check", "rules", "deploy/prometheus/rules/mea.yml")
    assert f"SUCCESS: {len(_rules())} rules found" in out, out


@needs_promtool
def test_promtool_test_rules() -> None:
    out = _promtool("test", "rules", "deploy/prometheus/tests/mea_test.yml")
    assert "SUCCESS" in out, out


# ------------------------------------------------------------------ pure Python


def test_rules_use_only_exported_metrics() -> None:
    used = {n for rule in _rules() for n in _metric_names(rule["expr"])}
    assert used, "no metric names found in the rule expressions"
    assert not undefined(used), f"rules use metrics no service exports: {undefined(used)}"


def test_rules_use_only_recorded_series() -> None:
    recorded = {rule["record"] for rule in _rules() if "record" in rule}
    for rule in _rules():
        used = set(_RECORDED.findall(_STRING.sub('""', rule["expr"])))
        assert used <= recorded, f"{rule.get('alert') or rule.get('record')}: {used - recorded} not recorded"


def test_rule_tests_feed_exported_metrics() -> None:
    doc = yaml.safe_load(RULE_TESTS.read_text(encoding="utf-8"))
    names = {
        s["series"].split("{", 1)[0].strip() for test in doc["tests"] for s in test.get("input_series", [])
    }
    assert "up" in names
    assert not undefined(names - {"up"}), f"synthetic series no service exports: {undefined(names - {'up'})}"


def test_every_rule_is_labelled_and_annotated() -> None:
    for rule in _rules():
        if "alert" in rule:
            assert rule.get("labels", {}).get("severity") in ("critical", "warning", "info"), rule["alert"]
            annotations = rule.get("annotations", {})
            assert annotations.get("summary") and annotations.get("description"), rule["alert"]
        else:
            assert re.fullmatch(r"mea:[a-z0-9_]+:[a-z0-9_]+|mea:[a-z0-9_]+", rule["record"]), rule["record"]


def test_every_alert_is_tested_firing_and_quiet() -> None:
    doc = yaml.safe_load(RULE_TESTS.read_text(encoding="utf-8"))
    fired, quiet = set(), set()
    for test in doc["tests"]:
        for case in test.get("alert_rule_test", []):
            (fired if case.get("exp_alerts") else quiet).add(case["alertname"])
    alerts = {rule["alert"] for rule in _rules() if "alert" in rule}
    assert alerts - fired == set(), f"never tested firing: {alerts - fired}"
    assert alerts - quiet == set(), f"never tested quiet: {alerts - quiet}"
    tested = {case["expr"].split()[0] for test in doc["tests"] for case in test.get("promql_expr_test", [])}
    recorded = {rule["record"] for rule in _rules() if "record" in rule}
    assert recorded - tested == set(), f"recording rules without a test: {recorded - tested}"


@pytest.mark.parametrize("name", CONFIGS)
def test_scrape_configs_match_the_services(name: str) -> None:
    """Every job scrapes its service's default port (services.common.metrics.DEFAULT_PORTS; actors
    9110 + i on one host, 9110 each in their own container), with a `service` label, every 5 s."""
    cfg = _config(name)
    assert cfg["global"]["scrape_interval"] == "5s"
    assert cfg["rule_files"] == ["rules/*.yml"]
    jobs = {job["job_name"]: job for job in cfg["scrape_configs"]}
    assert set(jobs) <= set(DEFAULT_PORTS), set(jobs) - set(DEFAULT_PORTS)
    assert {"learner", "augmenter", "evaluator", "inference", "actor"} <= set(jobs)
    for job_name, job in jobs.items():
        assert job.get("honor_labels") is True, job_name  # the services' own `service` labels win
        ports = []
        for sc in job["static_configs"]:
            assert sc["labels"]["service"] == job_name
            ports += [int(t.rsplit(":", 1)[1]) for t in sc["targets"]]
        base = DEFAULT_PORTS[job_name]
        if job_name == "actor" and name == "prometheus-local.yml":
            assert ports == [base + i for i in range(len(ports))], ports
        else:
            assert ports and set(ports) == {base}, (job_name, ports)


def test_compose_targets_are_the_compose_services() -> None:
    """prometheus.yml scrapes every service of deploy/docker-compose.yml that serves /metrics on all
    interfaces (and nothing else), on the port it is told to use."""
    compose_file = ROOT / "deploy" / "docker-compose.yml"
    if not compose_file.exists():
        pytest.skip("deploy/docker-compose.yml not there")
    services = yaml.safe_load(compose_file.read_text(encoding="utf-8"))["services"]
    exported = {}
    for name, svc in services.items():
        cmd = [str(c) for c in svc.get("command") or []]
        if "--service.metrics-addr" in cmd and cmd[cmd.index("--service.metrics-addr") + 1] == "0.0.0.0":
            exported[name] = (
                int(cmd[cmd.index("--service.metrics-port") + 1]) if "--service.metrics-port" in cmd else None
            )
    targets = {}
    for job in _config("prometheus.yml")["scrape_configs"]:
        for sc in job["static_configs"]:
            for t in sc["targets"]:
                host, port = t.rsplit(":", 1)
                targets[host] = int(port)
    assert set(targets) == set(exported), set(targets) ^ set(exported)
    for host, port in exported.items():
        if port is not None:
            assert targets[host] == port, host


def test_rules_select_jobs_the_configs_define() -> None:
    jobs = {job["job_name"] for name in CONFIGS for job in _config(name)["scrape_configs"]}
    for rule in _rules():
        for op, value in _JOB.findall(rule["expr"]):
            selected = value.split("|") if op == "=~" else [value]
            assert set(selected) <= jobs, f"{rule.get('alert') or rule.get('record')}: {set(selected) - jobs}"


def test_helper_derives_the_documented_metrics() -> None:
    """The helper finds every family (a sample of each service's and the common ones)."""
    names = exported_metric_names()
    for n in (
        "mea_service_info",
        "mea_policy_version",
        "mea_bus_rejected_messages_total",
        "process_start_time_seconds",
        "mea_learner_weights_version",
        "mea_learner_update_seconds_bucket",
        "mea_actor_env_steps_total",
        "mea_augmenter_transitions_out_total",
        "mea_evaluator_evaluations_total",
        "mea_inference_requests_total",
        "mea_robot_round_trip_seconds_count",
        "mea_launcher_service_restarts_total",
        "mea_launcher_services_alive",
    ):
        assert n in names, n
    assert not any(n.endswith("_created") for n in names)
