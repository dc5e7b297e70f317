"""``recipes/constrained.py`` over the radar share (MODEL.md § D): the most data subject to a
miss-detection target when each step may share its frame — with ``env.actions=continuous`` the
trade-off region's bounds (``irdrc.core.share_cmdp``: the dual bound above, a randomised ρ policy
and the LP over 21 levels below), with ``env.actions=levels`` § A's LP over the G levels; each
beside § A's LP over the binary modes, and what time-sharing is worth at the target."""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Any

import torch

from irdrc.core.checks import grouped
from irdrc.core.params import Params
from irdrc.recipes.constrained.lp_cost import LP_BYTES_PER_NONZERO, check_lp_fits

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run


def binary_params(params: Params) -> Params:
    """The same scenario with whole-step modes (``env.actions=binary``)."""
    return dataclasses.replace(params, env=dataclasses.replace(params.env, actions="binary"))


def worth(objective: str, shared: float, binary: float, target: float) -> str:
    """What time-sharing is worth at ``target``, in words."""
    times = f" (×{shared / binary:.2f})" if binary > 0 else ""
    return (
        f"at miss detection ≤ {target:g}, sharing each step's frame gets {objective} "
        f"{shared:.4f} per step against {binary:.4f} with whole-step modes{times}"
    )


SHOWN = 8
"""At most this many randomised states are printed (``policy.csv`` has them all)."""

LP_SECONDS, LP_NONZEROS, LP_POWER = 57.0, 3.09e6, 1.6
"""The LP over radar shares as measured here (one core): 57 s at 3.09 M non-zeros (21 shares, 480
states), 359 s at 10.4 M (928 states): time ∝ non-zeros^1.6."""

LP_NOTICE_SECONDS = 60.0
"""An LP over shares estimated to take longer than this is announced before it starts."""


def share_lp_cost(params: Params) -> tuple[int, float, float]:
    """(non-zeros, seconds, bytes) of the largest LP over radar shares that ``params`` asks for:
    over its G levels (``env.actions=levels``), or the 21 of the region's feasible LP
    (``continuous``); seconds and bytes as measured here (``LP_SECONDS``)."""
    from irdrc.core.cmdp import transitions
    from irdrc.core.exact import build_model
    from irdrc.core.share_cmdp import LEVELS

    if params.env.actions == "continuous":
        grid = torch.linspace(0.0, 1.0, LEVELS, dtype=torch.float64)
        model = build_model(params, shares=grid)
    else:
        model = build_model(params)
    nonzeros = sum(P.nnz for P in transitions(model))
    seconds = LP_SECONDS * (nonzeros / LP_NONZEROS) ** LP_POWER
    return nonzeros, seconds, LP_BYTES_PER_NONZERO * nonzeros


def check_share_lp(params: Params) -> None:
    """Refuse an LP over radar shares that would need more memory than this machine has free."""
    nonzeros, _, _ = share_lp_cost(params)
    check_lp_fits(
        f"env.actions={params.env.actions}",
        "over radar shares",
        nonzeros,
        params.env.num_states,
        "use a smaller scenario (env.queue_capacity) or env.actions=binary",
    )


def share_lp_notice(params: Params) -> None:
    """Say that a long LP over shares is starting, with its estimate (``LP_NOTICE_SECONDS``)."""
    from irdrc.recipes.solve import duration, size

    nonzeros, seconds, need = share_lp_cost(params)
    if seconds > LP_NOTICE_SECONDS:
        print(
            f"[lp] the constrained optimum over radar shares: an LP of {nonzeros / 1e6:.1f} M "
            f"non-zeros over {grouped(params.env.num_states)} states, ~{duration(seconds)} and "
            f"~{size(need)} here; one solver call with no progress of its own",
            flush=True,
        )


def describe(policy: Any, levels: Any) -> list[str]:
    """One line per state where ``policy`` (a ``SharePolicy``) uses two shares (``SHOWN`` at most)."""
    from irdrc.runs.tables import state_label

    states = policy.randomised
    lines = [
        f"  {state_label(s, levels)}: ρ = {float(policy.rho[s]):.4f}, or "
        f"{float(policy.rho_alt[s]):.4f} with probability {float(policy.p_alt[s]):.4f}"
        for s in states[:SHOWN]
    ]
    if len(states) > SHOWN:
        lines.append(f"  … and {len(states) - SHOWN} more (policy.csv: rho, rho_alt, p_alt)")
    return lines


