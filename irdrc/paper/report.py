"""docs/REPRODUCTION.md: fills its generated blocks and copies the figures from a figure2 run and a
tradeoff run (``bash ci/reproduce.sh`` calls ``write_report``)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

from irdrc.core.metrics import RESOLUTION
from irdrc.paper.docs import replace_block
from irdrc.paper.figures import same_value
from irdrc.runs.results import atomic_write_text, md_table
from irdrc.runs.results import read_csv_rows as read_csv

FIGURES = ("panel_a.png", "panel_b.png", "panel_c.png", "panel_d.png")


def _fmt(x: Any, digits: int = 4) -> str:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if math.isnan(v):
        return "n/a"
    return f"<{RESOLUTION:.0e}" if v != 0 and abs(v) < RESOLUTION else f"{v:.{digits}g}"


def write_report(
    figure_dir: Path,
    tradeoff_dir: Path,
    docs_dir: Path,
    command: str,
    frontier_dir: Path | None = None,
    learner_dir: Path | None = None,
    study_dir: Path | None = None,
) -> None:
    """Copy the figures into ``docs_dir/figures`` and fill the generated blocks of
    ``docs_dir/REPRODUCTION.md`` from a figure2 run, a tradeoff run and (when given) a
    ``constrained.py frontier=true`` run, a ``bench_constrained.py`` run and a ``study.py`` run."""
    figure_dir, tradeoff_dir, docs_dir = Path(figure_dir), Path(tradeoff_dir), Path(docs_dir)
    fig_out = docs_dir / "figures"
    fig_out.mkdir(parents=True, exist_ok=True)
    for name in FIGURES:
        shutil.copyfile(figure_dir / name, fig_out / name)
    shutil.copyfile(tradeoff_dir / "tradeoff.png", fig_out / "tradeoff.png")
    summary = json.loads((figure_dir / "summary.json").read_text())
    trade = json.loads((tradeoff_dir / "summary.json").read_text())
    if summary.get("resumed"):
        raise ValueError(f"{figure_dir} was resumed: its wall time is not the whole run's")

    report = (docs_dir / "REPRODUCTION.md").read_text()
    report = replace_block(report, "command", f"```bash\n{command}\n```")
    report = replace_block(
        report,
        "timing",
        f"Measured on this 2-core machine: **{summary['wall_seconds'] / 60:.1f} min** "
        f"({summary['wall_seconds']:.0f} s) for the figure: {summary['training_runs']} training "
        f"runs ({len(summary['seeds'])} seeds; p^v_1 ∈ {{{', '.join(f'{p:g}' for p in summary['p1_speed'])}}}) "
        f"took {summary['wall_seconds_training']:.0f} s of it; then {trade['wall_seconds']:.0f} s "
        "for the trade-off.",
    )
    # Panel (a) numbers.
    rows = []
    for name, final in summary["final_episode_reward"].items():
        ep = summary["episodes_to_95"].get(name)
        rows.append([name, "never" if ep is None else f"{ep:g}", f"{final:.1f}"])
    rows.append(["optimal (exact)", "—", f"{summary['optimum_episode_reward']:.1f}"])
    rows.append(["round-robin (exact)", "—", f"{summary['round_robin_episode_reward']:.1f}"])
    report = replace_block(
        report,
        "panel_a",
        md_table(
            [
                "method",
                "first training episode with mean ≥ 95 % of the optimum",
                "final total reward per episode (mean over seeds)",
            ],
            rows,
        ),
    )
    # Panels (b)–(d) at the ends of the sweep.
    p_lo, p_hi = summary["p1_speed"][0], summary["p1_speed"][-1]
    table: dict[str, dict[str, str]] = {}
    for panel, metric_key in (("b", None), ("c", "metric"), ("d", None)):
        for r in read_csv(figure_dir / f"panel_{panel}.csv"):
            metric = (
                r[metric_key] if metric_key else {"b": "avg_reward", "d": "miss_detection"}[panel]
            )
            for p, tag in ((p_lo, "lo"), (p_hi, "hi")):
                if same_value(r["x"], p):
                    band = "" if r["n"] == "0" else f" [{_fmt(r['lo'])}, {_fmt(r['hi'])}]"
                    table.setdefault(r["series"], {})[f"{metric}_{tag}"] = _fmt(r["mean"]) + band
    metrics = ("avg_reward", "throughput", "link_capacity", "miss_detection")
    header = ["method"] + [f"{m} at {p:g}" for m in metrics for p in (p_lo, p_hi)]
    rows = [
        [s] + [vals.get(f"{m}_{t}", "") for m in metrics for t in ("lo", "hi")]
        for s, vals in table.items()
    ]
    report = replace_block(report, "panels_bcd", md_table(header, rows))
    report = replace_block(report, "claims", (figure_dir / "claims.md").read_text())
    report = replace_block(report, "tradeoff", _tradeoff_block(tradeoff_dir, trade))
    if frontier_dir is not None:
        shutil.copyfile(Path(frontier_dir) / "frontier.png", fig_out / "frontier.png")
        report = replace_block(report, "design", design_block(Path(frontier_dir)))
    if learner_dir is not None:
        report = replace_block(report, "design_learner", learner_block(Path(learner_dir)))
    if study_dir is not None:
        report = replace_block(report, "study", study_block(Path(study_dir)))
    atomic_write_text(docs_dir / "REPRODUCTION.md", report)


def learner_block(bench_dir: Path) -> str:
    """The Lagrangian DQN's benchmark table (``bench_constrained.md``) and its total time."""
    rows = read_csv(bench_dir / "bench_constrained.csv")
    total = sum(float(r["wall_seconds"]) for r in rows)
    return (
        (bench_dir / "bench_constrained.md").read_text().strip()
        + f"\n\n{len(rows)} runs, {total / 60:.0f} min of run time in all (2 at a time here)."
    )


