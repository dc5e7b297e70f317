"""``recipes/tradeoff.py``: the radar/communication trade-off the paper only mentions (its claim 3),
exactly.

``run`` maps the exact optimum over r4 and finds, by bisection, the smallest r4 whose optimal
policy meets a miss-detection target; DQN runs at a few r4 go through the sweep engine.

    python recipes/tradeoff.py target_miss=0.1 'p1_speed=[0.1,0.5,1.0]'
    python recipes/tradeoff.py executor=local 'dqn.r4=[]'        # exact curves only
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from irdrc.core.checks import build, check_bool, check_list, check_number, numbers
from irdrc.core.metrics import Metrics
from irdrc.core.params import Params
from irdrc.paper import plots
from irdrc.paper.figures import mean_ci, same_value, to_float
from irdrc.recipes import dqn
from irdrc.recipes.constrained.frontier import optimal_at, ref_params
from irdrc.runs.compose import Composed
from irdrc.runs.grid import parse_grid
from irdrc.runs.limits import check_dense
from irdrc.runs.progress import Ticker
from irdrc.runs.results import write_rows_csv
from irdrc.runs.sections import (
    EXECUTOR,
    Executor,
    check_common,
    check_speeds,
    scenario_field,
    seeds,
)
from irdrc.sweeps.trials import execute, plan

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "tradeoff"
SOLVES_LIMIT = 5_000
"""The bisection's check solves every grid point below its answer: at most this many."""


@dataclass(frozen=True)
class Search:
    """``search.*``: the bisection's grid ``lo``, ``lo + resolution``, …, ≤ ``hi``, and whether to
    ``verify`` every grid point below the answer (bisection assumes miss detection never rises
    with r4)."""

    lo: float = 0.5
    hi: float = 200.0
    resolution: float = 0.5
    verify: bool = True

    def __post_init__(self) -> None:
        for key in ("lo", "hi", "resolution"):
            value = check_number(f"search.{key}", getattr(self, key), 0, 1e9, open_lo=True)
            object.__setattr__(self, key, value)
        check_bool("search.verify", self.verify)
        if self.hi < self.lo:
            raise ValueError(f"search.lo={self.lo} must be <= search.hi={self.hi}")

    @property
    def points(self) -> int:
        """Grid points of the search."""
        return math.floor((self.hi - self.lo) / self.resolution + 1e-9) + 1


@dataclass(frozen=True)
class Learned:
    """``dqn.*``: DQN at a few ``r4`` (``seeds`` each, with ``overrides``)."""

    r4: tuple[float, ...] = (5.0, 50.0)
    seeds: tuple[int, ...] = (0, 1, 2)
    overrides: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        r4 = check_list(
            "dqn.r4", self.r4 or [], numbers(0, 1e9, open_lo=True), empty=True, distinct=True
        )
        object.__setattr__(self, "r4", r4)
        if r4:
            object.__setattr__(self, "seeds", seeds("dqn.seeds", self.seeds))
        object.__setattr__(
            self, "overrides", check_list("dqn.overrides", self.overrides, empty=True)
        )


@dataclass(frozen=True)
class Config:
    """The trade-off's keys (``irdrc/conf/tradeoff.yaml``); ``planned``: DQN's runs, checked."""

    params: Params = scenario_field()
    r4: tuple[float, ...] = (5.0, 10.0, 25.0, 50.0, 100.0, 200.0)
    p1_speed: tuple[float, ...] = (0.1, 1.0)
    optimum_gamma: float = 0.99
    target_miss: float | None = 0.05
    search: Search = field(default_factory=Search)
    dqn: Learned = field(default_factory=Learned)
    executor: Executor = field(default_factory=Executor, metadata=EXECUTOR)
    planned: tuple[Any, ...] = field(default=(), metadata={"keys": ()})

    def __post_init__(self) -> None:
        check_common(self)
        r4 = check_list("r4", self.r4, numbers(0, 1e9, open_lo=True), distinct=True)
        object.__setattr__(self, "r4", tuple(sorted(set(r4))))
        object.__setattr__(
            self, "p1_speed", check_list("p1_speed", self.p1_speed, numbers(0, 1), distinct=True)
        )
        check_speeds("p1_speed", self.p1_speed, self.params)
        if self.target_miss is not None:
            object.__setattr__(
                self, "target_miss", check_number("target_miss", self.target_miss, 0, 1)
            )
            solves = self.search.points * len(self.p1_speed)
            if self.search.verify and solves > SOLVES_LIMIT:
                raise ValueError(
                    f"search.resolution={self.search.resolution}: the grid from search.lo="
                    f"{self.search.lo} to search.hi={self.search.hi} has {self.search.points} "
                    f"points per p^v_1, and search.verify may solve each of them ({solves} exact "
                    f"solves, ~{solves * 0.3 / 60:.0f} min here; limit {SOLVES_LIMIT}); use a "
                    "coarser resolution or search.verify=false"
                )


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config; DQN's runs composed and checked before any work."""
    cfg = build(Config, composed.cfg)
    composed.refuse_overwritten(
        {
            "env.p1.speed": "set p1_speed=[…]",
            "reward.r4": "set r4=[…] (the exact curves) and dqn.r4=[…] (DQN's runs)",
            "seed": "set dqn.seeds=[…]",
        },
        cfg.dqn.overrides,
        fixed=("optimum_gamma", "eval.mc_episodes"),
    )
    if cfg.target_miss is None:
        composed.refuse_unread(
            ("search",),
            "the search for the smallest r4 meeting target_miss is skipped (target_miss=null)",
        )
    check_dense(cfg.params)  # the exact curves' models, before any work
    if not cfg.dqn.r4:
        composed.refuse_unread(("dqn",), "no DQN run (dqn.r4=[])")
        return cfg
    base = [
        *composed.scenario_overrides,
        *cfg.dqn.overrides,
        "eval.mc_episodes=0",
        f"optimum_gamma={cfg.optimum_gamma}",
        f"env.p1.speed={cfg.p1_speed[0]}",
    ]
    grid = parse_grid({"reward.r4": list(cfg.dqn.r4), "seed": list(cfg.dqn.seeds)})
    return replace(cfg, planned=tuple(plan(dqn, grid, base)))


