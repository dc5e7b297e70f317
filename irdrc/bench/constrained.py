"""``recipes/bench_constrained.py``: the Lagrangian DQN over seeds × targets × scenarios through the
sweep engine, each run one ``recipes/constrained.py learner=dqn_lagrangian``, scored exactly
against the LP: per cell, the runs that meet the target and those that reach the LP's objective.

    python recipes/bench_constrained.py                              # CONSTRAINED.md's table
    python recipes/bench_constrained.py 'seeds=[10,11]' 'targets=[0.05]'
"""

from __future__ import annotations

import json
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from irdrc.core.checks import build, check_list, check_number, counted, grouped, numbers
from irdrc.runs.compose import Composed
from irdrc.runs.grid import parse_grid
from irdrc.runs.results import md_table
from irdrc.runs.sections import EXECUTOR, Executor, check_common, seeds

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "bench_constrained"


@dataclass(frozen=True)
class Config:
    """The benchmark's keys (``irdrc/conf/bench_constrained.yaml``); ``planned``: every run,
    checked (``irdrc.sweeps.trials.plan``)."""

    seeds: tuple[int, ...] = tuple(range(10))
    p1_speed: tuple[float, ...] = (0.1, 1.0)
    targets: tuple[float, ...] = (0.05, 0.15)
    overrides: tuple[str, ...] = ()
    miss_tolerance: float = 0.01
    objective_share: float = 0.95
    optimum_gamma: float = 0.99
    csv: str = "bench_constrained.csv"
    executor: Executor = field(default_factory=Executor, metadata=EXECUTOR)
    env: Any = None
    reward: Any = None
    planned: tuple[Any, ...] = field(default=(), metadata={"keys": ()})

    def __post_init__(self) -> None:
        check_common(self)
        object.__setattr__(self, "seeds", seeds("seeds", self.seeds))
        object.__setattr__(
            self, "p1_speed", check_list("p1_speed", self.p1_speed, numbers(0, 1), distinct=True)
        )
        object.__setattr__(
            self, "targets", check_list("targets", self.targets, numbers(0, 1), distinct=True)
        )
        object.__setattr__(self, "overrides", check_list("overrides", self.overrides, empty=True))
        for key in ("miss_tolerance", "objective_share"):
            object.__setattr__(self, key, check_number(key, getattr(self, key), 0, 1))

    @property
    def grid(self) -> dict[str, list[Any]]:
        """p^v_1 × target × seed."""
        return {
            "env.p1.speed": list(self.p1_speed),
            "target_miss": list(self.targets),
            "seed": list(self.seeds),
        }


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config; every run composed and checked before any trial."""
    from dataclasses import replace

    from irdrc.recipes.constrained import recipe as constrained
    from irdrc.sweeps.trials import plan

    cfg = build(Config, composed.cfg)
    composed.refuse_overwritten(
        {
            "env.p1.speed": "set p1_speed=[…]",
            "target_miss": "set targets=[…]",
            "seed": "set seeds=[…]",
        },
        cfg.overrides,
        fixed=("optimum_gamma", "checkpoint.every_frames"),
    )
    base = [
        *composed.scenario_overrides,
        "learner=dqn_lagrangian",
        *cfg.overrides,
        f"optimum_gamma={cfg.optimum_gamma}",
        "checkpoint.every_frames=0",
    ]
    return replace(cfg, planned=tuple(plan(constrained, parse_grid(cfg.grid), base)))


def run(cfg: Config, run: Run) -> int:
    """Every (p^v_1, target, seed) of ``cfg`` as one ``recipes/constrained.py
    learner=dqn_lagrangian`` run through the sweep engine, scored exactly against the LP: per cell,
    the runs whose miss detection is ≤ target + ``miss_tolerance`` and those whose objective is
    ≥ ``objective_share`` of the LP optimum, with env steps (training + measurement) and seconds."""
    from irdrc.runs.results import write_rows_csv, write_table_md
    from irdrc.sweeps.trials import execute, kept_points

    start = time.perf_counter()
    out, tol, share, grid = run.dir, cfg.miss_tolerance, cfg.objective_share, cfg.grid
    planned = list(cfg.planned)
    kept = kept_points(cfg.executor, planned, out)
    code = execute(cfg.executor, planned, out, run.recipe)
    rows = []
    for p in planned:
        path = Path(out) / "trials" / p["point_id"] / "summary.json"
        if not path.is_file():
            continue
        s = json.loads(path.read_text())
        learner = s["learner"]
        miss = float(s["metrics"]["miss_detection"])
        rows.append(
            {
                **dict(p["point"].items()),
                "objective": s["objective"],
                "lp_value": s["optimal_value"],
                "value": s["value"],
                "objective_ratio": s["objective_ratio"],
                "miss_detection": miss,
                "lp_miss_detection": s["optimal"]["miss_detection"],
                "miss_ok": miss <= float(p["point"]["target_miss"]) + tol,
                "objective_ok": float(s["objective_ratio"]) >= share,
                "mu": learner["mu"],
                "randomised_state": learner.get("switch_state"),
                "ranked": learner.get("ranked"),
                "path_promise": learner.get("path_promise"),
                "rank_promise": learner.get("rank_promise"),
                "training_env_steps": s["training_env_steps"],
                "measurement_env_steps": s["measurement_env_steps"],
                "env_steps": s["env_steps"],
                "wall_seconds": s["wall_seconds"],
            }
        )
    write_rows_csv(Path(out) / cfg.csv, rows)
    table = constrained_bench_table(rows, grid, tol, share)
    print(
        f"\nLagrangian DQN against the LP ({counted(len(grid['seed']), 'seed')} per cell): miss detection ≤ "
        f"target + {tol:g}, objective ≥ {share:g} of the LP optimum"
    )
    print(table)
    write_table_md(Path(out) / "bench_constrained.md", table, time.perf_counter() - start, kept)
    run.finish(None)
    return code


def _steps(n: float) -> str:
    """Env steps in words a table reads at a glance: 80 000, 1.2 M, 279 M."""
    if n >= 1e6:
        return f"{n / 1e6:.3g} M"
    return grouped(n)


def constrained_bench_table(
    rows: list[dict[str, Any]], grid: dict[str, list[Any]], tol: float, share: float
) -> str:
    """The benchmark's Markdown table: one line per (p^v_1, target) cell."""
    header = [
        "p^v_1",
        "target",
        "runs",
        f"miss ≤ target + {tol:g}",
        f"objective ≥ {share:g} of the LP",
        "worst miss",
        "worst ratio",
        "median ratio",
        "median env steps (training + measurement)",
        "median s",
    ]
    body = []
    for point in parse_grid({k: grid[k] for k in ("env.p1.speed", "target_miss")}):
        mine = [r for r in rows if all(r[k] == v for k, v in point.items())]
        if not mine:
            continue
        train = statistics.median(r["training_env_steps"] for r in mine)
        meas = statistics.median(r["measurement_env_steps"] for r in mine)
        total = statistics.median(r["env_steps"] for r in mine)
        body.append(
            [
                f"{point['env.p1.speed']:g}",
                f"{point['target_miss']:g}",
                len(mine),
                sum(r["miss_ok"] for r in mine),
                sum(r["objective_ok"] for r in mine),
                f"{max(r['miss_detection'] for r in mine):.4f}",
                f"{min(r['objective_ratio'] for r in mine):.3f}",
                f"{statistics.median(r['objective_ratio'] for r in mine):.3f}",
                f"{_steps(train)} + {_steps(meas)} = {_steps(total)}",
                f"{statistics.median(r['wall_seconds'] for r in mine):.0f}",
            ]
        )
    return md_table(header, body)
