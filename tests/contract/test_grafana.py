"""Grafana provisioning as data (Grafana itself is not installed here): the generated dashboards are
committed as the code makes them, carry what Grafana needs to load them, query only `mea_*` and
`process_*` metrics through the provisioned Prometheus datasource, and the provisioning files point at
that datasource and at the folder the dashboards are mounted in.

Which of those metric names a live stack really exports: tests/e2e/test_metrics_names_live.py."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import yaml

from deploy.grafana import dashboards as gen

pytestmark = pytest.mark.contract
GRAFANA = Path(__file__).resolve().parents[2] / "deploy" / "grafana"
JSON_FILES = sorted((GRAFANA / "dashboards").glob("*.json"))


def _load(path: Path) -> dict:
    return json.loads(path.read_text())


def _panels(dashboard: dict) -> list[dict]:
    out = []
    for panel in dashboard["panels"]:
        out.append(panel)
        out.extend(panel.get("panels", []))
    return out


def _datasource_uid() -> str:
    data = yaml.safe_load((GRAFANA / "provisioning" / "datasources" / "prometheus.yml").read_text())
    (ds,) = data["datasources"]
    return ds["uid"]


def test_the_committed_dashboards_are_what_the_code_generates(tmp_path):
    want = gen.render()
    assert sorted(p.name for p in JSON_FILES) == sorted(want), "run: python -m deploy.grafana.dashboards"
    for path in JSON_FILES:
        assert path.read_text() == want[path.name], (
            f"{path.name} is stale: python -m deploy.grafana.dashboards"
        )
    assert gen.stale() == []
    assert gen.main(["--check"]) == 0
    # --check notices a hand edit
    for name, text in want.items():
        (tmp_path / name).write_text(text)
    assert gen.main(["--check", "--out", str(tmp_path)]) == 0
    (tmp_path / "mea-system.json").write_text(want["mea-system.json"].replace("MEA / System", "edited"))
    assert gen.main(["--check", "--out", str(tmp_path)]) == 1


@pytest.mark.parametrize("path", JSON_FILES, ids=lambda p: p.name)
def test_a_dashboard_has_what_grafana_needs(path):
    d = _load(path)
    assert re.fullmatch(r"[a-zA-Z0-9_-]{1,40}", d["uid"]) and d["uid"] == path.stem
    assert d["title"] and isinstance(d["schemaVersion"], int) and d["schemaVersion"] >= 39
    assert isinstance(d["annotations"]["list"], list)  # Grafana's dashboard model expects the list
    panels = _panels(d)
    assert panels
    ids = [p["id"] for p in panels]
    assert all(isinstance(i, int) and i > 0 for i in ids) and len(set(ids)) == len(ids), ids
    occupied: set[tuple[int, int]] = set()
    for p in panels:
        g = p["gridPos"]
        assert all(isinstance(g[k], int) for k in "xywh"), p["title"]
        assert g["x"] >= 0 and g["y"] >= 0 and g["w"] > 0 and g["h"] > 0 and g["x"] + g["w"] <= 24, p["title"]
        cells = {(x, y) for x in range(g["x"], g["x"] + g["w"]) for y in range(g["y"], g["y"] + g["h"])}
        assert not cells & occupied, f"{p['title']} overlaps another panel"
        occupied |= cells
        assert p["title"] and p["type"] in {"row", "timeseries", "stat"}
        if p["type"] == "row":
            assert not p.get("targets") and g["w"] == 24 and g["h"] == 1
            continue
        assert p["targets"], p["title"]
        ref_ids = [t["refId"] for t in p["targets"]]
        assert all(ref_ids) and len(set(ref_ids)) == len(ref_ids), p["title"]
        for t in p["targets"]:
            assert isinstance(t["expr"], str) and t["expr"].strip(), p["title"]
            assert t["expr"].count("(") == t["expr"].count(")"), t["expr"]
            assert t["expr"].count("{") == t["expr"].count("}"), t["expr"]


@pytest.mark.parametrize("path", JSON_FILES, ids=lambda p: p.name)
def test_every_query_goes_to_the_provisioned_prometheus(path):
    d = _load(path)
    uid = _datasource_uid()
    variables = {v["name"]: v for v in d["templating"]["list"]}
    ds = variables["datasource"]
    assert ds["type"] == "datasource" and ds["query"] == "prometheus"
    assert ds["current"]["value"] == uid  # the variable defaults to the provisioned datasource
    refs = [p["datasource"] for p in _panels(d) if p["type"] != "row"]
    refs += [t["datasource"] for p in _panels(d) for t in p.get("targets", [])]
    refs += [v["datasource"] for v in variables.values() if v["type"] == "query"]
    assert refs and all(r == {"type": "prometheus", "uid": "${datasource}"} or r == {"type": "prometheus", "uid": uid}
                        for r in refs), refs  # fmt: skip
    # every variable an expression uses is defined (Grafana's own $__ variables aside)
    used = {m for e in gen.expressions(d) for m in re.findall(r"\$\{?(\w+)", e) if not m.startswith("__")}
    assert used <= set(variables), used - set(variables)


@pytest.mark.parametrize("path", JSON_FILES, ids=lambda p: p.name)
def test_queries_read_only_service_metrics(path):
    names = set()
    for expr in gen.expressions(_load(path)):
        found = gen.metric_names(expr)
        assert found, expr
        names |= found
    bad = {n for n in names if not re.fullmatch(r"(mea|process)_[a-z0-9_]+", n)}
    assert not bad, bad


def test_metric_names_parses_promql():
    expr = ('sum by (namespace, le) (rate(mea_x_bucket{namespace=~"$namespace", service="a"}[$__rate_interval])) '
            "/ on(job, instance) group_left(service_instance) mea_service_info{a=\"b\"} > 0 and time() - "
            "mea_start_time_seconds offset 5m or vector(0) * process_open_fds")  # fmt: skip
    assert gen.metric_names(expr) == {
        "mea_x_bucket",
        "mea_service_info",
        "mea_start_time_seconds",
        "process_open_fds",
    }
    assert gen.metric_names("histogram_quantile(0.99, sum by (le) (rate(a_bucket[5m])))") == {"a_bucket"}
    assert gen.metric_names('label_values(mea_service_info{namespace=~"$namespace"}, service)') == {
        "mea_service_info"
    }


def test_the_issue_s_panels_are_there():
    titles = {p["title"] for path in JSON_FILES for p in _panels(_load(path))}
    for title in ("Env steps/s per actor", "Episodes/min per actor", "Augmented transitions/s",
                  "Augmenter queue depth", "Learner updates/s", "Losses", "Entropy temperature α", "Replay size",
                  "Batch demo share", "Weights version", "Weights staleness per consumer",
                  "Success rate vs env steps", "Grasp score vs env steps", "Inference act() server time",
                  "Robot round trip", "Server holds/s by reason", "Clamps/s by reason", "Robot holds/s by reason",
                  "Bus rejects/s by topic and reason", "CPU per process", "Resident memory per process"):  # fmt: skip
        assert title in titles, title


def test_provisioning_points_at_the_datasource_and_the_dashboards_folder():
    data = yaml.safe_load((GRAFANA / "provisioning" / "datasources" / "prometheus.yml").read_text())
    assert data["apiVersion"] == 1
    (ds,) = data["datasources"]
    assert ds["type"] == "prometheus" and ds["url"] == "http://prometheus:9090" and ds["access"] == "proxy"
    assert ds["uid"] == gen.DATASOURCE_UID == "prometheus" and ds["isDefault"] is True
    providers = yaml.safe_load((GRAFANA / "provisioning" / "dashboards" / "mea.yml").read_text())
    assert providers["apiVersion"] == 1
    (p,) = providers["providers"]
    assert p["type"] == "file" and p["options"]["path"] == "/var/lib/grafana/dashboards"
    # every dashboard's uid is unique (the provider refuses duplicates)
    uids = [_load(path)["uid"] for path in JSON_FILES]
    assert len(set(uids)) == len(uids) == 3
