"""Statistics across seeds for any sweep whose grid varies ``seed``.

``summary_by_point.csv``: one row per grid point without its seed (the other keys' values), with
the number of seeds DONE and, for the optimality ratio, env steps and every final metric, the mean
and the half-width of its 95 % t-interval over those seeds. ``learning_curves.png``: per point,
the mean learning curve (exact optimality ratio against env steps, from each trial's
``metrics.csv``) with its 95 % band and the seeds' range.
"""

from __future__ import annotations

import csv
import io
import math
import statistics
from collections import defaultdict
from pathlib import Path
from typing import Any

from irdrc.runs.results import atomic_savefig, atomic_write_text

T95 = {
    1: 12.706,
    2: 4.303,
    3: 3.182,
    4: 2.776,
    5: 2.571,
    6: 2.447,
    7: 2.365,
    8: 2.306,
    9: 2.262,
    10: 2.228,
    15: 2.131,
    20: 2.086,
    30: 2.042,
}
"""Two-sided 95 % quantiles of Student's t by degrees of freedom (1.96 beyond 30)."""


def t95(dof: int) -> float:
    """The 95 % t quantile for ``dof`` degrees of freedom (the next tabulated one below)."""
    if dof < 1:
        return math.nan
    if dof > 30:
        return 1.96
    return T95[max(k for k in T95 if k <= dof)]


def mean_ci(values: list[float]) -> tuple[float, float]:
    """Mean and 95 % t-interval half-width (NaN with fewer than two values)."""
    if not values:
        return math.nan, math.nan
    m = statistics.fmean(values)
    if len(values) < 2:
        return m, math.nan
    return m, t95(len(values) - 1) * statistics.stdev(values) / math.sqrt(len(values))


def _num(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def group_rows(
    rows: list[dict[str, str]], keys: list[str]
) -> dict[tuple[str, ...], list[dict[str, str]]]:
    """``summary.csv`` rows grouped by their values of ``keys`` (the grid without ``seed``)."""
    groups: dict[tuple[str, ...], list[dict[str, str]]] = defaultdict(list)
    for r in rows:
        groups[tuple(r.get(k, "") for k in keys)].append(r)
    return dict(groups)


def read_seed_grid(summary_csv: Path) -> tuple[list[str], list[str], list[dict[str, str]]] | None:
    """``summary.csv``'s (columns, grid keys without ``seed``, rows); None when the grid has no
    ``seed`` key."""
    with Path(summary_csv).open() as f:
        reader = csv.DictReader(f)
        fields, rows = list(reader.fieldnames or []), list(reader)
    if "seed" not in fields:
        return None
    keys = [k for k in fields[: fields.index("status")] if k != "seed"]
    return fields, keys, rows


def write_seed_summary(summary_csv: Path, out: Path) -> Path | None:
    """``summary_by_point.csv`` next to ``summary_csv`` (see the module docstring); None when the
    grid has no ``seed`` key."""
    grid = read_seed_grid(summary_csv)
    if grid is None:
        return None
    fields, keys, rows = grid
    values = [c for c in fields[fields.index("point_id") + 1 :] if c != "wall_seconds"]
    table = []
    for key, group in group_rows(rows, keys).items():
        done = [r for r in group if r["status"] == "DONE"]
        row: dict[str, Any] = dict(zip(keys, key, strict=True))
        row["seeds"] = len(group)
        row["done"] = len(done)
        for c in values:
            m, h = mean_ci([v for r in done if (v := _num(r.get(c))) is not None])
            row[f"{c}_mean"] = "" if math.isnan(m) else f"{m:.6g}"
            row[f"{c}_ci95"] = "" if math.isnan(h) else f"{h:.4g}"
        table.append(row)
    header = [*keys, "seeds", "done", *(f"{c}_{s}" for c in values for s in ("mean", "ci95"))]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=header, restval="")
    w.writeheader()
    w.writerows(table)
    path = Path(out) / "summary_by_point.csv"
    atomic_write_text(path, buf.getvalue())
    return path


def _curve(metrics_csv: Path) -> dict[int, float]:
    """env steps → optimality ratio of learner 0 in a trial's ``metrics.csv``."""
    out: dict[int, float] = {}
    with metrics_csv.open() as f:
        for r in csv.DictReader(f):
            if r.get("learner", "0") not in ("0", ""):
                continue
            v = _num(r.get("optimality_ratio"))
            if v is not None:
                out[int(float(r["env_steps"]))] = v
    return out


def series_labels(points: list[dict[str, str]]) -> list[str]:
    """A legend label per point (grid key → value), leaving out what every point shares: the keys
    with one value throughout, and the ``base`` overrides common to every point's base."""
    common = set.intersection(*(set(p.get("base", "").split()) for p in points))
    labels = []
    for p in points:
        parts = [
            f"{k}={v}" for k, v in p.items() if k != "base" and len({q.get(k) for q in points}) > 1
        ]
        own = [o for o in p.get("base", "").split() if o not in common]
        labels.append(", ".join([*parts, *own]) or "all")
    return labels


def plot_seed_curves(summary_csv: Path, trials_dir: Path, out: Path) -> Path | None:
    """``learning_curves.png``: per point (the grid without ``seed``), the mean curve over the
    DONE seeds with its 95 % t-band and the seeds' min–max; None without ``seed`` in the grid or
    without learning curves (e.g. ``method=solve``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = read_seed_grid(summary_csv)
    if grid is None:
        return None
    _, keys, rows = grid
    series = []
    for key, group in group_rows(rows, keys).items():
        curves = [
            _curve(p)
            for r in group
            if r["status"] == "DONE"
            and (p := Path(trials_dir) / r["point_id"] / "metrics.csv").is_file()
        ]
        if not curves:
            continue
        steps = sorted(set.intersection(*(set(c) for c in curves)))
        if steps:
            series.append((dict(zip(keys, key, strict=True)), steps, curves))
    if not series:
        return None
    labelled = [
        (label, steps, curves)
        for label, (_, steps, curves) in zip(
            series_labels([point for point, _, _ in series]), series, strict=True
        )
    ]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (label, steps, curves) in enumerate(labelled):
        color = colors[i % len(colors)]
        stats = [mean_ci([c[s] for c in curves]) for s in steps]
        mean = [m for m, _ in stats]
        half = [0.0 if math.isnan(h) else h for _, h in stats]
        ax.fill_between(
            steps,
            [min(c[s] for c in curves) for s in steps],
            [max(c[s] for c in curves) for s in steps],
            color=color,
            alpha=0.12,
            linewidth=0,
        )
        ax.fill_between(
            steps,
            [m - h for m, h in zip(mean, half, strict=True)],
            [m + h for m, h in zip(mean, half, strict=True)],
            color=color,
            alpha=0.3,
            linewidth=0,
        )
        ax.plot(steps, mean, color=color, linewidth=1.8, label=f"{label} ({len(curves)} seeds)")
    ax.axhline(1.0, color="black", linestyle="--", linewidth=1, label="exact optimum")
    ax.axhline(0.99, color="black", linestyle=":", linewidth=1, label="99 % of the optimum")
    ax.set_xlabel("env steps per learner", fontsize=11)
    ax.set_ylabel("average reward / optimum's (exact)", fontsize=11)
    ax.set_title("mean over seeds; band: 95 % t-interval, light: the seeds' range", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    path = Path(out) / "learning_curves.png"
    atomic_savefig(fig, path, dpi=200)
    return path