def smallest_r4(
    miss_of: Callable[[float], float],
    target: float,
    lo: float,
    hi: float,
    resolution: float,
) -> tuple[float | None, int]:
    """The smallest r4 on the grid ``lo + k·resolution`` (≤ ``hi``) with ``miss_of(r4) ≤ target``.

    Bisection: assumes miss detection does not increase with r4 (a larger detection reward never
    makes the optimum watch less), and checks both ends first.

    Returns:
        (r4 or None if even ``hi`` misses the target, number of ``miss_of`` calls).
    """
    if resolution <= 0 or hi < lo:
        raise ValueError("need resolution > 0 and hi >= lo")
    calls = 0

    def ok(k: int) -> bool:
        nonlocal calls
        calls += 1
        return miss_of(lo + k * resolution) <= target

    k_hi = math.floor((hi - lo) / resolution + 1e-9)
    if ok(0):
        return lo, calls
    if not ok(k_hi):
        return None, calls
    a, b = 0, k_hi  # ok(a) is False, ok(b) is True
    while b - a > 1:
        mid = (a + b) // 2
        if ok(mid):
            b = mid
        else:
            a = mid
    return round(lo + b * resolution, 10), calls


def run(cfg: Config, run: Run) -> int:
    """Exact trade-off curves over r4, the bisection for ``target_miss``, DQN at a few points."""
    t0 = time.perf_counter()
    out = run.dir.resolve()
    r4s, ps, target = list(cfg.r4), list(cfg.p1_speed), cfg.target_miss
    rows = _exact_curves(cfg.params, ps, r4s, cfg.optimum_gamma)
    write_rows_csv(out / "tradeoff.csv", rows)
    found, scan_rows = ({}, []) if target is None else _smallest_r4_each(cfg, ps, target)
    if scan_rows:
        write_rows_csv(out / "r4_scan.csv", scan_rows)
    code, learned_rows = _dqn_points(cfg, run, ps[0])
    plots.plot_tradeoff(rows, learned_rows, out / "tradeoff.png", target=target, scan=scan_rows)
    summary = {
        "r4": r4s,
        "p1_speed": ps,
        "target_miss": target,
        "smallest_r4": found,
        "wall_seconds": time.perf_counter() - t0,
    }
    run.finish(summary)
    return code


def _exact_curves(
    base: Params, ps: list[float], r4s: list[float], gamma: float
) -> list[dict[str, Any]]:
    """The optimal policy's metrics at every (p^v_1, r4), printed as a table."""
    rows = []
    ticker = Ticker(len(ps) * len(r4s), "exact solves over r4")
    for p in ps:
        params = ref_params(base, p)
        for r4 in r4s:
            policy, m = optimal_at(params, r4, gamma)
            ticker.tick()
            rows.append(
                {
                    "series": f"p1.speed={p:g}",
                    "p1_speed": p,
                    "r4": r4,
                    "radar_states": int(policy.sum()),
                    **m.as_dict(),
                }
            )
    print(f"the optimal policy as r4 varies (exact, γ = {gamma}):\n")
    print("p1.speed      r4  radar states  miss detection  throughput  link capacity  avg reward")
    for r in rows:
        print(
            f"{r['p1_speed']:>8g}  {r['r4']:>6g}  {r['radar_states']:>12}  {r['miss_detection']:>14.4f}  "
            f"{r['throughput']:>10.4f}  {r['link_capacity']:>13.4f}  {r['avg_reward']:>10.4f}"
        )
    return rows


