"""`mea plot RUN_DIR... [--out FILE.png] [--label-by KEY]`: learning curves like the paper's figures.

Success rate against training env steps from each run's ``RUN_DIR/eval/history.jsonl``, the runs of
one label (seeds of one configuration) as mean ± std, and a table per label (final success, AUC,
improvement timestep), so variants compare as the paper compares them.

Design notes: docs/architecture-notes.md, services/evaluator/plot.py."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.common.config import OneLineParser
from services.evaluator.core.curves import (
    INTERPOLATIONS,
    align,
    common_grid,
    curve,
    improvement_timestep,
    mean_std,
    success_auc,
)
from services.evaluator.history import HISTORY, read_history


class PlotError(Exception):
    """A problem with the inputs; reported as ``mea plot: <message>`` with exit status 2."""


@dataclass(frozen=True)
class Run:
    path: Path
    label: str
    steps: np.ndarray
    success: np.ndarray


@dataclass(frozen=True)
class Group:
    """One label's runs on a common grid."""

    label: str
    runs: list[Run]
    method: str
    grid: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    count: np.ndarray


def run_label(run_dir: Path, label_by: str) -> str:
    """The ``label_by`` value in ``run_dir/config.json`` (dotted path), else the directory's name."""
    cfg_path = run_dir / "config.json"
    try:
        value = json.loads(cfg_path.read_text())
        for part in label_by.split("."):
            value = value[part]
    except (OSError, ValueError, KeyError, TypeError):
        return run_dir.resolve().name
    return value if isinstance(value, str) else json.dumps(value)


def load_run(run_dir: Path, label_by: str) -> Run:
    path = run_dir / HISTORY
    if not path.is_file():
        raise PlotError(f"no evaluation history at {path}")
    steps, success = curve(read_history(path))
    if steps.size == 0:
        raise PlotError(f"no evaluation with known env steps in {path}")
    return Run(run_dir, run_label(run_dir, label_by), steps, success)


def group_runs(runs: Sequence[Run], method: str = "hold") -> list[Group]:
    """Runs grouped by label (first-seen order), each group aligned and reduced to mean ± std."""
    labels: dict[str, list[Run]] = {}
    for r in runs:
        labels.setdefault(r.label, []).append(r)
    groups = []
    for label, members in labels.items():
        curves = [(r.steps, r.success) for r in members]
        grid = common_grid(curves)
        mean, std, count = mean_std(align(curves, grid, method))
        groups.append(Group(label, members, method, grid, mean, std, count))
    return groups


def summary_row(g: Group) -> dict:
    finals = np.array([r.success[-1] for r in g.runs])
    per_run = [improvement_timestep(r.steps, r.success) for r in g.runs]
    have = [t for t in per_run if t is not None]
    aucs = np.array([success_auc(r.steps, r.success) for r in g.runs], dtype=np.float64)
    return {
        "label": g.label,
        "runs": len(g.runs),
        "evaluations": int(sum(r.steps.size for r in g.runs)),
        "final_mean": float(finals.mean()),
        "final_std": float(finals.std()),
        "auc_mean": float(aucs.mean()),
        "auc_std": float(aucs.std()),
        "auc_of_mean": success_auc(g.grid, g.mean),
        "improvement_mean": float(np.mean(have)) if have else None,
        "improvement_runs": len(have),
        "improvement_of_mean": improvement_timestep(g.grid, g.mean),
    }


def format_table(rows: Sequence[dict]) -> str:
    def steps(v) -> str:
        return "—" if v is None else f"{v:,.0f}"

    head = (
        "label",
        "runs",
        "evals",
        "final success",
        "AUC",
        "improvement (runs with one)",
        "improvement (mean curve)",
    )
    body = [
        (
            r["label"],
            str(r["runs"]),
            str(r["evaluations"]),
            f"{r['final_mean']:.2f} ± {r['final_std']:.2f}",
            f"{r['auc_mean']:.2f} ± {r['auc_std']:.2f}",
            f"{steps(r['improvement_mean'])} ({r['improvement_runs']}/{r['runs']})",
            steps(r["improvement_of_mean"]),
        )
        for r in rows
    ]
    widths = [max(len(row[i]) for row in (head, *body)) for i in range(len(head))]
    lines = [
        "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in (head, *body)
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def render(groups: Sequence[Group], out: Path, title: str = "") -> None:
    """Success rate vs env steps, mean ± std (shaded) per label, to a PNG."""
    try:
        import matplotlib  # deferred: slow to import, and only drawing needs it (not the launcher)

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # deferred: after the Agg backend is chosen
    except ImportError as exc:
        raise PlotError(f"plotting needs matplotlib (pip install matplotlib): {exc}") from None
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    try:
        for g in groups:
            step = "post" if g.method == "hold" else None  # a held value lasts until the next evaluation
            (line,) = ax.plot(g.grid, g.mean, drawstyle="steps-post" if step else "default",
                              marker="o" if len(g.grid) == 1 else "", label=f"{g.label} (n={len(g.runs)})")  # fmt: skip
            lo, hi = np.clip(g.mean - g.std, 0.0, 1.0), np.clip(g.mean + g.std, 0.0, 1.0)
            ax.fill_between(g.grid, lo, hi, color=line.get_color(), alpha=0.2, linewidth=0, step=step)
        ax.set_xlabel("env steps")
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left")
        if title:
            ax.set_title(title)
        fig.tight_layout()
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, format="png")
    finally:
        plt.close(fig)


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    p = OneLineParser(  # bad flags: one line, exit code 2
        prog="mea plot",
        description="Render learning curves (success rate vs env steps, mean ± std over runs with the "
        "same label) from RUN_DIR/eval/history.jsonl to a PNG, and print a summary table.",
    )
    p.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR", help="run directories to plot")
    p.add_argument("--out", type=Path, default=Path("learning_curves.png"), help="PNG to write")
    p.add_argument("--label-by", default="variant",
                   help="config.json key (dots for nested) that labels a run; runs with the same label "
                        "are seeds (default: variant; falls back to the directory name)")  # fmt: skip
    p.add_argument("--interp", choices=INTERPOLATIONS, default="hold",
                   help="how runs are put on a common env-step grid: step-wise hold of the last "
                        "evaluation, or linear interpolation (default: hold)")  # fmt: skip
    p.add_argument("--title", default="", help="figure title")
    return p.parse_args(list(argv))


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        runs = [load_run(d, args.label_by) for d in args.run_dirs]
        groups = group_runs(runs, args.interp)
        render(groups, args.out, args.title)
    except PlotError as exc:
        print(f"mea plot: {exc}", file=sys.stderr)
        return 2
    print(format_table([summary_row(g) for g in groups]))
    print(f"wrote {args.out}")
    return 0


__all__ = [
    "Group",
    "PlotError",
    "Run",
    "format_table",
    "group_runs",
    "load_run",
    "main",
    "render",
    "summary_row",
]


if __name__ == "__main__":
    sys.exit(main())
