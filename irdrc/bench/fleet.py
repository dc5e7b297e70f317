"""``recipes/bench_fleet.py``: the fleet's benchmark — multi-agent learners against the exact
centralised optimum at N = 2, and against the baselines (Monte-Carlo) as the fleet grows.

Part A — N = 2, every (share, channels) cell × learner × seed, one ``recipes/fleet.py`` run each
through the sweep engine: the final ratio to the exact optimum, fleet steps and seconds to 95 % /
99 %, beside the exact baselines of the cell; in every cell, the best decentralised policy found
(``irdrc.bench.fleet_best``) — how far own observations can go: the information gap apart
from the learning gap. Part B — N = 2 (part A's runs) and ``vehicles`` (one channel, share 0.5), the own-observation
learners against the baselines: fleet reward, miss detection, throughput, denial rate. A figure: the fleet's
frontier (throughput against miss detection) at N = 2 for the optimum, the learners and the
baselines, one panel per cell.

    python recipes/bench_fleet.py                                 # FLEET.md's tables and figure
    python recipes/bench_fleet.py 'learners=[vdn]' 'seeds=[0]' search=false
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from irdrc.agents.configs import FLEET_LEARNERS
from irdrc.core import checks
from irdrc.core.checks import counted, grouped
from irdrc.runs.compose import Composed
from irdrc.runs.grid import require_runs
from irdrc.runs.results import (
    atomic_savefig,
    md_table,
    read_csv_rows,
    write_rows_csv,
    write_table_md,
)
from irdrc.runs.sections import EXECUTOR, Executor, Plot, seeds

NAME = "bench_fleet"
OWN_LEARNERS = ("idqn", "vdn", "qmix", "mappo", "ippo")
"""Learners whose vehicles see only their own state (``env.observe=own``)."""

BASELINES = (
    "N copies of the single optimum",
    "round-robin in anti-phase",
    "sensing rotation",
    "always radar",
)
SHORT = {
    "N copies of the single optimum": "copies",
    "round-robin in anti-phase": "anti-phase",
    "sensing rotation": "rotation",
    "always radar": "radar always",
}
"""The baselines' labels in the figure."""


def observe_of(learner: str) -> str:
    """What a learner's vehicles observe in the benchmark (joint: every vehicle's state)."""
    return "full" if learner == "joint" else "own"


