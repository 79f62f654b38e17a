"""The Prometheus series names the services export, derived from the code (nothing hard-coded).

Every place under ``services/`` that defines a ``mea_*`` metric (a call such as ``m.counter("mea_...",
...)``, ``m.gauge``, ``m.histogram`` or prometheus_client's ``Counter``/``Gauge``/``Histogram``/
``Info``/``Summary`` with a literal name) is found by parsing the source. The function around it is
then run when that can be done without a service: a factory taking a ``ServiceMetrics`` (``m``) or a
``ServiceContext`` (only its ``.metrics`` is used) is called with a fresh ``ServiceMetrics`` and that
registry is read (``collect()``: each family's name and type). ``ServiceMetrics`` itself (identity,
start time, policy version, ``process_*``/``python_*``) and its bus collector (``mea_bus_*``, fed a
fake bus with empty ``BusStats``) are read the same way. Definitions inside functions that cannot be
run alone (the launcher's ``Supervisor.__init__`` and ``_supervise``) are taken from the source: the
literal name and the kind of the call (``source_only_names`` says which).

Names are exposition names, as a scrape shows them: a counter ``mea_x`` is ``mea_x_total``, a
histogram ``mea_h`` gives ``mea_h_bucket``, ``mea_h_count``, ``mea_h_sum`` (and ``mea_h`` for its
metadata), an info ``mea_i`` is ``mea_i_info``. The ``*_created`` series prometheus_client adds are
left out on purpose: rules and dashboards should not use them (``PROMETHEUS_DISABLE_CREATED_SERIES``
removes them, and Prometheus versions differ in whether they ingest them).

Kept free of pytest so that scripts (e.g. a live ``/metrics`` cross-check) can import it.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import importlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[2]
SERVICES = ROOT / "services"

_METHOD_KINDS = {"counter": "counter", "gauge": "gauge", "histogram": "histogram"}
"""``ServiceMetrics`` helper -> metric type."""
_CLASS_KINDS = {
    "Counter": "counter",
    "Gauge": "gauge",
    "Histogram": "histogram",
    "Info": "info",
    "Summary": "summary",
    "CounterMetricFamily": "counter",
    "GaugeMetricFamily": "gauge",
    "HistogramMetricFamily": "histogram",
}
"""prometheus_client constructor -> metric type."""
_FACTORY_PARAMS = {"ServiceMetrics": "metrics", "ServiceContext": "context"}
"""Annotation of a function's only parameter -> how to call it (a ServiceMetrics, or a context)."""


@dataclasses.dataclass(frozen=True)
class Definition:
    """One ``mea_*`` metric defined in the source."""

    name: str
    """The name as written (prometheus_client adds ``_total`` to counters)."""
    kind: str
    """counter, gauge, histogram, info or summary."""
    module: str
    """Dotted module, e.g. ``services.launcher``."""
    function: str
    """Qualified name of the enclosing function (``Supervisor.__init__``), ``""`` at module level."""
    line: int
    factory: str | None
    """How the enclosing function can be called alone (``metrics``/``context``), None if it cannot."""


def series_names(name: str, kind: str) -> frozenset[str]:
    """Exposed series (and metadata) names of a metric ``name`` of type ``kind`` (no ``_created``)."""
    if kind == "counter":
        base = name.removesuffix("_total")
        return frozenset({base + "_total"})
    if kind == "info":
        base = name.removesuffix("_info")
        return frozenset({base + "_info"})
    if kind in ("histogram", "gaugehistogram"):
        return frozenset({name, name + "_bucket", name + "_count", name + "_sum"})
    if kind == "summary":
        return frozenset({name, name + "_count", name + "_sum"})
    return frozenset({name})


def _module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts)


def _call_kind(call: ast.Call) -> str | None:
    f = call.func
    if isinstance(f, ast.Attribute) and f.attr in _METHOD_KINDS:
        return _METHOD_KINDS[f.attr]
    if isinstance(f, ast.Name) and f.id in _CLASS_KINDS:
        return _CLASS_KINDS[f.id]
    if isinstance(f, ast.Attribute) and f.attr in _CLASS_KINDS:
        return _CLASS_KINDS[f.attr]
    return None


def _factory(fn: ast.FunctionDef | ast.AsyncFunctionDef | None, nested: bool) -> str | None:
    """``metrics``/``context`` if ``fn`` is a module-level function of one annotated parameter."""
    if fn is None or nested or isinstance(fn, ast.AsyncFunctionDef):
        return None
    args = fn.args
    if args.posonlyargs or args.kwonlyargs or args.vararg or args.kwarg or len(args.args) != 1:
        return None
    ann = args.args[0].annotation
    text = ast.unparse(ann).strip("'\"").rsplit(".", 1)[-1] if ann is not None else ""
    return _FACTORY_PARAMS.get(text)


