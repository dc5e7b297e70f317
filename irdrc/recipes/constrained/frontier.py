"""The design question's frontier (``recipes/constrained.py frontier=true``): the most data for each
miss-detection target, exactly (the LP), against the paper's route of tuning the detection reward r4
(the reward-optimal deterministic policy at each r4), on the same axes; with
``env.actions=continuous`` also the trade-off region of time-sharing (MODEL.md § D: the randomised
ρ policy and the dual bound at every target, the LP over 21 levels at the table's targets)."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from irdrc.core.cmdp import solve_cmdp
from irdrc.core.exact import build_model, stationary_metrics, value_iteration
from irdrc.core.metrics import Metrics
from irdrc.core.params import Params
from irdrc.recipes.constrained.region import binary_params, levels_lp_value, share_points
from irdrc.runs.progress import Ticker
from irdrc.runs.results import atomic_savefig, md_table, write_rows_csv, write_table_md

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

FRONTIER_COLUMNS = (
    "p1_speed",
    "route",
    "target_miss",
    "r4",
    "throughput",
    "miss_detection",
    "radar_fraction",
    "link_capacity",
    "avg_reward",
    "randomised_states",
    "upper",
)


def _lp_targets(params: Params, n: int, gamma: float, extra: list[float]) -> list[float]:
    """``n`` targets from 0 to the reward-optimal policy's miss detection, and the ``extra`` ones
    (the table's)."""
    model = build_model(params)
    top = stationary_metrics(model, value_iteration(model, gamma=gamma).policy).miss_detection
    return sorted({*np.linspace(0.0, top, n).tolist(), *extra})


def _lp_points(
    params: Params, p: float, kwargs: dict[str, Any], targets: list[float], ticker: Ticker
) -> list[dict[str, Any]]:
    """LP optima at ``targets``."""
    model = build_model(params)
    rows = []
    for target in targets:
        sol = solve_cmdp(model, **{**kwargs, "target_miss": float(target)})
        ticker.tick()
        rows.append(
            {
                "p1_speed": p,
                "route": "lp",
                "target_miss": float(target),
                "r4": None,
                **{k: getattr(sol.metrics, k) for k in FRONTIER_COLUMNS[4:9]},
                "randomised_states": len(sol.randomised),
                "upper": None,
            }
        )
    return rows


def _r4_points(
    params: Params, p: float, r4s: list[float], gamma: float, ticker: Ticker
) -> list[dict[str, Any]]:
    rows = []
    for r4 in r4s:
        _, m = optimal_at(params, r4, gamma)
        ticker.tick()
        rows.append(
            {
                "p1_speed": p,
                "route": "r4",
                "target_miss": None,
                "r4": r4,
                **{k: getattr(m, k) for k in FRONTIER_COLUMNS[4:9]},
                "randomised_states": 0,
                "upper": None,
            }
        )
    return rows


def share_table(
    share: list[dict[str, Any]], gap: list[dict[str, Any]], levels: dict[tuple[float, float], float]
) -> list[dict[str, Any]]:
    """``gap`` rows with time-sharing's bounds at their target (``share``'s rows) and the LP over
    levels (``levels``: (p1_speed, target) → value)."""
    out = []
    for g in gap:
        row = next(
            r
            for r in share
            if r["p1_speed"] == g["p1_speed"] and r["target_miss"] == g["target_miss"]
        )
        out.append(
            {
                **g,
                "share_lower": row["throughput"],
                "share_upper": row["upper"],
                "levels_lp": levels.get((g["p1_speed"], g["target_miss"])),
            }
        )
    return out


def region_md(gap: list[dict[str, Any]], levels: int) -> str:
    """The trade-off region's table at the table's targets (``tradeoff_region.md``)."""
    rows = [
        [
            f"{g['p1_speed']:g}",
            f"{g['target_miss']:g}",
            f"{g['share_lower']:.6f}",
            f"{g['share_upper']:.6f}",
            f"{g['share_upper'] - g['share_lower']:.1e}",
            f"{g['levels_lp']:.6f}",
            f"{g['lp_throughput']:.4f}",
            f"×{g['share_lower'] / g['lp_throughput']:.2f}" if g["lp_throughput"] > 0 else "—",
        ]
        for g in gap
    ]
    header = [
        "p^v_1",
        "target miss",
        "time-sharing: feasible ρ policy",
        "dual bound",
        "gap",
        f"LP over {levels} levels",
        "binary modes' LP",
        "time-sharing / binary",
    ]
    return md_table(header, rows)


def give_up_table(
    lp: list[dict[str, Any]], r4: list[dict[str, Any]], targets: list[float]
) -> list[dict[str, Any]]:
    """At each target (solved exactly by the LP among ``lp``): the LP's throughput, the best throughput of an r4-route policy meeting the
    target (and its r4), and what the r4 route gives up."""
    out = []
    for p in sorted({r["p1_speed"] for r in lp}):
        r4_rows = [r for r in r4 if r["p1_speed"] == p]
        model_lp = [r for r in lp if r["p1_speed"] == p]
        for t in targets:
            best_lp = next((r["throughput"] for r in model_lp if r["target_miss"] == t), None)
            ok = [r for r in r4_rows if r["miss_detection"] <= t + 1e-12]
            best = max(ok, key=lambda r: r["throughput"]) if ok else None
            out.append(
                {
                    "p1_speed": p,
                    "target_miss": t,
                    "lp_throughput": best_lp,
                    "r4_throughput": best["throughput"] if best else None,
                    "r4": best["r4"] if best else None,
                    "given_up": (best_lp - best["throughput"])
                    if best and best_lp is not None
                    else None,
                }
            )
    return out


def run_frontier(cfg: Any, run: Run) -> dict[str, Any]:
    """The LP frontier and the r4 route at each ``frontier_grid.p1_speed``: ``frontier.csv``,
    ``frontier_gap.csv``, ``frontier.png``, and the printed tables; returns the summary."""
    grid = cfg.frontier_grid
    ps, n, targets = list(grid.p1_speed), grid.points, list(grid.targets)
    r4s = grid.r4.values()
    kwargs = cfg.constraints
    t0 = time.perf_counter()
    lp_rows: list[dict[str, Any]] = []
    r4_rows: list[dict[str, Any]] = []
    shared = cfg.params.env.actions == "continuous"
    shares = {p: ref_params(cfg.params, p) for p in ps}
    scenarios = {p: binary_params(shares[p]) for p in ps}
    lp_targets = {p: _lp_targets(scenarios[p], n, cfg.optimum_gamma, targets) for p in ps}
    # one count for the whole run, every solve alike, so the first ETA is a fair one
    total = sum(len(t) for t in lp_targets.values()) * (2 if shared else 1) + len(ps) * len(r4s)
    total += len(ps) * len(targets) if shared else 0
    what = "exact LP solves per target, then value iteration per r4"
    if shared:
        what += ", then time-sharing's bounds per target and its LP over levels at the table's"
    ticker = Ticker(total, f"frontier: {what}")
    for p in ps:
        lp_rows += _lp_points(scenarios[p], p, kwargs, lp_targets[p], ticker)
    for p in ps:
        r4_rows += _r4_points(scenarios[p], p, r4s, cfg.optimum_gamma, ticker)
    share_rows: list[dict[str, Any]] = []
    levels: dict[tuple[float, float], float] = {}
    if shared:
        from irdrc.core.share_cmdp import LEVELS

        for p in ps:
            share_rows += share_points(shares[p], p, kwargs["objective"], lp_targets[p], ticker)
            for t in targets:
                levels[(p, t)] = levels_lp_value(shares[p], t, kwargs["objective"], LEVELS)
                ticker.tick()
    gap = give_up_table(lp_rows, r4_rows, targets)
    if shared:
        gap = share_table(share_rows, gap, levels)
    wall = time.perf_counter() - t0
    write_rows_csv(run.dir / "frontier.csv", [*lp_rows, *r4_rows, *share_rows], FRONTIER_COLUMNS)
    write_rows_csv(run.dir / "frontier_gap.csv", gap)
    if shared:
        write_table_md(run.dir / "tradeoff_region.md", region_md(gap, LEVELS), wall)
    plot_frontier(lp_rows, r4_rows, run.dir / "frontier.png", targets=targets, share=share_rows)
    print(
        f"\nthe most data per miss-detection target (LP, {n} targets per p^v_1) against the best "
        f"reward-optimal policy over r4 ∈ [{r4s[0]:g}, {r4s[-1]:g}] (step {grid.r4.step:g}), "
        f"{wall:.1f} s:\n"
    )
    print("p1.speed  target  LP throughput  r4 route throughput (r4)  given up")
    for g in gap:
        r4txt = (
            f"{g['r4_throughput']:.4f} (r4={g['r4']:g})"
            if g["r4_throughput"] is not None
            else "none meets it"
        )
        lost = f"{g['given_up']:.4f}" if g["given_up"] is not None else "all"
        print(
            f"{g['p1_speed']:>8g}  {g['target_miss']:>6g}  {g['lp_throughput']:>13.4f}  "
            f"{r4txt:>24}  {lost:>8}"
        )
    if shared:
        print(
            f"\ntime-sharing (MODEL.md § D, {cfg.params.env.sensing} sensing): the most data at "
            "each target over ρ ∈ [0, 1] — a feasible randomised ρ policy, the dual bound above "
            f"it, and the LP over {LEVELS} levels — against the binary modes' LP:\n"
        )
        print("p1.speed  target  time-sharing [feasible, bound]  LP over levels  binary LP  gain")
        for g in gap:
            times = g["share_lower"] / g["lp_throughput"] if g["lp_throughput"] > 0 else None
            print(
                f"{g['p1_speed']:>8g}  {g['target_miss']:>6g}  "
                f"[{g['share_lower']:.6f}, {g['share_upper']:.6f}]  {g['levels_lp']:>14.6f}  "
                f"{g['lp_throughput']:>9.4f}  {'—' if times is None else f'×{times:.2f}'}"
            )
    return {
        "method": "constrained_frontier",
        "p1_speed": ps,
        "targets": targets,
        "objective": kwargs["objective"],
        "wall_seconds": wall,
        "given_up": gap,
    }


def ref_params(base: Params, p1_speed: float) -> Params:
    """The scenario at ``p1_speed``."""
    return base.with_overrides({"env.p1.speed": p1_speed})


def optimal_at(params: Params, r4: float, gamma: float) -> tuple[torch.Tensor, Metrics]:
    """The optimal policy (discount ``gamma``) and its exact long-run metrics at detection reward
    ``r4``."""
    model = build_model(params.with_overrides({"reward.r4": r4}))
    policy = value_iteration(model, gamma=gamma).policy
    return policy, stationary_metrics(model, policy)


def plot_frontier(
    lp: Sequence[Mapping[str, Any]],
    r4: Sequence[Mapping[str, Any]],
    path: Path,
    *,
    targets: Sequence[float] = (),
    share: Sequence[Mapping[str, Any]] = (),
) -> None:
    """Throughput against miss detection: the LP frontier (a line per p^v_1) and the reward-optimal
    deterministic policies over r4 (markers, same colour), with the targets as vertical lines; with
    ``share`` rows, time-sharing's frontier (thick line: the feasible policies; dotted: the dual
    bound at each target)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.6))
    for p in sorted({float(r["p1_speed"]) for r in lp}):
        pts = sorted(
            (r for r in lp if float(r["p1_speed"]) == p), key=lambda r: r["miss_detection"]
        )
        (line,) = ax.plot(
            [r["miss_detection"] for r in pts],
            [r["throughput"] for r in pts],
            label=f"most data at each target (exact LP), p1.speed={p:g}",
        )
        own = [r for r in r4 if float(r["p1_speed"]) == p]
        ax.plot(
            [r["miss_detection"] for r in own],
            [r["throughput"] for r in own],
            "o",
            mfc="none",
            color=line.get_color(),
            label=f"reward-optimal policy at each r4 (r4 route), p1.speed={p:g}",
        )
        mine = sorted(
            (r for r in share if float(r["p1_speed"]) == p), key=lambda r: r["target_miss"]
        )
        if mine:
            ax.plot(
                [r["miss_detection"] for r in mine],
                [r["throughput"] for r in mine],
                lw=3,
                alpha=0.6,
                color=line.get_color(),
                label=f"time-sharing over ρ (feasible), p1.speed={p:g}",
            )
            ax.plot(
                [r["target_miss"] for r in mine],
                [r["upper"] for r in mine],
                ":",
                color="black",
                lw=1,
                label="time-sharing's dual bound"
                if p == min(float(r["p1_speed"]) for r in lp)
                else None,
            )
    for i, t in enumerate(targets):
        label = "the recipe's targets (target_miss)" if i == 0 else None
        ax.axvline(t, color="tab:red", linestyle=":", alpha=0.6, label=label)
    ax.set_xlabel("miss detection probability")
    ax.set_ylabel("throughput (packets sent per step)")
    title = "The design question: most data subject to a miss-detection target"
    ax.set_title(title + ("\nwhole-step modes against time-sharing" if share else ""), fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=80)