@dataclass(frozen=True)
class Config:
    """The benchmark's keys (``irdrc/conf/bench_fleet.yaml``); ``planned``: every run, checked
    (``irdrc.sweeps.trials.plan``), and ``part``: each run's part and learner."""

    learners: tuple[str, ...] = FLEET_LEARNERS
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    share: tuple[float, ...] = (0.0, 0.5, 1.0)
    channels: tuple[int, ...] = (1, 2)
    scale_learners: tuple[str, ...] = ("idqn", "vdn", "qmix", "ippo")
    vehicles: tuple[int, ...] = (3, 4, 6, 8)
    scale_seeds: tuple[int, ...] = (0, 1)
    overrides: tuple[str, ...] = ()
    eval: dict[str, Any] = field(default_factory=lambda: {"every_frames": 50_000})
    search: bool = True
    search_sweeps: int = 10
    plot: Plot = field(default_factory=Plot)
    csv: str = "bench_fleet.csv"
    executor: Executor = field(default_factory=Executor, metadata=EXECUTOR)
    planned: tuple[Any, ...] = field(default=(), metadata={"keys": ()})
    part: dict[str, Any] = field(default_factory=dict, metadata={"keys": ()})

    def __post_init__(self) -> None:
        def pick(choices: Sequence[str]) -> Callable[[str, Any], Any]:
            return lambda key, x: checks.check_choice(key, x, choices)

        lists = (
            ("learners", pick(FLEET_LEARNERS), True),
            ("scale_learners", pick(OWN_LEARNERS), True),
            ("share", checks.numbers(0, 1), True),
            ("channels", checks.numbers(1, 16, integer=True), True),
            ("vehicles", checks.numbers(1, 16, integer=True), True),
            ("overrides", None, True),
        )
        for key, item, empty in lists:
            object.__setattr__(
                self,
                key,
                checks.check_list(
                    key, getattr(self, key), item, empty=empty, distinct=key != "overrides"
                ),
            )
        for key in ("seeds", "scale_seeds"):
            object.__setattr__(self, key, seeds(key, getattr(self, key), empty=True))
        checks.check_bool("search", self.search)
        checks.check_file_name("csv", self.csv)
        checks.check_numbers(self, "", (("search_sweeps", 1, 1000, checks.INT),))
        from irdrc.core.checks import check_number

        check_number("eval.every_frames", self.eval.get("every_frames"), 1, 10**12, integer=True)


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config; every run of both parts composed and checked before any trial."""
    from dataclasses import replace

    from irdrc.recipes.fleet import recipe as fleet
    from irdrc.sweeps.trials import plan

    cfg = checks.build(Config, composed.cfg)
    composed.refuse_overwritten(
        {
            "learner": "set learners=[…] and scale_learners=[…]",
            "env.observe": "each learner's own (joint: full; the others: own)",
            "env.share": "set share=[…] (part B: 0.5)",
            "env.channels": "set channels=[…] (part B: 1)",
            "env.vehicles": "set vehicles=[…] (part A: 2)",
            "seed": "set seeds=[…] and scale_seeds=[…]",
        },
        cfg.overrides,
        fixed=("eval.every_frames",),
    )
    if not cfg.search:
        composed.refuse_unread(("search_sweeps",), "no search runs (search=false)")
    if not cfg.scale_learners or not cfg.vehicles:
        off = "scale_learners=[]" if not cfg.scale_learners else "vehicles=[]"
        composed.refuse_unread(
            [k for k in ("scale_learners", "vehicles") if not off.startswith(k)] + ["scale_seeds"],
            f"part B does not run ({off})",
        )
    base = [*cfg.overrides, f"eval.every_frames={cfg.eval['every_frames']}"]
    planned, part = [], {}
    for learner in cfg.learners:
        extra = [f"learner={learner}", f"env.observe={observe_of(learner)}", "env.vehicles=2"]
        grid = [
            {"env.share": s, "env.channels": k, "seed": seed}
            for s in cfg.share
            for k in cfg.channels
            for seed in cfg.seeds
        ]
        for p in plan(fleet, grid, [*base, *extra]):
            planned.append(p)
            part[p["point_id"]] = ("A", learner)
    for learner in cfg.scale_learners:
        extra = [f"learner={learner}", "env.observe=own", "env.channels=1", "env.share=0.5"]
        grid = [{"env.vehicles": n, "seed": seed} for n in cfg.vehicles for seed in cfg.scale_seeds]
        for p in plan(fleet, grid, [*base, *extra]):
            planned.append(p)
            part[p["point_id"]] = ("B", learner)
    require_runs(
        len(planned),
        "learners × share × channels × seeds; scale_learners × vehicles × scale_seeds",
    )
    return replace(cfg, planned=tuple(planned), part=part)


def run(cfg: Config, run: Run) -> int:
    """Run both parts, then write ``bench_fleet.csv`` (a row per run), ``bench_fleet.md`` (the
    tables) and ``fleet_frontier.<format>``."""
    from irdrc.sweeps.trials import execute, kept_points

    start = time.perf_counter()
    out, planned, part = run.dir, list(cfg.planned), cfg.part
    kept = kept_points(cfg.executor, planned, out)
    code = execute(cfg.executor, planned, out, run.recipe)
    rows, tables, specs = [], {}, {}
    for p in planned:
        tdir = out / "trials" / p["point_id"]
        if not (tdir / "summary.json").is_file():
            continue
        s = json.loads((tdir / "summary.json").read_text())
        which, learner = part[p["point_id"]]
        fleet = s["fleet"]
        hist = read_csv_rows(tdir / "metrics.csv")
        row = {
            "part": which,
            "learner": learner,
            "vehicles": fleet["vehicles"],
            "channels": fleet["channels"],
            "share": fleet["share"],
            "observe": fleet["observe"],
            "seed": int(p["point"]["seed"]),
            "reference": s["reference"],
            "final_ratio": s["optimality_ratio"],
            "fleet_steps": s["env_steps"],
            "wall_seconds": s["wall_seconds"],
            **_to(hist, 0.95),
            **_to(hist, 0.99),
            **{k: s["per_vehicle"][-1][k] for k in KEYS},
            "point_id": p["point_id"],
        }
        rows.append(row)
        tables[p["point_id"]] = s["table"]
        specs[p["point_id"]] = p["config"].fleet[0]
    write_rows_csv(out / cfg.csv, rows)
    a = [r for r in rows if r["part"] == "A"]
    # part B starts with part A's own-observation runs of its cell at N = 2
    b = [
        r
        for r in a
        if r["observe"] == "own"
        and r["learner"] in cfg.scale_learners
        and (r["share"], r["channels"]) == (0.5, 1)
    ] + [r for r in rows if r["part"] == "B"]
    text = []
    if a:
        text.append(exact_table(a, tables, len(cfg.seeds)))
        if cfg.search and any(r["observe"] == "own" for r in a):
            from irdrc.bench.fleet_best import best_per_cell

            section, found = best_per_cell(a, specs, out, cfg.search_sweeps)
            write_rows_csv(out / "best_decentralised_summary.csv", found)
            text.append(section)
    if b:
        text.append(scale_table(b, tables))
    table = "\n\n".join(text)
    print("\n" + table)
    if a:
        frontier_figure(a, tables, out / f"fleet_frontier.{cfg.plot.format}")
    write_table_md(out / "bench_fleet.md", table, time.perf_counter() - start, kept)
    run.finish(None)
    return code


KEYS = ("avg_reward", "throughput", "miss_detection", "denial_rate", "radar_fraction")


def _to(hist: list[dict[str, str]], th: float) -> dict[str, Any]:
    first = next((r for r in hist if float(r["optimality_ratio"]) >= th), None)
    tag = f"{round(th * 100)}"
    return {
        f"fleet_steps_to_{tag}": int(first["env_steps"]) if first else None,
        f"seconds_to_{tag}": float(first["wall_seconds"]) if first else None,
    }


def _med(values: list[float], fmt: str = "{:.4f}") -> str:
    hit = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return fmt.format(statistics.median(hit)) if hit else "—"


def _steps(values: list[float]) -> str:
    hit = [v for v in values if v is not None]
    if not hit:
        return "—"
    label = grouped(statistics.median(hit))
    return label if len(hit) == len(values) else f"{label} ({len(hit)}/{len(values)})"


def exact_table(rows: list[dict[str, Any]], tables: dict[str, Any], seeds: int) -> str:
    """Part A as Markdown: per cell, each learner's final ratio to the exact centralised optimum
    (median, min–max over the seeds), runs ≥ 0.95, fleet steps and seconds to 95 % (median over
    the runs that reached it), and the exact baselines' ratios."""
    cells = sorted({(r["share"], r["channels"]) for r in rows})
    learners = list(dict.fromkeys(r["learner"] for r in rows))
    out = []
    for share, k in cells:
        mine = [r for r in rows if (r["share"], r["channels"]) == (share, k)]
        table = tables[mine[0]["point_id"]]
        opt = table["centralised optimum"][-1]["avg_reward"]
        body = []
        for learner in learners:
            rs = [r for r in mine if r["learner"] == learner]
            if not rs:
                continue
            ratios = [r["final_ratio"] for r in rs]
            body.append(
                [
                    f"{learner} ({rs[0]['observe']})",
                    f"{_med(ratios)} ({min(ratios):.4f}–{max(ratios):.4f})",
                    f"{sum(x >= 0.95 for x in ratios)}/{len(rs)}",
                    _steps([r["fleet_steps_to_95"] for r in rs]),
                    _med([r["seconds_to_95"] for r in rs], "{:.0f}"),
                    _med([r["miss_detection"] for r in rs]),
                    _med([r["throughput"] for r in rs]),
                ]
            )
        for name in BASELINES:
            per = table[name]
            body.append(
                [
                    f"*{name}* (exact)",
                    f"{per[-1]['avg_reward'] / opt:.4f}",
                    "",
                    "",
                    "",
                    f"{per[-1]['miss_detection']:.4f}",
                    f"{per[-1]['throughput']:.4f}",
                ]
            )
        out.append(
            f"**N = 2, share {share:g}, {k} channel(s)** — centralised optimum {opt:.4f} per "
            f"fleet step (exact), {counted(seeds, 'seed')} per learner\n\n"
            + md_table(
                [
                    "policy",
                    "final ratio (median, range)",
                    "≥ 0.95",
                    "fleet steps to 95 %",
                    "s to 95 %",
                    "miss detection",
                    "throughput",
                ],
                body,
            )
        )
    return "\n\n".join(out)