def _walk(node: ast.AST, stack: tuple[ast.AST, ...]) -> Iterator[tuple[ast.Call, tuple[ast.AST, ...]]]:
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.Call):
            yield child, stack
        inner = (
            stack + (child,)
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)
            else stack
        )
        yield from _walk(child, inner)


def source_definitions(root: Path = SERVICES) -> list[Definition]:
    """Every ``mea_*`` metric defined with a literal name in a ``.py`` file under ``root``."""
    out = []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for call, stack in _walk(tree, ()):
            kind = _call_kind(call)
            if kind is None or not call.args:
                continue
            first = call.args[0]
            if not (isinstance(first, ast.Constant) and isinstance(first.value, str)):
                continue
            if not first.value.startswith("mea_"):
                continue
            fns = [n for n in stack if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)]
            fn = fns[-1] if fns else None
            nested = len(stack) > 1  # inside a class or another function: not callable alone
            qual = ".".join(n.name for n in stack)  # type: ignore[attr-defined]
            out.append(
                Definition(first.value, kind, _module_name(path), qual, call.lineno, _factory(fn, nested))
            )
    return out


def _fake_bus() -> SimpleNamespace:
    from services.common.bus.base import BusStats

    return SimpleNamespace(stats=BusStats())


def _registry_names(metrics) -> dict[str, str]:
    """Exposed name -> type of every family in ``metrics.registry``."""
    names: dict[str, str] = {}
    for family in metrics.registry.collect():
        for n in series_names(family.name, family.type):
            names[n] = family.type
        for sample in family.samples:
            if not sample.name.endswith("_created"):
                names.setdefault(sample.name, family.type)
    return names


def _run_factory(d: Definition):
    from services.common.metrics import ServiceMetrics

    m = ServiceMetrics(d.module.split(".")[1] if d.module.count(".") else d.module, "metric-names")
    fn = getattr(importlib.import_module(d.module), d.function)
    fn(m if d.factory == "metrics" else SimpleNamespace(metrics=m))
    return m


@functools.cache
def _collect() -> tuple[dict[str, tuple[str, str]], frozenset[str]]:
    """(exposed name -> (type, source), names that came from the source alone)."""
    from services.common.metrics import ServiceMetrics

    found: dict[str, tuple[str, str]] = {}

    def add(names: dict[str, str], source: str) -> None:
        for n, kind in names.items():
            found.setdefault(n, (kind, source))

    base = ServiceMetrics("metric-names", "metric-names")
    base.watch_bus(_fake_bus())  # type: ignore[arg-type]
    add(_registry_names(base), "services.common.metrics.ServiceMetrics")
    defs = source_definitions()
    for module, function in sorted({(d.module, d.function) for d in defs if d.factory}):
        first = next(d for d in defs if (d.module, d.function) == (module, function))
        add(_registry_names(_run_factory(first)), f"{module}.{function}")
    source_only: set[str] = set()
    for d in defs:
        names = series_names(d.name, d.kind)
        if names <= found.keys():
            continue
        if d.factory:  # the factory ran but did not register it: a bug in this helper or the code
            raise AssertionError(f"{d.module}.{d.function} did not register {d.name} (line {d.line})")
        for n in names:
            found.setdefault(n, (d.kind, f"source:{d.module}:{d.line}"))
            source_only.add(n)
    return found, frozenset(source_only)


def exported_metric_names() -> frozenset[str]:
    """Every series (and metric metadata) name a scrape of some service can show, ``*_created`` aside."""
    return frozenset(_collect()[0])


def metric_types() -> dict[str, str]:
    """Exposed name -> Prometheus type (counter, gauge, histogram, info, summary)."""
    return {n: kind for n, (kind, _src) in _collect()[0].items()}


def metric_sources() -> dict[str, str]:
    """Exposed name -> where it came from: the factory run, or ``source:MODULE:LINE``."""
    return {n: src for n, (_kind, src) in _collect()[0].items()}


def source_only_names() -> frozenset[str]:
    """The names that could only be read from the source (their defining function was not run)."""
    return _collect()[1]


def undefined(names: Iterable[str]) -> list[str]:
    """Those of ``names`` that no service exports, sorted."""
    known = exported_metric_names()
    return sorted({n for n in names if n not in known})


if __name__ == "__main__":  # python -m tests.helpers.metric_names: the list, with its sources
    for name, src in sorted(metric_sources().items()):
        print(f"{name:60s} {metric_types()[name]:10s} {src}")
