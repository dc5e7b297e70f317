"""Tabular Q-learning: train (vectorised over learners), evaluate exactly and by Monte-Carlo.

python recipes/qlearning.py                                  # our profile, paper scenario
python recipes/qlearning.py algo=qlearning_paper num_learners=5
python recipes/qlearning.py env.p1.speed=0.5 reward.r4=50 seed=3 hydra.run.dir=runs/q3
"""

from __future__ import annotations

import statistics
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig
from tqdm import tqdm

from irdrc import DFRCEnv, Params
from irdrc.config import CONF_DIR, register_scenarios, scenario_name
from irdrc.evaluate import evaluate
from irdrc.metrics import format_table
from irdrc.model import build_model
from irdrc.policies import table_policy
from irdrc.qlearning import QLearningConfig, steps_to_ratio, train
from irdrc.results import summary_dict, write_policy_csv, write_rows_csv, write_summary
from irdrc.solve import ExactScorer, stationary_metrics

register_scenarios()


@hydra.main(config_path=str(CONF_DIR), config_name="qlearning", version_base=None)
def main(cfg: DictConfig) -> None:
    """Train, print the comparison table, write summary.json, policy.csv and metrics.csv."""
    torch.set_num_threads(1)
    params = Params.from_config(cfg)
    algo = QLearningConfig.from_dict(cfg.algo)
    if cfg.num_learners < 1 or cfg.mc_episodes < 0 or cfg.num_envs < 1:
        raise ValueError("num_learners and num_envs must be >= 1, mc_episodes >= 0")
    out = Path(HydraConfig.get().runtime.output_dir)
    model = build_model(params)
    scorer = ExactScorer(model, algo.gamma)
    bar = tqdm(total=algo.episodes, unit="ep", disable=not cfg.progress, dynamic_ncols=True)

    def on_eval(entry: dict) -> None:
        bar.update(entry["episode"] - bar.n)
        r = entry["optimality_ratio"]
        bar.set_postfix(ratio=f"{statistics.median(r):.4f}", min=f"{min(r):.4f}")

    res = train(
        params, algo, cfg.num_learners, cfg.seed, cfg.device, scorer=scorer, on_eval=on_eval
    )
    bar.close()

    n_learn = cfg.num_learners
    learners = [
        {
            "learner": n,
            "final_ratio": res.history[-1]["optimality_ratio"][n],
            "env_steps_to_95": steps_to_ratio(res.history, n, 0.95),
            "env_steps_to_99": steps_to_ratio(res.history, n, 0.99),
        }
        for n in range(n_learn)
    ]
    greedy = res.greedy[0].cpu()
    learned = scorer.metrics(greedy)
    opt = scorer.optimal_metrics
    rows = {
        f"{algo_name(cfg)} (exact)": learned,
        "optimal (exact)": opt,
        "round_robin (exact)": stationary_metrics(model, "round_robin"),
    }
    errs = {}
    if cfg.mc_episodes:
        env = DFRCEnv(params, batch_size=[cfg.num_envs], seed=cfg.seed + 1)
        ev = evaluate(table_policy(greedy), env, episodes=cfg.mc_episodes)
        rows[f"{algo_name(cfg)} (Monte-Carlo, episodic)"] = ev.metrics
        errs[f"{algo_name(cfg)} (Monte-Carlo, episodic)"] = ev.ci95
    env_steps = algo.episodes * params.env.horizon
    print(
        f"\nscenario={scenario_name(cfg)} algo={algo_name(cfg)} seed={cfg.seed} learners={n_learn}"
    )
    print(f"{env_steps} env steps per learner in {res.wall_seconds:.1f} s\n")
    print(format_table(rows, errors=errs))
    print("\nlearner  final ratio  env steps to 95 %  to 99 %")
    for row in learners:
        print(
            f"{row['learner']:>7}  {row['final_ratio']:>11.4f}  {row['env_steps_to_95']!s:>17}  "
            f"{row['env_steps_to_99']!s:>7}"
        )

    for th in ("95", "99"):
        got = [r[f"env_steps_to_{th}"] for r in learners]
        hit = sorted(g for g in got if g is not None)
        med = statistics.median(hit) if len(hit) == len(got) else None
        print(f"to {th} %: {len(hit)}/{len(got)} learners; median env steps {med}")

    write_summary(
        out / "summary.json",
        summary_dict(
            method=algo_name(cfg),
            scenario=scenario_name(cfg),
            seed=cfg.seed,
            env_steps=env_steps,
            wall_seconds=res.wall_seconds,
            metrics=learned,
            optimal=opt,
            learners=learners,
        ),
    )
    write_policy_csv(out / "policy.csv", greedy)
    write_rows_csv(
        out / "metrics.csv",
        [
            {
                "episode": e["episode"],
                "env_steps": e["env_steps"],
                "wall_seconds": round(e["wall_seconds"], 4),
                **{f"optimality_ratio_{n}": e["optimality_ratio"][n] for n in range(n_learn)},
                **{f"avg_reward_{n}": e["avg_reward"][n] for n in range(n_learn)},
            }
            for e in res.history
        ],
    )
    write_rows_csv(
        out / "episode_rewards.csv",
        [
            {"episode": i + 1, **{f"reward_{n}": float(r[n]) for n in range(n_learn)}}
            for i, r in enumerate(res.episode_rewards)
        ],
    )
    print(f"\nwrote summary.json, policy.csv, metrics.csv, episode_rewards.csv to {out}")


def algo_name(cfg: DictConfig) -> str:
    """The profile's name (``qlearning`` or ``qlearning_paper``)."""
    return str(cfg.algo.get("name", "qlearning"))


if __name__ == "__main__":
    main()
