"""The runs behind the recipes: one function per method, shared by the single-run recipes and sweeps.

Each ``run_*`` takes a composed config (the recipe's Hydra config, or the same composed by
``recipes/sweep.py`` for one grid point) and an output directory, writes the run's files there, prints
its table, and returns the ``summary.json`` record.
"""

from __future__ import annotations

import hashlib
import json
import math
import statistics
import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from irdrc import dqn as dq
from irdrc import qlearning as ql
from irdrc.config import scenario_name
from irdrc.dqn import (
    DQNConfig,
    NetworkConfig,
    checkpoint_state,
    greedy_table,
    load_checkpoint,
)
from irdrc.env import DFRCEnv
from irdrc.evaluate import evaluate
from irdrc.metrics import Metrics, format_table
from irdrc.model import build_model
from irdrc.params import Params
from irdrc.policies import table_policy
from irdrc.qlearning import QLearningConfig, steps_to_ratio
from irdrc.results import (
    atomic_write_text,
    clean_number,
    policy_table,
    summary_dict,
    write_policy_csv,
    write_rows_csv,
    write_summary,
)
from irdrc.solve import (
    ExactScorer,
    episodic_metrics,
    stationary_metrics,
    value_iteration,
)
from irdrc.sweep import parse_grid, point_overrides  # the same grid grammar as sweep.grid
from irdrc.tracking import log_scalars, make_logger


def qlearning_paper_metrics(params: Params, seed: int, cache_dir: Path, progress: bool) -> Metrics:
    """Exact metrics of Q-learning's paper profile trained on ``params`` (cached on disk)."""
    key = hashlib.sha256(json.dumps([params.to_dict(), seed, str(ql.PAPER)]).encode()).hexdigest()[
        :16
    ]
    path = cache_dir / f"qlearning_paper-{key}.json"
    if path.is_file():
        return Metrics.from_dict(json.loads(path.read_text()))
    bar = tqdm(
        total=ql.PAPER.episodes, unit="ep", desc="Q-learning paper profile", disable=not progress
    )
    res = ql.train(params, ql.PAPER, 1, seed, on_eval=lambda e: bar.update(e["episode"] - bar.n))
    bar.close()
    m = stationary_metrics(build_model(params), res.greedy[0])
    atomic_write_text(path, json.dumps(m.as_dict()))
    return m


