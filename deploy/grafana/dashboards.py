"""Grafana dashboards as code (grafana-foundation-sdk, Grafana 11.6 schema) for a `mea run` stack.

Three dashboards, written as JSON into ``deploy/grafana/dashboards/`` (kept in the repo; Grafana's
file provider, ``provisioning/dashboards/mea.yml``, loads them from the folder docker-compose mounts
at ``/var/lib/grafana/dashboards``):

* ``mea-training``: actors' env steps and episodes, the augmenter's output and queue, the learner's
  updates, losses, temperature, replay and batches, weights versions and staleness, evaluations;
* ``mea-serving``: `mea serve` and `mea robot`: latency, holds and clamps by reason, served weights;
* ``mea-system``: CPU, memory and file descriptors per process, bus traffic and rejects, the launcher.

Every query uses only metric names the services export (``tests/e2e/test_metrics_names_live.py``
scrapes a live stack and checks them); per-process series are named by joining
``mea_service_info{service, service_instance}`` on the scrape target (``job``, ``instance``). The
``namespace`` variable filters on a ``namespace`` target label that the Prometheus scrape config is
expected to set per run (the services do not export it); without that label, "All" matches everything.

Run from the repository root (``deploy`` is a namespace package, never installed)::

    python -m deploy.grafana.dashboards           # (re)write deploy/grafana/dashboards/*.json
    python -m deploy.grafana.dashboards --check   # exit 1 if a committed file differs

``python deploy/grafana/dashboards.py [--check]`` works as well (the module imports nothing of the repo).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from grafana_foundation_sdk.builders import common as cb
from grafana_foundation_sdk.builders import dashboard as db
from grafana_foundation_sdk.builders import prometheus, stat, timeseries
from grafana_foundation_sdk.cog.encoder import JSONEncoder
from grafana_foundation_sdk.models import common as cm
from grafana_foundation_sdk.models import dashboard as dm

OUT_DIR = Path(__file__).resolve().parent / "dashboards"
DATASOURCE_UID = "prometheus"
"""uid of the provisioned Prometheus datasource (``provisioning/datasources/prometheus.yml``), the
``datasource`` variable's default."""
DATASOURCE = dm.DataSourceRef(type_val="prometheus", uid="${datasource}")
NS = 'namespace=~"$namespace"'
RI = "[$__rate_interval]"
CONSUMERS = 'service!~"launcher|router|learner"'
"""Services whose ``mea_policy_version`` is a consumer's (the learner's own version is the reference)."""


# --- PromQL helpers ---------------------------------------------------------------------------------


def sel(metric: str, *matchers: str) -> str:
    """``metric{namespace=~"$namespace", matchers...}``."""
    return f"{metric}{{{', '.join((NS, *matchers))}}}"


def rate(metric: str, *matchers: str, window: str = RI) -> str:
    return f"rate({sel(metric, *matchers)}{window})"


def joined(expr: str, by: Sequence[str] = ("service_instance",), match: str = 'service=~".+"') -> str:
    """``expr`` per scrape target, labelled with its ``service_instance`` (``mea_service_info``),
    restricted to the services ``match`` selects, summed by ``namespace`` and ``by``."""
    labels = ", ".join(("namespace", *by))
    info = sel("mea_service_info", match)
    return f"sum by ({labels}) (({expr}) * on(job, instance) group_left(service_instance) {info})"


def quantile(q: float, metric: str, by: Sequence[str] = (), window: str = RI) -> str:
    """``histogram_quantile`` of the histogram ``metric`` (its ``_bucket`` series)."""
    labels = ", ".join(("le", *by))
    return f"histogram_quantile({q}, sum by ({labels}) (rate({sel(metric + '_bucket')}{window})))"


_PROMQL_KEYWORDS = {"and", "or", "unless", "bool", "offset", "inf", "nan", "by", "without", "on", "ignoring",
                    "group_left", "group_right", "start", "end"}  # fmt: skip


