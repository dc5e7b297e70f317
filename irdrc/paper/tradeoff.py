"""The radar/communication trade-off the paper only mentions (its claim 3), exactly.

``run_tradeoff`` maps the exact optimum over r4 and finds, by bisection, the smallest r4 whose
optimal policy meets a miss-detection target; DQN runs at a few r4 go through the sweep engine.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from irdrc.core.metrics import Metrics
from irdrc.core.model import build_model
from irdrc.core.params import Params, check_bool, check_number, to_plain
from irdrc.core.solve import stationary_metrics, value_iteration
from irdrc.experiments.grid import parse_grid
from irdrc.experiments.progress import Ticker
from irdrc.experiments.results import atomic_write_text, write_rows_csv
from irdrc.experiments.sweep import execute, plan
from irdrc.experiments.validate import SOLVES_LIMIT, check_common, check_executor
from irdrc.paper import plots
from irdrc.paper.figures import mean_ci, same_value, to_float


def ref_params(base: Params, p1_speed: float) -> Params:
    """The scenario at ``p1_speed``."""
    return base.with_overrides({"env.p1.speed": p1_speed})


def optimal_at(params: Params, r4: float, gamma: float) -> tuple[torch.Tensor, Metrics]:
    """The optimal policy (discount ``gamma``) and its exact long-run metrics at detection reward
    ``r4``."""
    p = params.with_overrides({"reward.r4": r4})
    model = build_model(p)
    policy = value_iteration(model, gamma=gamma).policy
    return policy, stationary_metrics(model, policy)


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


def run_tradeoff(cfg: DictConfig, out: Path, scenario: list[str] | None = None) -> int:
    """Exact trade-off curves over r4, the bisection for ``target_miss``, DQN at a few points."""
    t0 = time.perf_counter()
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    r4s = sorted({float(r) for r in to_plain(cfg.r4)})
    ps = [float(p) for p in to_plain(cfg.p1_speed)]
    if not r4s or any(r <= 0 for r in r4s) or not ps:
        raise ValueError("r4 must be a non-empty list of positive values; p1_speed non-empty")
    target = cfg.target_miss
    if target is not None and not 0.0 <= float(target) <= 1.0:
        raise ValueError(f"target_miss={target!r} must be in [0, 1] (or null)")
    base = Params.from_config(cfg)
    gamma = float(cfg.optimum_gamma)
    rows = _exact_curves(base, ps, r4s, gamma)
    write_rows_csv(out / "tradeoff.csv", rows)
    found, scan_rows = ({}, []) if target is None else _smallest_r4_each(cfg, base, ps, gamma)
    if scan_rows:
        write_rows_csv(out / "r4_scan.csv", scan_rows)
    code, learned_rows = _dqn_points(cfg, out, ps[0], scenario, gamma)
    plots.plot_tradeoff(
        rows,
        learned_rows,
        out / "tradeoff.png",
        target=None if target is None else float(target),
        scan=scan_rows,
    )
    summary = {
        "r4": r4s,
        "p1_speed": ps,
        "target_miss": target,
        "smallest_r4": found,
        "wall_seconds": time.perf_counter() - t0,
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    print(
        f"\nwrote tradeoff.csv, tradeoff.png, summary.json to {out} ({summary['wall_seconds']:.0f} s)"
    )
    return code


def _exact_curves(base: Params, ps: list[float], r4s: list[float], gamma: float) -> list[dict]:
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
    cfg: DictConfig, base: Params, ps: list[float], gamma: float
) -> tuple[dict[str, Any], list[dict]]:
    """For each p^v_1, the smallest r4 on the search grid meeting ``target_miss`` (bisection, then
    optionally every grid point below it); returns (answers by p^v_1, the points solved)."""
    target = float(cfg.target_miss)
    found: dict[str, Any] = {}
    scan_rows: list[dict] = []
    lo, hi, res = float(cfg.search.lo), float(cfg.search.hi), float(cfg.search.resolution)
    for p in ps:
        params = ref_params(base, p)
        metrics_at: dict[float, Metrics] = {}

        def miss_of(r: float, params: Params = params, memo: dict = metrics_at) -> float:
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


def _dqn_points(
    cfg: DictConfig, out: Path, p: float, scenario: list[str] | None, gamma: float
) -> tuple[int, list[dict]]:
    """DQN at ``dqn.r4`` (``dqn.seeds`` each) through the sweep engine: (exit code, mean rows)."""
    learned_rows: list[dict] = []
    dqn_r4 = [float(r) for r in (to_plain(cfg.dqn.r4) or [])]
    if not dqn_r4:
        return 0, learned_rows
    seeds = [int(s) for s in to_plain(cfg.dqn.seeds)]
    base_ov = [
        *(scenario or []),
        *[str(o) for o in cfg.dqn.overrides],
        "eval.mc_episodes=0",
        f"optimum_gamma={gamma}",
        f"env.p1.speed={p}",
    ]
    planned = plan("dqn", parse_grid({"reward.r4": dqn_r4, "seed": seeds}), base_ov)
    code = execute(cfg, planned, out)
    if code != 0:
        return code, learned_rows
    for r4 in dqn_r4:
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


def validate_tradeoff(cfg: DictConfig) -> None:
    """Every key of ``recipes/conf/tradeoff.yaml``, and the cost of the search, before any work."""
    check_common(cfg)
    check_executor(cfg)
    r4 = to_plain(cfg.r4)
    if not isinstance(r4, list) or not r4:
        raise ValueError(f"r4={r4!r} must be a non-empty list of detection rewards")
    for i, v in enumerate(r4):
        check_number(f"r4[{i}]", v, 0, 1e9, open_lo=True)
    ps = to_plain(cfg.p1_speed)
    if not isinstance(ps, list) or not ps:
        raise ValueError(f"p1_speed={ps!r} must be a non-empty list of probabilities")
    for i, v in enumerate(ps):
        check_number(f"p1_speed[{i}]", v, 0, 1)
    if cfg.target_miss is not None:
        check_number("target_miss", cfg.target_miss, 0, 1)
        lo = check_number("search.lo", cfg.search.lo, 0, 1e9, open_lo=True)
        hi = check_number("search.hi", cfg.search.hi, 0, 1e9, open_lo=True)
        res = check_number("search.resolution", cfg.search.resolution, 0, 1e9, open_lo=True)
        check_bool("search.verify", cfg.search.verify)
        if hi < lo:
            raise ValueError(f"search.lo={lo} must be <= search.hi={hi}")
        points = math.floor((hi - lo) / res + 1e-9) + 1
        if cfg.search.verify and points * len(ps) > SOLVES_LIMIT:
            raise ValueError(
                f"search.resolution={res}: the grid from search.lo={lo} to search.hi={hi} has "
                f"{points} points per p^v_1, and search.verify may solve each of them "
                f"({points * len(ps)} exact solves, ~{points * len(ps) * 0.3 / 60:.0f} min here; "
                f"limit {SOLVES_LIMIT}); use a coarser resolution or search.verify=false"
            )
    if to_plain(cfg.dqn.r4):
        for i, v in enumerate(to_plain(cfg.dqn.r4)):
            check_number(f"dqn.r4[{i}]", v, 0, 1e9, open_lo=True)
        seeds = to_plain(cfg.dqn.seeds)
        if not isinstance(seeds, list) or not seeds:
            raise ValueError(f"dqn.seeds={seeds!r} must be a non-empty list of seeds")
