"""The runs behind the recipes: one function per method, shared by single-run recipes and sweeps.

Each ``run_*`` takes a composed config (the recipe's Hydra config, or the same composed by a sweep
for one grid point) and an output directory, writes the run's files there, prints its table, and
returns the ``summary.json`` record. Every learner finishes the same way (``finish_run``):
``metrics.csv`` (one schema: ``irdrc.agents.base.PROGRESS_FIELDS``), ``episode_rewards.csv``,
``learners.csv``, ``policy.csv``, ``summary.json`` (every row of the printed table), and
``checkpoint.pt`` for learners that checkpoint.
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

from irdrc.agents import dqn, qlearning
from irdrc.agents.base import EPISODE_FIELDS, PROGRESS_FIELDS, Hooks, RunRecord
from irdrc.core.env import DFRCEnv
from irdrc.core.evaluate import evaluate
from irdrc.core.metrics import Metrics, format_table
from irdrc.core.model import build_model
from irdrc.core.params import Params
from irdrc.core.policies import table_policy
from irdrc.core.solve import ExactScorer, episodic_metrics, stationary_metrics, value_iteration
from irdrc.experiments.config import compose, scenario_name
from irdrc.experiments.grid import is_scenario_key, parse_grid, point_overrides
from irdrc.experiments.results import (
    clean_number,
    policy_table,
    summary_dict,
    write_policy_csv,
    write_rows_csv,
    write_summary,
)
from irdrc.experiments.tracking import log_scalars, make_logger

LEARNERS = {dqn.NAME: dqn, qlearning.NAME: qlearning}
"""Method name → learner module (``Config``, ``train``; see ``irdrc.agents.base``)."""


def run_solve(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """Solve, print the policy and the comparison table, write summary.json and policy.csv."""
    torch.set_num_threads(1)
    params = Params.from_config(cfg)
    _check_eval(cfg)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    gamma = float(cfg.optimum_gamma)
    t0 = time.perf_counter()
    model = build_model(params)
    sol = value_iteration(model, gamma=gamma, tol=cfg.tol, max_iter=cfg.max_iter)
    wall = time.perf_counter() - t0
    print(f"scenario={scenario}: value iteration, γ={gamma}, {sol.iterations} sweeps, {wall:.2f} s")
    print(f"optimal policy ({int(sol.policy.sum())} of {model.num_states} states in radar mode):\n")
    print(policy_table(model, sol.policy))

    rows, errs = {}, {}
    opt = stationary_metrics(model, sol.policy)
    rows["optimal (stationary)"] = opt
    rows["optimal (episodic)"] = episodic_metrics(model, sol.policy)
    if cfg.eval.mc_episodes:
        env = DFRCEnv(params, batch_size=[int(cfg.eval.mc_num_envs)], seed=cfg.seed)
        ev = evaluate(table_policy(sol.policy), env, episodes=int(cfg.eval.mc_episodes))
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
        episodic=rows["optimal (episodic)"].as_dict(),
        table=_table_dict(rows, errs),
    )
    write_summary(out / "summary.json", summary)
    write_policy_csv(out / "policy.csv", sol.policy)
    print(f"\nwrote {out / 'summary.json'} and {out / 'policy.csv'}")
    return summary


def run_qlearning(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """Tabular Q-learning (``batch_grid``: several scenarios in one vectorised batch)."""
    return run_learner(qlearning.NAME, cfg, out, scenario)


def run_dqn(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """DQN from TorchRL parts (checkpoints; ``resume`` continues one)."""
    return run_learner(dqn.NAME, cfg, out, scenario)


def _check_eval(cfg: DictConfig) -> None:
    ev = cfg.eval
    if int(ev.mc_episodes) < 0 or int(ev.mc_num_envs) < 1:
        raise ValueError("eval.mc_episodes must be >= 0 and eval.mc_num_envs >= 1")
    if "every_frames" in ev and int(ev.every_frames) < 1:
        raise ValueError(f"eval.every_frames={ev.every_frames!r} must be >= 1")


def batch_points(cfg: DictConfig) -> list[dict[str, Any]]:
    """The scenario points of ``batch_grid`` (one point, no overrides, when it is unset)."""
    grid = cfg.get("batch_grid")
    if grid is None:
        return [{}]
    points = parse_grid(grid, "batch_grid")
    for key in points[0]:
        if not is_scenario_key(key):
            raise ValueError(
                f"batch_grid key {key!r} must be an env. or reward. key (one batch varies "
                "the scenario; vary algo settings with a sweep)"
            )
    return points


class _Progress:
    """Progress bar and logging hooks of a run (learner 0 is the one logged as ``eval/…``)."""

    def __init__(self, total: int, enabled: bool, logger) -> None:
        self.bar = tqdm(total=total, unit="step", disable=not enabled, dynamic_ncols=True)
        self.logger = logger
        self.ratio = math.nan
        self.min_ratio = math.nan

    def on_batch(self, info: dict[str, Any]) -> None:
        self.bar.update(info["env_steps"] - self.bar.n)
        post = {"opt": f"{self.ratio:.4f}"}
        if not math.isnan(self.min_ratio):
            post["min"] = f"{self.min_ratio:.4f}"
        if "epsilon" in info:
            post["eps"] = f"{info['epsilon']:.3f}"
        self.bar.set_postfix(post)
        scalars = {f"train/{k}": v for k, v in info.items() if k not in ("env_steps",)}
        log_scalars(self.logger, scalars, info["env_steps"])

    def on_eval(self, records: list[dict[str, Any]]) -> None:
        first = records[0]
        self.ratio = first["optimality_ratio"]
        if len(records) > 1:
            self.min_ratio = min(r["optimality_ratio"] for r in records)
        step = first["env_steps"]
        skip = ("learner", "env_steps", "episodes", "wall_seconds", "updates")
        log_scalars(self.logger, {f"eval/{k}": v for k, v in first.items() if k not in skip}, step)
        log_scalars(
            self.logger,
            {"time/wall_seconds": first["wall_seconds"], "time/updates": first["updates"]},
            step,
        )

    def close(self) -> None:
        self.bar.close()


def run_learner(
    method: str, cfg: DictConfig, out: Path, scenario: str | None = None
) -> dict[str, Any]:
    """Train ``method`` on the composed config ``cfg`` and finish the run in ``out``."""
    agent = LEARNERS[method]
    torch.set_num_threads(int(cfg.get("num_threads", 1)))
    config = agent.Config.from_node(cfg)
    base = Params.from_config(cfg)
    _check_eval(cfg)
    num_learners = int(cfg.get("num_learners", 1))
    if num_learners < 1:
        raise ValueError(f"num_learners={num_learners} must be >= 1")
    points = batch_points(cfg)
    scenarios = [base.with_overrides(p) for p in points]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    resume = None
    if cfg.get("resume"):
        resume = dqn.load_checkpoint(Path(str(cfg.resume)).expanduser())
    name = str(cfg.algo.get("name", method))
    exp_name = f"{scenario}__{name}__{cfg.seed}"
    OmegaConf.save(cfg, out / "config.yaml")
    logger = make_logger(
        cfg.logger.backend,
        exp_name,
        out / "logs",
        project=cfg.logger.project,
        mode=cfg.logger.mode,
        config=OmegaConf.to_container(cfg, resolve=True),
    )
    gamma = float(cfg.optimum_gamma)
    scorers = [ExactScorer(build_model(p), gamma=gamma) for p in scenarios]
    progress = _Progress(config.env_steps(base.env.horizon), bool(cfg.progress), logger)
    record = agent.train(
        scenarios,
        config,
        num_learners=num_learners,
        seed=int(cfg.seed),
        device=cfg.device,
        scorers=scorers,
        eval_every_frames=int(cfg.eval.every_frames),
        hooks=Hooks(on_eval=progress.on_eval, on_batch=progress.on_batch),
        resume=resume,
    )
    progress.close()
    comparisons = comparison_rows(cfg, base)
    summary = finish_run(
        name, cfg, out, scenario, record, scenarios, scorers, points, num_learners, comparisons
    )
    log_scalars(logger, {"final/optimality_ratio": summary["optimality_ratio"]}, record.env_steps)
    if logger is not None and cfg.logger.backend == "wandb":
        logger.experiment.finish()
    return summary


def finish_run(
    name: str,
    cfg: DictConfig,
    out: Path,
    scenario: str,
    record: RunRecord,
    scenarios: list[Params],
    scorers: list[ExactScorer],
    points: list[dict[str, Any]],
    num_learners: int,
    comparisons: dict[str, Metrics],
) -> dict[str, Any]:
    """Write the run files of every learner the same way, print the table, return the summary."""
    learners = learner_rows(record, scorers, points, num_learners)
    write_rows_csv(out / "metrics.csv", record.history, PROGRESS_FIELDS)
    write_rows_csv(out / "episode_rewards.csv", record.episode_rewards, EPISODE_FIELDS)
    write_rows_csv(out / "learners.csv", learners)
    greedy = record.greedy[0].cpu()
    write_policy_csv(out / "policy.csv", greedy)
    if record.state is not None:
        config_plain = OmegaConf.to_container(cfg, resolve=True)
        torch.save({**record.state, "config": config_plain}, out / "checkpoint.pt")

    model, opt = scorers[0].model, scorers[0].optimal_metrics
    learned = scorers[0].metrics(greedy)
    rows: dict[str, Metrics] = {f"{name} (exact)": learned}
    errs: dict[str, dict[str, float]] = {}
    if int(cfg.eval.mc_episodes):
        env = DFRCEnv(scenarios[0], batch_size=[int(cfg.eval.mc_num_envs)], seed=int(cfg.seed) + 1)
        ev = evaluate(table_policy(greedy), env, episodes=int(cfg.eval.mc_episodes))
        label = f"{name} (Monte-Carlo, episodic)"
        rows[label], errs[label] = ev.metrics, ev.ci95
    rows["optimal (exact)"] = opt
    rows["round_robin (exact)"] = stationary_metrics(model, "round_robin")
    for label, m in comparisons.items():
        rows[f"{label} (exact)"] = m

    first99 = record.first_reaching(0.99)
    extra: dict[str, Any] = {
        "updates": record.updates,
        "env_steps_to_95": record.first_reaching(0.95),
        "env_steps_to_99": first99,
        "num_learners": num_learners,
        "learners": [_summary_row(r) for r in learners],
        "table": _table_dict(rows, errs),
        **record.info,
    }
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
        method=name,
        scenario=scenario,
        seed=int(cfg.seed),
        env_steps=record.env_steps,
        wall_seconds=record.wall_seconds,
        metrics=learned,
        optimal=opt,
        **extra,
    )
    write_summary(out / "summary.json", summary)

    _print_run(name, cfg, out, scenario, record, scenarios, scorers, points, learners, rows, errs)
    return summary


def _print_run(
    name: str,
    cfg: DictConfig,
    out: Path,
    scenario: str,
    record: RunRecord,
    scenarios: list[Params],
    scorers: list[ExactScorer],
    points: list[dict[str, Any]],
    learners: list[dict[str, Any]],
    rows: dict[str, Metrics],
    errs: dict[str, dict[str, float]],
) -> None:
    """The run's printout: the table (or one line per batched scenario), learners, files."""
    num_learners = int(cfg.get("num_learners", 1))
    print(
        f"\nscenario={scenario} method={name} seed={cfg.seed} learners={num_learners}"
        + (f" × {len(scenarios)} scenarios (batch_grid)" if len(scenarios) > 1 else "")
    )
    print(
        f"{record.env_steps} env steps per learner, {record.updates} updates in "
        f"{record.wall_seconds:.1f} s; exact evaluation every {cfg.eval.every_frames} env steps\n"
    )
    if len(scenarios) == 1:
        print(format_table(rows, errors=errs))
    else:
        print("scenario                        optimum avg reward  final ratio (median, min)")
        for g, point in enumerate(points):
            mine = [r["final_ratio"] for r in learners if record.group[r["learner"]] == g]
            label = " ".join(point_overrides(point))
            print(
                f"{label:<32}{scorers[g].optimal_metrics.avg_reward:>18.4f}  "
                f"{statistics.median(mine):.4f}, {min(mine):.4f}"
            )
    if record.num_learners > 1:
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
    for key, value in record.info.items():
        print(f"{key.replace('_', ' ')}: {value}")
    files = ["summary.json", "policy.csv", "metrics.csv", "learners.csv", "episode_rewards.csv"]
    if record.state is not None:
        files += ["config.yaml", "checkpoint.pt"]
    print(f"\nwrote {', '.join(files)} to {out}")