def metric_names(expr: str) -> set[str]:
    """The metric names a PromQL expression reads (selectors' names, not functions, labels or keywords)."""
    s = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)  # strings
    s = re.sub(r"\blabel_values\((.*),\s*\w+\s*\)", r"(\1)", s)  # a variable query: drop its label argument
    s = re.sub(r"\{[^}]*\}", " ", s)  # label matchers
    s = re.sub(r"\[[^\]]*\]", " ", s)  # ranges and subqueries
    s = re.sub(r"\b(?:by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", " ", s)  # label lists
    names = set()
    for match in re.finditer(r"(?<![\w.$])[a-zA-Z_:][\w:]*", s):
        rest = s[match.end() :].lstrip()
        if not rest.startswith("(") and match.group() not in _PROMQL_KEYWORDS:
            names.add(match.group())
    return names


def expressions(dashboard: dict) -> Iterator[str]:
    """Every query expression of a dashboard's JSON (panels, rows' panels and query variables)."""
    stack = list(dashboard.get("panels", []))
    while stack:
        panel = stack.pop(0)
        stack.extend(panel.get("panels", []))
        for target in panel.get("targets", []):
            yield target["expr"]
    for var in dashboard.get("templating", {}).get("list", []):
        if var.get("type") == "query":
            query = var["query"]
            yield query["query"] if isinstance(query, dict) else query


# --- panels -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Q:
    """One query: its expression, legend and (in time series) whether it draws on the right axis."""

    expr: str
    legend: str = ""
    right: bool = False


def _targets(queries: Sequence[Q]) -> list[prometheus.Dataquery]:
    return [
        prometheus.Dataquery()
        .expr(q.expr)
        .legend_format(q.legend or "__auto")
        .ref_id(chr(ord("A") + i))
        .datasource(DATASOURCE)
        .range()
        for i, q in enumerate(queries)
    ]


def ts(title: str, *queries: Q, unit: str = "short", desc: str = "", right_unit: str = "short",
       lo: float | None = None, hi: float | None = None, points: bool = False,
       bars: bool = False) -> timeseries.Panel:  # fmt: skip
    """A time series panel; queries with ``right=True`` use the right axis (in ``right_unit``)."""
    p = (
        timeseries.Panel()
        .title(title)
        .description(desc)
        .datasource(DATASOURCE)
        .unit(unit)
        .line_width(1)
        .fill_opacity(10 if not bars else 80)
        .show_points(cm.VisibilityMode.ALWAYS if points else cm.VisibilityMode.AUTO)
        .draw_style(cm.GraphDrawStyle.BARS if bars else cm.GraphDrawStyle.LINE)
        .span_nulls(True)
        .legend(
            cb.VizLegendOptions()
            .display_mode(cm.LegendDisplayMode.LIST)
            .placement(cm.LegendPlacement.BOTTOM)
            .show_legend(True)
        )
        .tooltip(cb.VizTooltipOptions().mode(cm.TooltipDisplayMode.MULTI).sort(cm.SortOrder.DESCENDING))
    )
    if lo is not None:
        p = p.min(lo)
    if hi is not None:
        p = p.max(hi)
    for target in _targets(queries):
        p = p.with_target(target)
    for i, q in enumerate(queries):
        if q.right:
            p = p.override_by_query(
                chr(ord("A") + i),
                [
                    dm.DynamicConfigValue(id_val="custom.axisPlacement", value="right"),
                    dm.DynamicConfigValue(id_val="unit", value=right_unit),
                    # no value: Grafana removes the panel's min/max from this field (the left axis keeps them)
                    *(
                        dm.DynamicConfigValue(id_val=k)
                        for k, v in (("min", lo), ("max", hi))
                        if v is not None
                    ),
                ],
            )
    return p


def single(title: str, q: Q, unit: str = "short", desc: str = "", decimals: int | None = None) -> stat.Panel:
    """A stat panel showing the last value."""
    p = (
        stat.Panel()
        .title(title)
        .description(desc)
        .datasource(DATASOURCE)
        .unit(unit)
        .graph_mode(cm.BigValueGraphMode.AREA)
        .color_mode(cm.BigValueColorMode.VALUE)
        .reduce_options(cb.ReduceDataOptions().calcs(["lastNotNull"]).values(False))
    )
    if decimals is not None:
        p = p.decimals(decimals)
    for target in _targets([q]):
        p = p.with_target(target)
    return p


# --- layout -----------------------------------------------------------------------------------------