def scale_table(rows: list[dict[str, Any]], tables: dict[str, Any]) -> str:
    """Part B as Markdown: per N, each learner (median over seeds) and each baseline: fleet reward
    per fleet step, miss detection, throughput, denial rate."""
    body = []
    for n in sorted({r["vehicles"] for r in rows}):
        mine = [r for r in rows if r["vehicles"] == n]
        table = tables[mine[0]["point_id"]]
        how = "exact" if mine[0]["reference"].startswith("centralised") else "Monte-Carlo"
        for learner in dict.fromkeys(r["learner"] for r in mine):
            rs = [r for r in mine if r["learner"] == learner]
            body.append(
                [str(n), f"{learner} ({how}, {len(rs)} seed(s))"]
                + [_med([r[k] for r in rs]) for k in KEYS[:4]]
            )
        for name in BASELINES:
            per = next(v for key, v in table.items() if key.startswith(name))
            body.append(
                [str(n), f"*{name}* ({how})"]
                + [f"{per[-1][k]:.4f}" if per[-1][k] is not None else "—" for k in KEYS[:4]]
            )
        if how == "exact":
            per = table["centralised optimum"]
            body.append(
                [str(n), "*centralised optimum* (exact)"]
                + [f"{per[-1][k]:.4f}" if per[-1][k] is not None else "—" for k in KEYS[:4]]
            )
    return "**The fleet as it grows** (one channel, share 0.5, own observations)\n\n" + md_table(
        ["N", "policy", "fleet reward / step", "throughput", "miss detection", "denial rate"], body
    )