def learner_rows(
    record: RunRecord,
    scorers: list[ExactScorer],
    points: list[dict[str, Any]],
    num_learners: int,
) -> list[dict[str, Any]]:
    """``learners.csv``: one row per learner — its scenario point, ``learner`` (the index used in
    ``metrics.csv`` and ``episode_rewards.csv``), ``replicate`` (its index within its scenario),
    final ratio, steps to 95 / 99 % and final exact metrics."""
    rows = []
    for n in range(record.num_learners):
        g = record.group[n]
        final = scorers[g].metrics(record.greedy[n].cpu())
        curve = record.curve(n)
        rows.append(
            {
                **points[g],
                "learner": n,
                "replicate": n % num_learners,
                "final_ratio": curve[-1]["optimality_ratio"],
                "env_steps_to_95": record.first_reaching(0.95, n),
                "env_steps_to_99": record.first_reaching(0.99, n),
                **{k: clean_number(v) for k, v in final.as_dict().items()},
            }
        )
    return rows


def _summary_row(row: dict[str, Any]) -> dict[str, Any]:
    keys = ("learner", "replicate", "final_ratio", "env_steps_to_95", "env_steps_to_99")
    return {k: row[k] for k in keys} | {k: v for k, v in row.items() if is_scenario_key(k)}