@dataclass
class Board:
    """A dashboard laid out row by row: panels flow left to right, 24 columns wide; ids in order."""

    uid: str
    title: str
    description: str
    variables: list = field(default_factory=list)
    items: list = field(default_factory=list)  # (row title) or (panel builder, width, height)

    def row(self, title: str) -> Board:
        self.items.append(title)
        return self

    def add(self, panel, w: int = 12, h: int = 8) -> Board:
        self.items.append((panel, w, h))
        return self

    def build(self) -> dict:
        d = (
            db.Dashboard(self.title)
            .uid(self.uid)
            .description(self.description)
            .tags(["mea"])
            .editable()
            .tooltip(dm.DashboardCursorSync.CROSSHAIR)
            .time("now-1h", "now")
            .refresh("30s")
            .timezone("browser")
            .annotation(
                db.AnnotationQuery()
                .name("Annotations & Alerts")
                .datasource(dm.DataSourceRef(type_val="grafana", uid="-- Grafana --"))
                .built_in(1)
                .enable(True)
                .hide(True)
                .icon_color("rgba(0, 211, 255, 1)")
                .type("dashboard")
            )
            .link(
                db.DashboardLink("MEA dashboards")
                .type(dm.DashboardLinkType.DASHBOARDS)
                .tags(["mea"])
                .as_dropdown(True)
                .include_vars(True)
                .keep_time(True)
            )
        )
        for var in self.variables:
            d = d.with_variable(var)
        x = y = line_h = 0
        next_id = 1
        for item in self.items:
            if isinstance(item, str):
                y, x, line_h = y + line_h, 0, 0
                d = d.with_row(
                    db.Row(item).id(next_id).collapsed(False).grid_pos(dm.GridPos(h=1, w=24, x=0, y=y))
                )
                y += 1
            else:
                panel, w, h = item
                if x + w > 24:
                    y, x, line_h = y + line_h, 0, 0
                d = d.with_panel(panel.id(next_id).grid_pos(dm.GridPos(h=h, w=w, x=x, y=y)))
                x, line_h = x + w, max(line_h, h)
            next_id += 1
        return json.loads(JSONEncoder(sort_keys=True).encode(d.build()))


def _datasource_var() -> db.DatasourceVariable:
    return (
        db.DatasourceVariable("datasource")
        .label("Data source")
        .type("prometheus")
        .current(dm.VariableOption(selected=True, text="Prometheus", value=DATASOURCE_UID))
    )


def _label_var(name: str, label: str, query: str, multi: bool = False) -> db.QueryVariable:
    return (
        db.QueryVariable(name)
        .label(label)
        .datasource(DATASOURCE)
        .query({"query": query, "refId": f"{name}-query", "qryType": 1})
        .refresh(dm.VariableRefresh.ON_TIME_RANGE_CHANGED)
        .sort(dm.VariableSort.ALPHABETICAL_ASC)
        .include_all(True)
        .all_value(".*")
        .multi(multi)
        .current(dm.VariableOption(selected=True, text="All", value="$__all"))
    )


def _namespace_var() -> db.QueryVariable:
    return _label_var("namespace", "Namespace", "label_values(mea_service_info, namespace)")


# --- dashboards -------------------------------------------------------------------------------------