def solve_shares(cfg: Any, run: Run) -> dict[str, Any]:
    """Solve the constrained problem over shares at ``cfg.target_miss``; print it beside the binary
    modes' LP and the reward-optimal shares; write ``policy.csv`` (``SHARE_POLICY_COLUMNS``);
    return the summary (the feasible policy's exact metrics under ``metrics``)."""
    from irdrc.core.cmdp import solve_cmdp
    from irdrc.core.exact import build_model, stationary_metrics, value_iteration
    from irdrc.core.exact.continuum import ContinuumScorer
    from irdrc.core.metrics import format_table
    from irdrc.core.share_cmdp import SharePolicy, share_region
    from irdrc.runs.report import table_dict
    from irdrc.runs.results import summary_dict
    from irdrc.runs.tables import write_share_policy_csv

    params, target, objective = cfg.params, cfg.target_miss, cfg.objective
    env = params.env
    share_lp_notice(params)
    t0 = time.perf_counter()
    extra: dict[str, Any] = {}
    if env.actions == "continuous":
        region = share_region(params, target, objective)
        policy, binary = region.dual.policy, region.binary
        best = ContinuumScorer(params, cfg.optimum_gamma).optimal_metrics
        shared = region.lower
        wall = time.perf_counter() - t0
        dual = region.dual
        print(
            f"scenario={run.scenario}: maximise {objective} subject to miss detection ≤ "
            f"{target:g} over the radar share ρ ∈ [0, 1] (MODEL.md § D, {env.sensing} sensing), "
            f"{wall:.1f} s"
        )
        print(
            f"  upper bound (dual, μ = {dual.mu:.6g}, {dual.multipliers} multipliers): "
            f"{region.upper:.6f}\n"
            f"  feasible: a randomised ρ policy {dual.value:.6f} (two shares in "
            f"{len(policy.randomised)} state(s)); the LP over {region.levels} levels "
            f"{region.levels_lp.value:.6f}\n"
            f"  gap: {region.gap:.1e} — the optimum over ρ lies in [{region.lower:.6f}, "
            f"{region.upper:.6f}]"
        )
        rows = {
            "time-sharing: randomised ρ policy": policy.metrics,
            f"time-sharing: LP over {region.levels} levels": region.levels_lp.metrics,
            "binary modes: LP (MODEL.md § A)": binary.metrics,
            "reward-optimal over ρ (no target)": best,
        }
        extra = {
            "upper_bound": region.upper,
            "lower_bound": region.lower,
            "gap": region.gap,
            "mu": dual.mu,
            "multipliers": dual.multipliers,
            "levels": region.levels,
            "levels_lp_value": region.levels_lp.value,
        }
    else:
        model = build_model(params)
        sol = solve_cmdp(model, **cfg.constraints)
        binary = solve_cmdp(build_model(params, shares=(0.0, 1.0)), **cfg.constraints)
        policy = SharePolicy.from_probs(env.shares, sol.policy, sol.metrics)
        best = stationary_metrics(
            model, value_iteration(model, gamma=cfg.optimum_gamma, tol=1e-9).policy
        )
        shared = sol.value
        wall = time.perf_counter() - t0
        print(
            f"scenario={run.scenario}: maximise {objective} subject to miss detection ≤ "
            f"{target:g} over {env.levels} radar shares (env.actions=levels) — exact LP over "
            f"{model.num_actions * model.num_states} occupation variables, {wall:.1f} s"
        )
        print(
            f"optimum: {objective} {sol.value:.6g} per step; two shares in "
            f"{len(policy.randomised)} state(s)"
        )
        rows = {
            f"LP over {env.levels} levels": sol.metrics,
            "binary modes: LP (MODEL.md § A)": binary.metrics,
            f"reward-optimal over {env.levels} levels (no target)": best,
        }
        extra = {"levels": env.levels}
    for line in describe(policy, env.factor_levels):
        print(line)
    print("\nexact long-run metrics:\n")
    print(format_table(rows))
    print("\n" + worth(objective, shared, binary.value, target))
    shares = env.shares if env.actions == "levels" else None
    write_share_policy_csv(run.dir / "policy.csv", policy, env.factor_levels, shares)
    return summary_dict(
        method="constrained",
        scenario=run.scenario,
        seed=cfg.seed,
        env_steps=0,
        wall_seconds=wall,
        metrics=policy.metrics,
        optimal=policy.metrics,
        target_miss=target,
        objective=objective,
        value=shared,
        binary_value=binary.value,
        binary=binary.metrics.as_dict(),
        randomised_states=len(policy.randomised),
        reward_optimal=best.as_dict(),
        table=table_dict(rows, {}),
        **extra,
    )


def share_points(
    params: Params, p: float, objective: str, targets: list[float], ticker: Any
) -> list[dict[str, Any]]:
    """The trade-off region's frontier at ``targets`` (ascending): per target the randomised ρ
    policy's exact metrics and the dual bound (``upper``). A target whose multiplier is 0 (the
    target does not bind) binds no larger one either: those reuse its policy."""
    from irdrc.core.share_cmdp import dual_bound

    rows, start, mu, slack = [], None, 1.0, None
    for target in sorted(targets):
        if slack is None:
            dual = dual_bound(params, float(target), objective, start, mu)
            start, mu = dual.policy.rho, max(dual.mu, 1e-6)
            if dual.mu == 0.0:
                slack = dual
        else:
            dual = dataclasses.replace(slack, target_miss=float(target))
        ticker.tick()
        m = dual.policy.metrics
        rows.append(
            {
                "p1_speed": p,
                "route": "share",
                "target_miss": float(target),
                "r4": None,
                **{k: getattr(m, k) for k in ("throughput", "miss_detection", "radar_fraction")},
                "link_capacity": m.link_capacity,
                "avg_reward": m.avg_reward,
                "randomised_states": len(dual.policy.randomised),
                "upper": dual.upper,
            }
        )
    return rows


def levels_lp_value(params: Params, target: float, objective: str, levels: int) -> float:
    """§ A's LP over ``levels`` equally spaced shares at ``target``: a feasible value."""
    from irdrc.core.cmdp import solve_cmdp
    from irdrc.core.exact import build_model

    grid = torch.linspace(0.0, 1.0, levels, dtype=torch.float64)
    return solve_cmdp(build_model(params, shares=grid), target, objective).value