def run_solve(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """Solve, print the policy and the comparison table, write summary.json and policy.csv."""
    torch.set_num_threads(1)
    params = Params.from_config(cfg)
    if cfg.mc_episodes < 0 or cfg.num_envs < 1:
        raise ValueError("mc_episodes must be >= 0 and num_envs >= 1")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    t0 = time.perf_counter()
    model = build_model(params)
    sol = value_iteration(model, gamma=cfg.gamma, tol=cfg.tol, max_iter=cfg.max_iter)
    wall = time.perf_counter() - t0
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

    summary = summary_dict(
        method="optimal",
        scenario=scenario,
        seed=cfg.seed,
        env_steps=0,
        wall_seconds=wall,
        metrics=opt,
        optimal=opt,
        episodic={k: v for k, v in rows["optimal (episodic)"].as_dict().items()},
    )
    write_summary(out / "summary.json", summary)
    write_policy_csv(out / "policy.csv", sol.policy)
    print(f"\nwrote {out / 'summary.json'} and {out / 'policy.csv'}")
    return summary


def _batch_points(cfg: DictConfig) -> list[dict[str, Any]]:
    """The scenario points of ``batch_grid`` (one point, no overrides, when it is unset)."""
    grid = cfg.get("batch_grid")
    if grid is None:
        return [{}]
    points = parse_grid(grid)
    for point in points:
        for key in point:
            if not key.startswith(("env.", "reward.")):
                raise ValueError(
                    f"batch_grid key {key!r} must be an env. or reward. key (one batch varies "
                    "the scenario; vary algo settings with a sweep)"
                )
    return points


def run_qlearning(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """Train, print the comparison table, write summary.json, policy.csv, metrics.csv,
    learners.csv and episode_rewards.csv.

    With ``batch_grid`` set, every point of the grid is a scenario with ``num_learners`` learners
    of its own, all trained in one vectorised batch.
    """
    torch.set_num_threads(1)
    base = Params.from_config(cfg)
    algo = QLearningConfig.from_dict(cfg.algo)
    if cfg.num_learners < 1 or cfg.mc_episodes < 0 or cfg.num_envs < 1:
        raise ValueError("num_learners and num_envs must be >= 1, mc_episodes >= 0")
    points = _batch_points(cfg)
    scenarios = [base.with_overrides(p) for p in points]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    models = [build_model(p) for p in scenarios]
    scorers = [ExactScorer(m, algo.gamma) for m in models]
    bar = tqdm(total=algo.episodes, unit="ep", disable=not cfg.progress, dynamic_ncols=True)

    def on_eval(entry: dict) -> None:
        bar.update(entry["episode"] - bar.n)
        r = entry["optimality_ratio"]
        bar.set_postfix(ratio=f"{statistics.median(r):.4f}", min=f"{min(r):.4f}")

    res = ql.train(
        scenarios, algo, cfg.num_learners, cfg.seed, cfg.device, scorer=scorers, on_eval=on_eval
    )
    bar.close()

    n_learn = cfg.num_learners
    n_rows = n_learn * len(scenarios)
    learners = []
    for n in range(n_rows):
        g = res.group[n]
        final = scorers[g].metrics(res.greedy[n].cpu())
        learners.append(
            {
                **points[g],
                "learner": n % n_learn,
                "row": n,
                "final_ratio": res.history[-1]["optimality_ratio"][n],
                "env_steps_to_95": steps_to_ratio(res.history, n, 0.95),
                "env_steps_to_99": steps_to_ratio(res.history, n, 0.99),
                **{k: clean_number(v) for k, v in final.as_dict().items()},
            }
        )
    greedy = res.greedy[0].cpu()
    learned = scorers[0].metrics(greedy)
    opt = scorers[0].optimal_metrics
    model = models[0]
    env_steps = algo.episodes * base.env.horizon
    print(
        f"\nscenario={scenario} algo={algo_name(cfg)} seed={cfg.seed} learners={n_learn}"
        + (f" × {len(scenarios)} scenarios (batch_grid)" if len(scenarios) > 1 else "")
    )
    print(f"{env_steps} env steps per learner in {res.wall_seconds:.1f} s\n")
    if len(scenarios) == 1:
        rows = {
            f"{algo_name(cfg)} (exact)": learned,
            "optimal (exact)": opt,
            "round_robin (exact)": stationary_metrics(model, "round_robin"),
        }
        errs = {}
        if cfg.mc_episodes:
            env = DFRCEnv(base, batch_size=[cfg.num_envs], seed=cfg.seed + 1)
            ev = evaluate(table_policy(greedy), env, episodes=cfg.mc_episodes)
            rows[f"{algo_name(cfg)} (Monte-Carlo, episodic)"] = ev.metrics
            errs[f"{algo_name(cfg)} (Monte-Carlo, episodic)"] = ev.ci95
        print(format_table(rows, errors=errs))
        print("\nlearner  final ratio  env steps to 95 %  to 99 %")
        for row in learners:
            print(
                f"{row['learner']:>7}  {row['final_ratio']:>11.4f}  {row['env_steps_to_95']!s:>17}  "
                f"{row['env_steps_to_99']!s:>7}"
            )
    else:
        print("scenario                        optimum avg reward  final ratio (median, min)")
        for g, point in enumerate(points):
            mine = [r["final_ratio"] for r in learners if res.group[r["row"]] == g]
            label = " ".join(point_overrides(point))
            print(
                f"{label:<32}{scorers[g].optimal_metrics.avg_reward:>18.4f}  "
                f"{statistics.median(mine):.4f}, {min(mine):.4f}"
            )

    for th in ("95", "99"):
        got = [r[f"env_steps_to_{th}"] for r in learners]
        hit = sorted(g for g in got if g is not None)
        med = statistics.median(hit) if len(hit) == len(got) else None
        print(f"to {th} %: {len(hit)}/{len(got)} learners; median env steps {med}")

    extra: dict[str, Any] = {"learners": [_summary_row(r) for r in learners]}
    if len(scenarios) > 1:
        extra["batch_grid"] = [
            {
                "overrides": point_overrides(point),
                "optimal": {
                    k: clean_number(v) for k, v in scorers[g].optimal_metrics.as_dict().items()
                },
            }
            for g, point in enumerate(points)
        ]
    summary = summary_dict(
        method=algo_name(cfg),
        scenario=scenario,
        seed=cfg.seed,
        env_steps=env_steps,
        wall_seconds=res.wall_seconds,
        metrics=learned,
        optimal=opt,
        **extra,
    )
    write_summary(out / "summary.json", summary)
    write_policy_csv(out / "policy.csv", greedy)
    write_rows_csv(out / "learners.csv", learners)
    write_rows_csv(
        out / "metrics.csv",
        [
            {
                "episode": e["episode"],
                "env_steps": e["env_steps"],
                "wall_seconds": round(e["wall_seconds"], 4),
                **{f"optimality_ratio_{n}": e["optimality_ratio"][n] for n in range(n_rows)},
                **{f"avg_reward_{n}": e["avg_reward"][n] for n in range(n_rows)},
            }
            for e in res.history
        ],
    )
    write_rows_csv(
        out / "episode_rewards.csv",
        [
            {"episode": i + 1, **{f"reward_{n}": float(r[n]) for n in range(n_rows)}}
            for i, r in enumerate(res.episode_rewards)
        ],
    )
    print(
        f"\nwrote summary.json, policy.csv, learners.csv, metrics.csv, episode_rewards.csv to {out}"
    )
    return summary


def _summary_row(row: dict[str, Any]) -> dict[str, Any]:
    keys = ("learner", "row", "final_ratio", "env_steps_to_95", "env_steps_to_99")
    return {k: row[k] for k in keys} | {
        k: v for k, v in row.items() if k.startswith(("env.", "reward."))
    }


def algo_name(cfg: DictConfig) -> str:
    """The profile's name (``qlearning`` or ``qlearning_paper``)."""
    return str(cfg.algo.get("name", "qlearning"))


def run_dqn(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """Train, evaluate, write the run directory, print the comparison table."""
    torch.set_num_threads(int(cfg.num_threads))
    params = Params.from_config(cfg)
    algo = DQNConfig.from_dict(cfg.algo)
    net = NetworkConfig.from_dict(cfg.network)
    if cfg.eval.every_frames < 1 or cfg.eval.mc_episodes < 0 or cfg.eval.mc_num_envs < 1:
        raise ValueError(
            "eval.every_frames and eval.mc_num_envs must be >= 1, eval.mc_episodes >= 0"
        )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    state = None
    if cfg.resume:
        state = load_checkpoint(Path(str(cfg.resume)).expanduser())
    exp_name = f"{scenario}__{algo.name}__{cfg.seed}"
    OmegaConf.save(cfg, out / "config.yaml")
    logger = make_logger(
        cfg.logger.backend,
        exp_name,
        out / "logs",
        project=cfg.logger.project,
        mode=cfg.logger.mode,
        config=OmegaConf.to_container(cfg, resolve=True),
    )
    # The optimum every result is read against is defined by the model's discount, whatever the
    # learner's own algo.gamma.
    scorer = ExactScorer(build_model(params), gamma=float(cfg.optimum_gamma))
    bar = tqdm(total=algo.total_frames, unit="step", disable=not cfg.progress, dynamic_ncols=True)
    latest = {"ratio": math.nan}

    def on_batch(info: dict) -> None:
        bar.update(info["env_steps"] - bar.n)
        bar.set_postfix(
            eps=f"{info['epsilon']:.3f}", loss=f"{info['loss']:.3g}", opt=f"{latest['ratio']:.4f}"
        )
        log_scalars(
            logger,
            {
                "train/epsilon": info["epsilon"],
                "train/loss": info["loss"],
                "train/beta": info["beta"],
            },
            info["env_steps"],
        )

    def on_eval(entry: dict) -> None:
        latest["ratio"] = entry["optimality_ratio"]
        log_scalars(
            logger,
            {
                f"eval/{k}": v
                for k, v in entry.items()
                if k not in ("env_steps", "wall_seconds", "updates")
            },
            entry["env_steps"],
        )
        log_scalars(
            logger,
            {"time/wall_seconds": entry["wall_seconds"], "time/updates": entry["updates"]},
            entry["env_steps"],
        )

    run = dq.train(
        params,
        algo,
        net,
        seed=int(cfg.seed),
        device=cfg.device,
        eval_every_frames=int(cfg.eval.every_frames),
        on_eval=on_eval,
        on_batch=on_batch,
        state=state,
        scorer=scorer,
    )
    bar.close()
    print(
        f"replay sampler: {run.sampler_name}"
        + (" (prioritised)" if algo.prioritized else " (uniform)")
    )

    config_plain = OmegaConf.to_container(cfg, resolve=True)
    torch.save(checkpoint_state(run, config_plain), out / "checkpoint.pt")
    write_rows_csv(out / "metrics.csv", run.history)
    write_rows_csv(out / "episode_rewards.csv", run.episode_rewards)

    env = DFRCEnv(params, batch_size=[int(cfg.eval.mc_num_envs)], seed=int(cfg.seed) + 1)
    table = greedy_table(run.qnet, env)
    learned = scorer.metrics(table)
    model = scorer.model
    rows: dict[str, Metrics] = {f"{algo.name} (exact)": learned}
    errs = {}
    if cfg.eval.mc_episodes:
        ev = evaluate(table_policy(table), env, episodes=int(cfg.eval.mc_episodes))
        (
            rows[f"{algo.name} (Monte-Carlo, episodic)"],
            errs[f"{algo.name} (Monte-Carlo, episodic)"],
        ) = ev.metrics, ev.ci95
    rows["optimal (exact)"] = scorer.optimal_metrics
    rows["round_robin (exact)"] = stationary_metrics(model, "round_robin")
    if cfg.compare.qlearning_paper:
        cache = Path(str(cfg.cache_dir)).expanduser()
        rows["qlearning_paper (exact)"] = qlearning_paper_metrics(
            params, int(cfg.seed), cache, cfg.progress
        )

    ratios = [e["optimality_ratio"] for e in run.history]
    first99 = next((e["env_steps"] for e in run.history if e["optimality_ratio"] >= 0.99), None)
    summary = summary_dict(
        method=algo.name,
        scenario=scenario,
        seed=int(cfg.seed),
        env_steps=run.frames,
        wall_seconds=run.wall_seconds,
        metrics=learned,
        optimal=scorer.optimal_metrics,
        updates=run.updates,
        env_steps_to_99=first99,
        replay_sampler=run.sampler_name,
    )
    write_summary(out / "summary.json", summary)
    write_policy_csv(out / "policy.csv", table)
    log_scalars(logger, {"final/optimality_ratio": ratios[-1]}, run.frames)
    if logger is not None and hasattr(logger, "experiment") and cfg.logger.backend == "wandb":
        logger.experiment.finish()

    print(f"\nscenario={scenario} algo={algo.name} network={list(net.hidden)} seed={cfg.seed}")
    print(
        f"{run.frames} env steps, {run.updates} updates in {run.wall_seconds:.1f} s; "
        f"first ≥ 99 % of optimum at {first99} env steps (exact evaluation every "
        f"{cfg.eval.every_frames})\n"
    )
    print(format_table(rows, errors=errs))
    print(
        "\nwrote summary.json, policy.csv, metrics.csv, episode_rewards.csv, config.yaml, "
        f"checkpoint.pt to {out}"
    )

    return summary


RUNNERS = {"solve": run_solve, "qlearning": run_qlearning, "dqn": run_dqn}
"""Method name → run function (what ``recipes/sweep.py`` calls per grid point)."""