def training() -> dict:
    b = Board(
        "mea-training",
        "MEA / Training",
        "Actors, augmenter, learner, weights and evaluations of a `mea run`.",
        [_datasource_var(), _namespace_var()],
    )
    b.add(single("Env steps (learner)", Q(f"max({sel('mea_learner_env_steps')})")), 4, 4)
    b.add(single("Updates", Q(f"sum({sel('mea_learner_updates_total')})")), 4, 4)
    b.add(single("Weights version", Q(f"max({sel('mea_learner_weights_version')})")), 4, 4)
    b.add(single("Last success rate", Q(f"max({sel('mea_evaluator_success_rate')})"), "percentunit"), 4, 4)
    b.add(single("Improvement env steps", Q(f"max({sel('mea_evaluator_improvement_env_steps')})"),
                 desc="Env steps from which every evaluation succeeded at least once (-1: not yet)."), 4, 4)  # fmt: skip
    b.add(single("Replay memory", Q(f"sum({sel('mea_learner_replay_bytes')})"), "bytes"), 4, 4)

    b.row("Actors and augmenter")
    b.add(ts("Env steps/s per actor",
             Q(joined(rate("mea_actor_env_steps_total"), match='service="actor"'), "{{service_instance}}"),
             Q(f"sum({rate('mea_actor_env_steps_total')})", "all actors")), 8)  # fmt: skip
    b.add(ts("Episodes/min per actor",
             Q("60 * " + joined(rate("mea_actor_episodes_total"), ("service_instance", "kind"), 'service="actor"'),
               "{{service_instance}} {{kind}}"),
             desc="Episodes finished and published, by policy kind (demo, random, policy)."), 8)  # fmt: skip
    b.add(ts("Actor success ratio (15 min)",
             Q(f"sum by (kind) (increase({sel('mea_actor_successes_total')}[15m])) / "
               f"sum by (kind) (increase({sel('mea_actor_episodes_total')}[15m]))", "{{kind}}"),
             unit="percentunit", lo=0, hi=1), 8)  # fmt: skip
    b.add(ts("Augmented transitions/s",
             Q(f"sum({rate('mea_augmenter_transitions_out_total')})", "transitions/s"),
             Q(f"sum by (kind) ({rate('mea_augmenter_episodes_out_total')})", "episodes/s {{kind}}", right=True),
             desc="Transitions in the episodes the augmenter published; right axis: episodes by kind."), 8)  # fmt: skip
    b.add(ts("Augmenter queue depth",
             Q(joined(sel("mea_augmenter_queue_depth"), match='service="augmenter"'), "{{service_instance}}"),
             desc="Raw episodes waiting in the augmenter's input queue."), 8)  # fmt: skip
    b.add(ts("Augmenter latency",
             Q(quantile(0.5, "mea_augmenter_latency_seconds"), "p50"),
             Q(quantile(0.99, "mea_augmenter_latency_seconds"), "p99"), unit="s",
             desc="From a raw episode leaving the input queue to its last output published."), 8)  # fmt: skip

    b.row("Learner")
    b.add(ts("Learner updates/s",
             Q(f"sum({rate('mea_learner_updates_total')})", "updates/s"),
             Q(f"sum({sel('mea_learner_updates_per_second')})", "learner's 30 s window"),
             Q(f"sum({rate('mea_learner_updates_total')}) / sum({rate('mea_actor_env_steps_total')})",
               "updates per env step", right=True)), 8)  # fmt: skip
    b.add(ts("Losses", Q(f"max by (loss) ({sel('mea_learner_loss')})", "{{loss}}"),
             desc="Latest loss of each term (SAC: critic, actor, alpha, bc; GASv2: its world model's too)."), 8)  # fmt: skip
    b.add(ts("Entropy temperature α",
             Q(f"max({sel('mea_learner_alpha')})", "alpha"),
             Q(f"max({sel('mea_learner_policy_entropy')})", "policy entropy", right=True)), 8)  # fmt: skip
    b.add(ts("Replay size",
             Q(f"sum({sel('mea_learner_replay_transitions')})", "transitions"),
             Q(f"sum({sel('mea_learner_replay_episodes')})", "episodes", right=True)), 8)  # fmt: skip
    b.add(ts("Batch demo share",
             Q(f"max({sel('mea_learner_batch_demo_share')})", "demo share"),
             Q(f"max({sel('mea_learner_batch_reward_transitions')})", "reward transitions", right=True),
             unit="percentunit", lo=0, hi=1,
             desc="Share of the latest batch's episodes drawn from the demonstrations; right axis: "
                  "transitions with reward > 0 in it."), 8)  # fmt: skip
    b.add(ts("Q values", Q(f"max by (stat) ({sel('mea_learner_q')})", "{{stat}}")), 8)  # fmt: skip
    b.add(ts("Learner waiting",
             Q(f"sum({rate('mea_learner_wait_seconds_total')})", "waiting for limiter or data"),
             Q(f"max({sel('mea_learner_limiter_can_sample')})", "limiter allows updates", right=True),
             unit="percentunit", lo=0), 8)  # fmt: skip
    b.add(ts("Episodes into replay/s",
             Q(f"sum by (kind) ({rate('mea_learner_episodes_in_total')})", "{{kind}}"),
             Q(f"sum by (reason) ({rate('mea_learner_rejected_episodes_total')})", "rejected: {{reason}}")), 8)  # fmt: skip
    b.add(ts("Learner update time",
             Q(quantile(0.5, "mea_learner_update_seconds"), "p50"),
             Q(quantile(0.99, "mea_learner_update_seconds"), "p99"), unit="s"), 8)  # fmt: skip

    b.row("Weights")
    consumers = joined(f"{sel('mea_policy_version')} >= 0", match=CONSUMERS)
    b.add(ts("Weights version",
             Q(f"max by (namespace) ({sel('mea_learner_weights_version')})", "learner (published)"),
             Q(consumers, "{{service_instance}}"),
             desc="The learner's latest published version and the version each consumer runs."), 8)  # fmt: skip
    b.add(ts("Weights staleness per consumer",
             Q(f"max by (namespace) ({sel('mea_learner_weights_version')}) - on(namespace) group_right() "
               f"{consumers}", "{{service_instance}}"),
             desc="Versions behind the learner's latest (0: current)."), 8)  # fmt: skip
    b.add(ts("Weights publish time",
             Q(quantile(0.5, "mea_learner_weights_publish_seconds"), "p50"),
             Q(quantile(0.99, "mea_learner_weights_publish_seconds"), "p99"), unit="s"), 8)  # fmt: skip

    b.row("Evaluation")
    b.add(ts("Success rate vs env steps",
             Q(f"max({sel('mea_evaluator_success_rate')})", "success rate"),
             Q(f"max({sel('mea_evaluator_env_steps')})", "env steps of the evaluated version", right=True),
             unit="percentunit", lo=0, hi=1, points=True,
             desc="Each evaluation's success rate (left) and the learner's env steps when the evaluated "
                  "version was pulled (right): read the two at the same time for the learning curve."), 12)  # fmt: skip
    b.add(ts("Grasp score vs env steps",
             Q(f"max({sel('mea_evaluator_grasp_score')})", "grasp score"),
             Q(f"max({sel('mea_evaluator_env_steps')})", "env steps of the evaluated version", right=True),
             lo=0, hi=1, points=True), 12)  # fmt: skip
    b.add(ts("Evaluation return and length",
             Q(f"max({sel('mea_evaluator_mean_return')})", "mean return"),
             Q(f"max({sel('mea_evaluator_mean_length')})", "mean length (steps)", right=True),
             points=True), 12)  # fmt: skip
    b.add(ts("Evaluated version",
             Q(f"max({sel('mea_evaluator_policy_version')})", "evaluated version"),
             Q(f"sum({sel('mea_evaluator_evaluations_total')})", "evaluations", right=True),
             Q(f"sum by (reason) ({sel('mea_evaluator_bad_weights_total')})", "skipped: {{reason}}", right=True),
             points=True), 12)  # fmt: skip
    return b.build()


