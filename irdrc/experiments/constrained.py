"""The constrained design run (``recipes/constrained.py``): the most data subject to a miss-detection
target, solved exactly by the LP of ``irdrc.core.cmdp``, beside the reward-optimal policy."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from irdrc.core.cmdp import CMDPSolution, solve_cmdp
from irdrc.core.env import decode_state
from irdrc.core.metrics import format_table
from irdrc.core.model import build_model
from irdrc.core.params import Params, to_plain
from irdrc.core.solve import stationary_metrics, value_iteration
from irdrc.experiments.config import scenario_name
from irdrc.experiments.finish import table_dict
from irdrc.experiments.results import summary_dict, write_policy_csv, write_summary


def constraint_kwargs(cfg: DictConfig) -> dict[str, Any]:
    """``solve_cmdp``'s keyword arguments from a recipe config (``target_miss``, ``objective``,
    ``max_drop``, ``min_radar``)."""
    plain = to_plain(cfg)
    return {
        "target_miss": plain["target_miss"],
        "objective": plain.get("objective", "throughput"),
        "max_drop": plain.get("max_drop"),
        "min_radar": plain.get("min_radar"),
    }


def describe_randomised(sol: CMDPSolution) -> list[str]:
    """One line per randomised state: its factors and P(radar)."""
    lines = []
    for s in sol.randomised:
        d, c, r, w, v, m = (int(x) for x in decode_state(torch.tensor(s)).tolist())
        lines.append(
            f"  d={d} c={c} r={r} w={w} v={v} m={m}: radar with probability "
            f"{float(sol.p_radar[s]):.4f} (this state is {float(sol.occupancy[:, s].sum()):.4f} "
            "of the time)"
        )
    return lines


def run_constrained(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """Solve the constrained problem exactly; print it beside the reward-optimal policy; write
    ``summary.json`` (the LP optimum's exact metrics under ``optimal`` and ``metrics``) and
    ``policy.csv`` (with ``p_radar``)."""
    torch.set_num_threads(1)
    params = Params.from_config(cfg)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    kwargs = constraint_kwargs(cfg)
    t0 = time.perf_counter()
    model = build_model(params)
    sol = solve_cmdp(model, **kwargs)
    wall = time.perf_counter() - t0
    reward_opt = stationary_metrics(
        model, value_iteration(model, gamma=float(cfg.optimum_gamma)).policy
    )
    bounds = ", ".join(
        f"{name} {'≥' if name == 'radar_fraction' else '≤'} {bound:g}"
        for name, (_, bound) in sol.constraints.items()
    )
    print(
        f"scenario={scenario}: maximise {sol.objective} subject to {bounds} — exact LP over "
        f"{2 * model.num_states} occupation variables, {wall:.2f} s"
    )
    print(
        f"optimum: {sol.objective} {sol.value:.6g} per step; randomises in "
        f"{len(sol.randomised)} state(s); {len(sol.unvisited)} state(s) never visited (radar there)"
    )
    for line in describe_randomised(sol):
        print(line)
    rows = {"constrained optimum (LP)": sol.metrics, "reward-optimal (value iteration)": reward_opt}
    print("\nexact long-run metrics:\n")
    print(format_table(rows))
    summary = summary_dict(
        method="constrained",
        scenario=scenario,
        seed=int(cfg.get("seed", 0)),
        env_steps=0,
        wall_seconds=wall,
        metrics=sol.metrics,
        optimal=sol.metrics,
        target_miss=float(kwargs["target_miss"]),
        objective=sol.objective,
        value=sol.value,
        constraints={k: {"value": v, "bound": b} for k, (v, b) in sol.constraints.items()},
        randomised_states=len(sol.randomised),
        unvisited_states=len(sol.unvisited),
        reward_optimal=reward_opt.as_dict(),
        table=table_dict(rows, {}),
    )
    write_summary(out / "summary.json", summary)
    write_policy_csv(out / "policy.csv", sol.policy)
    print(f"\nwrote {out / 'summary.json'} and {out / 'policy.csv'}")
    return summary
