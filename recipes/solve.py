"""The exact optimum: value iteration on the exact model, and exact metrics beside the baselines.

python recipes/solve.py                            # paper scenario
python recipes/solve.py env.p1.speed=1.0 reward.r4=50 hydra.run.dir=runs/solve_v1
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from irdrc import DFRCEnv, Params
from irdrc.config import CONF_DIR, register_scenarios, scenario_name
from irdrc.evaluate import evaluate
from irdrc.metrics import format_table
from irdrc.model import build_model
from irdrc.policies import table_policy
from irdrc.results import policy_table, summary_dict, write_policy_csv, write_summary
from irdrc.solve import episodic_metrics, stationary_metrics, value_iteration

register_scenarios()


@hydra.main(config_path=str(CONF_DIR), config_name="solve", version_base=None)
def main(cfg: DictConfig) -> None:
    """Solve, print the policy and the comparison table, write summary.json and policy.csv."""
    torch.set_num_threads(1)
    params = Params.from_config(cfg)
    if cfg.mc_episodes < 0 or cfg.num_envs < 1:
        raise ValueError("mc_episodes must be >= 0 and num_envs >= 1")
    out = Path(HydraConfig.get().runtime.output_dir)
    t0 = time.perf_counter()
    model = build_model(params)
    sol = value_iteration(model, gamma=cfg.gamma, tol=cfg.tol, max_iter=cfg.max_iter)
    wall = time.perf_counter() - t0
    scenario = scenario_name(cfg)
    print(
        f"scenario={scenario}: value iteration, γ={cfg.gamma}, {sol.iterations} sweeps, {wall:.2f} s"
    )
    print(f"optimal policy ({int(sol.policy.sum())} of {model.num_states} states in radar mode):\n")
    print(policy_table(model, sol.policy))

    rows, errs = {}, {}
    opt = stationary_metrics(model, sol.policy)
    rows["optimal (stationary)"] = opt
    rows["optimal (episodic)"] = episodic_metrics(model, sol.policy)
    if cfg.mc_episodes:
        env = DFRCEnv(params, batch_size=[cfg.num_envs], seed=cfg.seed)
        ev = evaluate(table_policy(sol.policy), env, episodes=cfg.mc_episodes)
        rows["optimal (Monte-Carlo)"], errs["optimal (Monte-Carlo)"] = ev.metrics, ev.ci95
    for name in ("round_robin", "always_comm", "always_radar", "random"):
        rows[f"{name} (stationary)"] = stationary_metrics(model, name)
        rows[f"{name} (episodic)"] = episodic_metrics(model, name)
    print(
        "\nexact metrics (stationary = long run; episodic = episodes of "
        f"{params.env.horizon} steps from a uniform reset; Monte-Carlo ± 95 % CI):\n"
    )
    print(format_table(rows, errors=errs))

    write_summary(
        out / "summary.json",
        summary_dict(
            method="optimal",
            scenario=scenario,
            seed=cfg.seed,
            env_steps=0,
            wall_seconds=wall,
            metrics=opt,
            optimal=opt,
            episodic={k: v for k, v in rows["optimal (episodic)"].as_dict().items()},
        ),
    )
    write_policy_csv(out / "policy.csv", sol.policy)
    print(f"\nwrote {out / 'summary.json'} and {out / 'policy.csv'}")


if __name__ == "__main__":
    main()