def _smallest_r4_each(
    cfg: Config, ps: list[float], target: float
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """For each p^v_1, the smallest r4 on the search grid meeting ``target`` (``target_miss``:
    bisection, then optionally every grid point below it); returns (answers by p^v_1, the points
    solved)."""
    base, gamma = cfg.params, cfg.optimum_gamma
    found: dict[str, Any] = {}
    scan_rows: list[dict[str, Any]] = []
    lo, hi, res = cfg.search.lo, cfg.search.hi, cfg.search.resolution
    for p in ps:
        params = ref_params(base, p)
        metrics_at: dict[float, Metrics] = {}

        def miss_of(
            r: float, params: Params = params, memo: dict[float, Metrics] = metrics_at
        ) -> float:
            if r not in memo:
                memo[r] = optimal_at(params, r, gamma)[1]
            return memo[r].miss_detection

        r4, calls = smallest_r4(miss_of, target, lo, hi, res)
        entry: dict[str, Any] = {"r4": r4, "bisection_r4": r4, "solver_calls": calls}
        if r4 is not None and cfg.search.verify:
            # Bisection assumes miss detection never rises with r4; it can (see
            # docs/REPRODUCTION.md), so every grid point below the answer is solved too.
            grid = [round(lo + k * res, 10) for k in range(round((r4 - lo) / res))]
            ticker = Ticker(len(grid), f"p1.speed={p:g}: checking every r4 below {r4:g}")
            below = []
            for r in grid:
                if miss_of(r) <= target:
                    below.append(r)
                ticker.tick()
            entry["verified"] = not below
            if below:
                entry["r4"] = r4 = below[0]
            scan_rows += [
                {"series": f"p1.speed={p:g}", "p1_speed": p, "r4": r, **metrics_at[r].as_dict()}
                for r in sorted(metrics_at)
            ]
        if r4 is not None:
            entry["metrics"] = (
                metrics_at[r4].as_dict()
                if r4 in metrics_at
                else optimal_at(params, r4, gamma)[1].as_dict()
            )
            if r4 - res >= lo - 1e-9:
                entry["miss_at_lower_neighbour"] = miss_of(round(r4 - res, 10))
        found[f"{p:g}"] = entry
        _print_found(p, entry, target, lo, hi, res, calls)
    return found, scan_rows


def _print_found(
    p: float, entry: dict[str, Any], target: float, lo: float, hi: float, res: float, calls: int
) -> None:
    r4 = entry["r4"]
    if r4 is None:
        print(f"\np1.speed={p:g}: no r4 in [{lo:g}, {hi:g}] meets miss detection ≤ {target}")
        return
    print(
        f"\np1.speed={p:g}: smallest r4 meeting miss detection ≤ {target}: {r4:g} "
        f"(grid step {res:g}; bisection: {calls} exact solves"
        + (
            ", confirmed by solving every grid point below it)"
            if entry.get("verified")
            else f"; it answered {entry['bisection_r4']:g}, but miss detection is not "
            "monotone in r4 here and the scan below it found this one)"
            if "verified" in entry
            else ")"
        )
        + f"; there miss {entry['metrics']['miss_detection']:.4f}, "
        f"throughput {entry['metrics']['throughput']:.4f}, "
        f"link capacity {entry['metrics']['link_capacity']:.4f}"
        + (
            f"; at r4 = {r4 - res:g} miss {entry['miss_at_lower_neighbour']:.4f}"
            if "miss_at_lower_neighbour" in entry
            else ""
        )
    )


def _dqn_points(cfg: Config, run: Run, p: float) -> tuple[int, list[dict[str, Any]]]:
    """DQN at ``dqn.r4`` (``dqn.seeds`` each) through the sweep engine: (exit code, mean rows)."""
    learned_rows: list[dict[str, Any]] = []
    if not cfg.planned:
        return 0, learned_rows
    out, planned = run.dir, list(cfg.planned)
    code = execute(cfg.executor, planned, out, run.recipe)
    if code != 0:
        return code, learned_rows
    for r4 in cfg.dqn.r4:
        fin = [
            json.loads((out / "trials" / pl["point_id"] / "summary.json").read_text())["metrics"]
            for pl in planned
            if same_value(pl["point"]["reward.r4"], r4)
        ]
        miss = mean_ci(to_float(f["miss_detection"]) for f in fin)
        learned_rows.append(
            {
                "series": f"dqn, p1.speed={p:g}",
                "r4": r4,
                "miss_detection": miss["mean"],
                "lo": miss["lo"],
                "hi": miss["hi"],
                "n": miss["n"],
                "throughput": mean_ci(to_float(f["throughput"]) for f in fin)["mean"],
                "link_capacity": mean_ci(to_float(f["link_capacity"]) for f in fin)["mean"],
            }
        )
    write_rows_csv(out / "tradeoff_dqn.csv", learned_rows)
    print("\nDQN (ours), final greedy policies, exact, mean over seeds:")
    for r in learned_rows:
        print(
            f"  r4={r['r4']:g}: miss {r['miss_detection']:.4f} [{r['lo']:.4f}, {r['hi']:.4f}], "
            f"throughput {r['throughput']:.4f}, link capacity {r['link_capacity']:.4f}"
        )
    return code, learned_rows