def study_block(study_dir: Path) -> str:
    """The study's table (``study.md``), each scenario's optimum and solver, and its total time."""
    summary = json.loads((study_dir / "summary.json").read_text())
    optima = "; ".join(
        f"{name}: S = {o['states']}, optimum {o['avg_reward']:.4f} reward/step "
        f"({o['solver']}, {o['solve_seconds']:.1f} s)"
        for name, o in summary["scenarios"].items()
    )
    return (
        (study_dir / "study.md").read_text().strip()
        + f"\n\nSeeds {', '.join(map(str, summary['seeds']))}. {optima}. "
        + f"The whole study: {summary['wall_seconds'] / 60:.0f} min."
    )


def design_block(frontier_dir: Path) -> str:
    """The throughput the r4 route gives up at each target, from ``frontier_gap.csv``."""
    rows = []
    for g in read_csv(frontier_dir / "frontier_gap.csv"):
        r4 = g["r4_throughput"]
        rows.append(
            [
                _fmt(g["p1_speed"], 3),
                _fmt(g["target_miss"], 3),
                _fmt(g["lp_throughput"]),
                f"{_fmt(r4)} (r4 = {_fmt(g['r4'], 4)})"
                if r4 not in ("", None)
                else "none meets it",
                _fmt(g["given_up"]) if g["given_up"] not in ("", None) else "all",
            ]
        )
    summary = json.loads((frontier_dir / "summary.json").read_text())
    return (
        md_table(
            [
                "p^v_1",
                "target miss detection",
                "most data (exact LP), packets/step",
                "best r4-route policy meeting it",
                "throughput given up by the r4 route",
            ],
            rows,
        )
        + f"\n\nObjective: {summary['objective']}; {summary['wall_seconds']:.0f} s for the frontier "
        "and the r4 scan."
    )


def _tradeoff_block(tradeoff_dir: Path, trade: dict[str, Any]) -> str:
    """The trade-off table, the smallest r4 per p^v_1 and the DQN points, as Markdown."""
    rows = [
        [
            _fmt(r["p1_speed"], 3),
            _fmt(r["r4"], 4),
            r["radar_states"],
            _fmt(r["miss_detection"]),
            _fmt(r["throughput"]),
            _fmt(r["link_capacity"]),
        ]
        for r in read_csv(tradeoff_dir / "tradeoff.csv")
    ]
    body = md_table(
        ["p^v_1", "r4", "radar states (of 352)", "miss detection", "throughput", "link capacity"],
        rows,
    )
    lines = []
    for p, entry in (trade.get("smallest_r4") or {}).items():
        if entry.get("r4") is None:
            lines.append(f"- p^v_1 = {p}: no r4 on the search grid meets the target.")
            continue
        m = entry["metrics"]
        lines.append(
            f"- p^v_1 = {p}: smallest r4 with miss detection ≤ {trade['target_miss']}: "
            f"**{entry['r4']:g}** (miss {m['miss_detection']:.4f}, throughput {m['throughput']:.4f}, "
            f"link capacity {m['link_capacity']:.4f}); one grid step lower, miss "
            f"{entry.get('miss_at_lower_neighbour', float('nan')):.4f}"
            + ("; checked against every grid point below it" if entry.get("verified") else "")
            + "."
        )
    dqn_csv = tradeoff_dir / "tradeoff_dqn.csv"
    if dqn_csv.is_file() and dqn_csv.stat().st_size:
        for r in read_csv(dqn_csv):
            lines.append(
                f"- DQN (ours), {r['series']}, r4 = {_fmt(r['r4'])}: miss detection "
                f"{_fmt(r['miss_detection'])} [{_fmt(r['lo'])}, {_fmt(r['hi'])}] over {r['n']} seeds, "
                f"throughput {_fmt(r['throughput'])}, link capacity {_fmt(r['link_capacity'])}."
            )
    return body + "\n\n" + "\n".join(lines)