def _table_dict(
    rows: dict[str, Metrics], errs: dict[str, dict[str, float]]
) -> dict[str, dict[str, Any]]:
    """The printed table as JSON: row → metrics (and ``ci95`` where the row has intervals)."""
    out = {}
    for label, m in rows.items():
        entry: dict[str, Any] = {k: clean_number(v) for k, v in m.as_dict().items()}
        if label in errs:
            entry["ci95"] = {k: clean_number(v) for k, v in errs[label].items()}
        out[label] = entry
    return out


def scenario_as_overrides(params: Params) -> list[str]:
    """Every model value of ``params`` as a dotted override (``env.p1.speed=0.1``, ``reward.r4=5``)."""

    def flat(prefix: str, node: Any) -> list[str]:
        if isinstance(node, dict):
            return [o for k, v in node.items() for o in flat(f"{prefix}{k}.", v)]
        value = "true" if node is True else "false" if node is False else node
        return [f"{prefix[:-1]}={value}"]

    return flat("", params.to_dict())


def comparison_rows(cfg: DictConfig, params: Params) -> dict[str, Metrics]:
    """Opt-in comparisons of the final table (``compare.qlearning_paper``): another method run
    through its own run function on the same scenario and seed, cached under ``cache_dir``."""
    compare = cfg.get("compare") or {}
    if not compare.get("qlearning_paper"):
        return {}
    overrides = [
        "algo=qlearning_paper",
        f"seed={int(cfg.seed)}",
        "eval.mc_episodes=0",
        "logger=none",
        f"progress={'true' if cfg.progress else 'false'}",
        f"optimum_gamma={float(cfg.optimum_gamma)}",
        *scenario_as_overrides(params),
    ]
    qcfg = compose("qlearning", overrides)
    key = json.dumps(OmegaConf.to_container(qcfg, resolve=True), sort_keys=True)
    cache = Path(str(cfg.cache_dir)).expanduser() / (
        "qlearning_paper-" + hashlib.sha256(key.encode()).hexdigest()[:16]
    )
    summary_path = cache / "summary.json"
    if not summary_path.is_file():
        print("\ncomparison: training Q-learning's paper profile (cached for next time)")
        run_learner(qlearning.NAME, qcfg, cache, scenario="comparison")
    metrics = json.loads(summary_path.read_text())["metrics"]
    return {"qlearning_paper": Metrics.from_dict(metrics)}


RUNNERS = {"solve": run_solve, "qlearning": run_qlearning, "dqn": run_dqn}
"""Method name → run function (what a sweep calls per grid point)."""
