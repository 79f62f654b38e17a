"""Printing benchmark results: a rich table for people, or exactly one JSON object with --json."""

from __future__ import annotations

import json
import sys
from typing import Any

from rich.console import Console
from rich.table import Table

from mea_tools.bench.reference import ratios


def _fmt(v: Any) -> str:
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "NO"
    if isinstance(v, float):
        return f"{v:,.3g}" if abs(v) < 1000 else f"{v:,.0f}"
    if isinstance(v, (list, tuple)):  # an interval [lo, hi]
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


def emit(
    name: str,
    sections: dict[str, list[dict[str, Any]]],
    measured: dict[str, float | None],
    as_json: bool,
    meta: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Print a benchmark result and return it as a dict.

    ``sections`` maps a heading to rows (dicts with the same keys); ``measured`` feeds the
    reference-ratio rows that every benchmark prints (None where not measured here).
    """
    result = {
        "benchmark": name,
        "meta": meta or {},
        "results": sections,
        "reference_ratios": ratios(measured),
    }
    if as_json:
        sys.stdout.write(json.dumps(result, default=float) + "\n")
        sys.stdout.flush()
        return result
    console = Console()
    if not console.is_terminal:  # piped or logged: don't squeeze columns to 80
        console = Console(width=max(console.width, 160))
    for heading, rows in sections.items():
        if not rows:
            continue
        table = Table(title=f"{name}: {heading}")
        for col in rows[0]:
            table.add_column(col)
        for row in rows:
            table.add_row(*(_fmt(row.get(c)) for c in rows[0]))
        console.print(table)
    t = Table(title="against the public Equi-RSAC code on a 2-core CPU")
    for col in ("target", "public", "measured", "ratio", "required", "met"):
        t.add_column(col)
    for r in result["reference_ratios"]:
        measured_s = "not measured here" if r["measured"] is None else f"{_fmt(r['measured'])} {r['unit']}"
        t.add_row(
            r["label"],
            f"{_fmt(r['public'])} {r['unit']}",
            measured_s,
            "—" if r["ratio"] is None else f"{r['ratio']:.2f}x",
            f"≥{r['required_ratio']:g}x",
            _fmt(r["met"]),
        )
    console.print(t)
    return result