def serving() -> dict:
    b = Board(
        "mea-serving",
        "MEA / Serving",
        "`mea serve` (mea_inference_*) and `mea robot` (mea_robot_*): latency, safety envelope, weights.",
        [_datasource_var(), _namespace_var()],
    )
    b.add(single("Robot sessions", Q(f"sum({sel('mea_inference_sessions')})")), 4, 4)
    b.add(single("Served version", Q(f"max({sel('mea_inference_served_version')})")), 4, 4)
    b.add(single("Learner version", Q(f"max({sel('mea_learner_weights_version')})")), 4, 4)
    b.add(single("E-stop engaged", Q(f"max({sel('mea_inference_estop_engaged')})"), decimals=0), 4, 4)
    b.add(
        single("act() p99 (5 min)", Q(quantile(0.99, "mea_inference_act_seconds", window="[5m]")), "s"), 4, 4
    )
    b.add(single("Round trip p99 (5 min)", Q(quantile(0.99, "mea_robot_round_trip_seconds", window="[5m]")),
                 "s"), 4, 4)  # fmt: skip

    b.row("Latency")
    b.add(ts("Inference act() server time",
             *(Q(quantile(q, "mea_inference_act_seconds"), f"p{round(q * 100)}") for q in (0.5, 0.9, 0.99)),
             unit="s", desc="Server time of one act(): projection and policy."), 8)  # fmt: skip
    b.add(ts("Robot round trip",
             *(Q(quantile(q, "mea_robot_round_trip_seconds"), f"p{round(q * 100)}") for q in (0.5, 0.9, 0.99)),
             unit="s", desc="Request to reply of one act, robot side (injected latency included)."), 8)  # fmt: skip
    b.add(ts("Requests/s by kind", Q(f"sum by (kind) ({rate('mea_inference_requests_total')})", "{{kind}}")), 8)  # fmt: skip

    b.row("Safety envelope")
    b.add(ts("Server holds/s by reason",
             Q(f"sum by (reason) ({rate('mea_inference_holds_total')}) > 0", "{{reason}}"),
             desc="Actions answered with a hold (non-finite, workspace, watchdog, e-stop...)."), 8)  # fmt: skip
    b.add(ts("Clamps/s by reason", Q(f"sum by (reason) ({rate('mea_inference_clamps_total')}) > 0", "{{reason}}"),
             desc="Actions clipped by the envelope, by limit."), 8)  # fmt: skip
    b.add(ts("Robot holds/s by reason",
             Q(f"sum by (reason) ({rate('mea_robot_holds_total')}) > 0", "{{reason}}"),
             desc="Steps the robot held (its own rules or the server's holds)."), 8)  # fmt: skip
    b.add(ts("Robot episodes by outcome",
             Q(f"sum by (outcome) ({sel('mea_robot_episodes_total')})", "{{outcome}}")), 8)  # fmt: skip
    b.add(ts("E-stop engaged",
             Q(joined(sel("mea_inference_estop_engaged"), match='service="inference"'), "{{service_instance}}"),
             lo=0, hi=1), 8)  # fmt: skip
    b.add(ts("Robot sessions", Q(joined(sel("mea_inference_sessions"), match='service="inference"'),
                                 "{{service_instance}}"), lo=0), 8)  # fmt: skip

    b.row("Weights")
    b.add(ts("Served weights version",
             Q(f"max({sel('mea_learner_weights_version')})", "learner (published)"),
             Q(joined(sel("mea_inference_policy_version"), match='service="inference"'),
               "{{service_instance}} loaded"),
             Q(joined(sel("mea_inference_served_version"), match='service="inference"'),
               "{{service_instance}} last served")), 8)  # fmt: skip
    b.add(ts("Swaps and refused weights",
             Q(f"sum(increase({sel('mea_inference_swaps_total')}{RI}))", "swaps"),
             Q(f"sum by (reason) (increase({sel('mea_inference_weights_refused_total')}{RI})) > 0",
               "refused: {{reason}}"), bars=True), 8)  # fmt: skip
    b.add(ts("Swap to first action",
             Q(quantile(0.5, "mea_inference_swap_to_first_action_seconds", window="[15m]"), "p50 (15 min)"),
             Q(quantile(0.99, "mea_inference_swap_to_first_action_seconds", window="[15m]"), "p99 (15 min)"),
             unit="s", desc="From a version's announcement to the first action served with it."), 8)  # fmt: skip
    return b.build()