def frontier_figure(rows: list[dict[str, Any]], tables: dict[str, Any], path: Path) -> None:
    """Throughput against miss detection at N = 2, one panel per cell: the optimum, each learner's
    runs, the baselines."""
    cells = sorted({(r["share"], r["channels"]) for r in rows})
    cols = min(3, len(cells))
    nrows = math.ceil(len(cells) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.9 * nrows), squeeze=False)
    marks = {"idqn": "o", "vdn": "s", "qmix": "^", "joint": "D", "mappo": "v", "ippo": "P"}
    for ax, (share, k) in zip(axes.flat, cells, strict=False):
        mine = [r for r in rows if (r["share"], r["channels"]) == (share, k)]
        table = tables[mine[0]["point_id"]]
        for learner in dict.fromkeys(r["learner"] for r in mine):
            rs = [r for r in mine if r["learner"] == learner]
            ax.scatter(
                [r["miss_detection"] for r in rs],
                [r["throughput"] for r in rs],
                marker=marks.get(learner, "o"),
                s=36,
                alpha=0.7,
                label=learner,
            )
        opt = table["centralised optimum"][-1]
        ax.scatter(
            [opt["miss_detection"]], [opt["throughput"]], marker="*", s=200, c="k", label="optimum"
        )
        spots: dict[tuple[float, float], list[str]] = {}
        for name in BASELINES:
            b = table[name][-1]
            spot = (round(b["miss_detection"], 6), round(b["throughput"], 6))
            spots.setdefault(spot, []).append(SHORT[name])
        for (miss, thr), names in spots.items():
            ax.scatter([miss], [thr], marker="x", s=50, c="grey")
            ax.annotate(
                " = ".join(names),
                (miss, thr),
                fontsize=7,
                xytext=(-4, -11),
                textcoords="offset points",
                ha="right",
            )
        ax.set_title(f"share {share:g}, {k} channel(s)", fontsize=10)
        ax.set_xlabel("miss detection (fleet)", fontsize=9)
        ax.set_ylabel("throughput (packets / fleet step)", fontsize=9)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(cells) :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8, loc="best")
    fig.suptitle("Two vehicles: throughput against miss detection (exact)", fontsize=11)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=160)