def system() -> dict:
    svc = 'service=~"$service"'
    b = Board(
        "mea-system",
        "MEA / System",
        "Per-process CPU and memory, Zenoh bus traffic and rejects, and the launcher's supervision.",
        [
            _datasource_var(),
            _namespace_var(),
            _label_var("service", "Service", f"label_values({sel('mea_service_info')}, service)", multi=True),
        ],
    )
    b.add(single("Services alive", Q(f"sum({sel('mea_launcher_services_alive')})")), 6, 4)
    b.add(single("Processes scraped", Q(f"count({sel('mea_service_info', svc)})")), 6, 4)
    b.add(single("Bus rejects (range)",
                 Q(f"sum(increase({sel('mea_bus_rejected_messages_total')}[$__range]))"), decimals=0), 6, 4)  # fmt: skip
    b.add(single("Service restarts (range)",
                 Q(f"sum(increase({sel('mea_launcher_service_restarts_total')}[$__range]))"), decimals=0), 6, 4)  # fmt: skip

    b.row("Processes")
    b.add(ts("CPU per process", Q(joined(rate("process_cpu_seconds_total"), match=svc), "{{service_instance}}"),
             unit="percentunit", desc="CPU time per second (1 = one core)."), 12)  # fmt: skip
    b.add(ts("Resident memory per process",
             Q(joined(sel("process_resident_memory_bytes"), match=svc), "{{service_instance}}"), unit="bytes"), 12)  # fmt: skip
    b.add(ts("Open file descriptors",
             Q(joined(sel("process_open_fds"), match=svc), "{{service_instance}}")), 12)  # fmt: skip
    b.add(ts("Uptime", Q(joined(f"time() - {sel('mea_start_time_seconds')}", match=svc), "{{service_instance}}"),
             unit="s"), 12)  # fmt: skip

    b.row("Zenoh bus")
    rejected, unauth = rate("mea_bus_rejected_messages_total"), rate("mea_bus_unauthenticated_messages_total")
    b.add(ts("Bus rejects/s by topic and reason",
             Q(f"{joined(unauth, ('topic',), svc)} > 0", "{{topic}}: unauthenticated"),
             Q(f"({joined(rejected, ('topic',), svc)} - ({joined(unauth, ('topic',), svc)} or "
               f"{joined(rejected, ('topic',), svc)} * 0)) > 0", "{{topic}}: invalid"),
             desc="Messages the decoder refused: unauthenticated (seal missing or wrong, or a sender not "
                  "allowed on the topic) and the rest (malformed or out of limits)."), 12)  # fmt: skip
    b.add(ts("Bus rejects/s by receiving process",
             Q(f"{joined(rejected, ('service_instance', 'topic'), svc)} > 0", "{{service_instance}} {{topic}}")), 12)  # fmt: skip
    b.add(ts("Published messages/s by topic",
             Q(joined(rate("mea_bus_published_messages_total"), ("topic",), svc), "{{topic}}")), 12)  # fmt: skip
    b.add(ts("Received messages/s by topic",
             Q(joined(rate("mea_bus_received_messages_total"), ("topic",), svc), "{{topic}}")), 12)  # fmt: skip
    b.add(ts("Published bytes/s by topic",
             Q(joined(rate("mea_bus_published_bytes_total"), ("topic",), svc), "{{topic}}"), unit="Bps"), 12)  # fmt: skip
    b.add(ts("Received bytes/s by topic",
             Q(joined(rate("mea_bus_received_bytes_total"), ("topic",), svc), "{{topic}}"), unit="Bps"), 12)  # fmt: skip

    b.row("Launcher")
    b.add(ts("Service instances alive", Q(f"sum({sel('mea_launcher_services_alive')})", "alive")), 12)  # fmt: skip
    b.add(ts("Service exits and restarts",
             Q(f"sum by (service) (increase({sel('mea_launcher_service_exits_total')}{RI})) > 0", "exits: {{service}}"),
             Q(f"sum by (service) (increase({sel('mea_launcher_service_restarts_total')}{RI})) > 0",
               "restarts: {{service}}"), bars=True), 12)  # fmt: skip
    return b.build()


DASHBOARDS = {"mea-training": training, "mea-serving": serving, "mea-system": system}


def render() -> dict[str, str]:
    """File name -> the JSON text the code generates."""
    return {
        f"{name}.json": json.dumps(make(), indent=2, sort_keys=True) + "\n"
        for name, make in DASHBOARDS.items()
    }


def stale(out_dir: Path = OUT_DIR) -> list[str]:
    """Files in ``out_dir`` missing, different from the generated ones, or not generated at all."""
    want = render()
    have = {p.name for p in out_dir.glob("*.json")} if out_dir.is_dir() else set()
    diff = [n for n, text in want.items() if not (out_dir / n).is_file() or (out_dir / n).read_text() != text]
    return sorted(diff + [n for n in have if n not in want])


def main(argv: Iterable[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if a committed JSON differs from the code")
    ap.add_argument("--out", type=Path, default=OUT_DIR, help="output folder (default: %(default)s)")
    args = ap.parse_args(list(argv) if argv is not None else None)
    if args.check:
        bad = stale(args.out)
        for name in bad:
            print(
                f"{args.out / name}: differs from deploy/grafana/dashboards.py (regenerate it)",
                file=sys.stderr,
            )
        return 1 if bad else 0
    args.out.mkdir(parents=True, exist_ok=True)
    for name, text in render().items():
        (args.out / name).write_text(text)
        print(f"wrote {args.out / name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
