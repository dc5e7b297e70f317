"""The runs behind the recipes: one function per method, shared by single-run recipes and sweeps.

Each ``run_*`` takes a composed config (the recipe's Hydra config, or the same composed by a sweep
for one grid point) and an output directory, writes the run's files there, prints its table, and
returns the ``summary.json`` record. Every learner finishes the same way (``finish_run``):
``metrics.csv`` (one schema: ``irdrc.agents.base.progress_fields``), ``episode_rewards.csv``,
``learners.csv``, ``policy.csv``, ``summary.json`` (every row of the printed table), and
``checkpoint.pt`` for learners that checkpoint.
"""

from __future__ import annotations

import hashlib
import json
import logging
import signal
import time
import warnings
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from irdrc.agents import dqn, qlearning
from irdrc.agents.base import Hooks
from irdrc.agents.registry import LEARNERS
from irdrc.core.env import DFRCEnv
from irdrc.core.evaluate import evaluate
from irdrc.core.metrics import Metrics, format_table
from irdrc.core.model import DENSE_MODEL_LIMIT_BYTES, build_model
from irdrc.core.params import Params
from irdrc.core.policies import table_policy
from irdrc.core.solve import ExactScorer, episodic_metrics, stationary_metrics, value_iteration
from irdrc.experiments.config import compose, scenario_name
from irdrc.experiments.constrained import run_constrained
from irdrc.experiments.finish import degenerate_note, end_warning, finish_run, table_dict
from irdrc.experiments.grid import is_scenario_key, parse_grid
from irdrc.experiments.guard import (
    RunInterrupted,
    explicit_keys,
    load_resume,
    save_checkpoint,
    stop_on_signals,
)
from irdrc.experiments.progress import RunProgress
from irdrc.experiments.results import (
    atomic_write_text,
    policy_table,
    read_policy_csv,
    summary_dict,
    write_policy_csv,
    write_summary,
)
from irdrc.experiments.tracking import log_scalars, make_logger, resolve_wandb_mode
from irdrc.fleet.config import is_fleet

"""Method name → learner module (``Config``, ``train``; see ``irdrc.agents.base``)."""


def run_solve(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """Solve, print the policy and the comparison table, write summary.json and policy.csv
    (above the dense model's size, on the factored operator: ``run_solve_factored``)."""
    torch.set_num_threads(1)
    if is_fleet(cfg):
        from irdrc.experiments.fleet import run_solve_fleet

        return run_solve_fleet(cfg, out, scenario)
    params = Params.from_config(cfg)
    if 16 * params.env.num_states**2 > DENSE_MODEL_LIMIT_BYTES:
        return run_solve_factored(cfg, out, scenario)
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
    if note := degenerate_note(opt):
        print(note)

    summary = summary_dict(
        method="optimal",
        scenario=scenario,
        seed=cfg.seed,
        env_steps=0,
        wall_seconds=wall,
        metrics=opt,
        optimal=opt,
        episodic=rows["optimal (episodic)"].as_dict(),
        table=table_dict(rows, errs),
    )
    write_summary(out / "summary.json", summary)
    write_policy_csv(out / "policy.csv", sol.policy, model.params.env.levels)
    print(f"\nwrote {out / 'summary.json'} and {out / 'policy.csv'}")
    return summary


def run_solve_factored(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """``run_solve`` for models too large for S × S matrices: value iteration (McQueen's bounds,
    ``tol``) and exact long-run metrics on the factored operator (``irdrc.core.factored``), beside
    always-comm, always-radar and random; no episodic metrics or Monte-Carlo check."""
    from irdrc.core.factored import (
        build_factored,
        stationary_metrics_factored,
        value_iteration_factored,
    )

    params = Params.from_config(cfg)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    gamma = float(cfg.optimum_gamma)
    t0 = time.perf_counter()
    model = build_factored(params)
    sol = value_iteration_factored(model, gamma=gamma, tol=float(cfg.tol), max_iter=cfg.max_iter)
    opt = stationary_metrics_factored(model, sol.policy)
    wall = time.perf_counter() - t0
    S = model.num_states
    print(
        f"scenario={scenario}: S = {S} states, factored value iteration, γ={gamma}, "
        f"{sol.iterations} sweeps (values within {sol.bound:.1e} of the optimum), exact "
        f"stationary metrics, {wall:.2f} s"
    )
    print(f"optimal policy ({int(sol.policy.sum())} of {S} states in radar mode):\n")
    print(policy_table(model, sol.policy))
    rows = {"optimal (stationary)": opt}
    for name, p_radar in (("always_comm", 0.0), ("always_radar", 1.0), ("random", 0.5)):
        table = torch.full((S, 2), 1.0 - p_radar, dtype=torch.float64)
        table[:, 1] = p_radar
        rows[f"{name} (stationary)"] = stationary_metrics_factored(model, table)
    print("\nexact long-run metrics (factored operator; no episodic metrics at this size):\n")
    print(format_table(rows))
    summary = summary_dict(
        method="optimal",
        scenario=scenario,
        seed=cfg.seed,
        env_steps=0,
        wall_seconds=wall,
        metrics=opt,
        optimal=opt,
        num_states=S,
        solver="factored",
        sweeps=sol.iterations,
        value_bound=sol.bound,
        table=table_dict(rows, {}),
    )
    write_summary(out / "summary.json", summary)
    write_policy_csv(out / "policy.csv", sol.policy, model.params.env.levels)
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


def run_learner(
    method: str, cfg: DictConfig, out: Path, scenario: str | None = None
) -> dict[str, Any]:
    """Train ``method`` on the composed config ``cfg`` and finish the run in ``out``.

    SIGINT / SIGTERM stop the learner after its current batch; the files so far (and, for learners
    that checkpoint, ``checkpoint.pt``) are written and ``RunInterrupted`` says how to go on.
    """
    agent = LEARNERS[method]
    # a resumed run goes on with the checkpoint's configuration (what the command line set aside)
    resume, cfg = load_resume(cfg, explicit_keys())  # before anything is written
    torch.set_num_threads(int(cfg.get("num_threads", 1)))
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its storage line would cut the bar
    # the run's own record counts the extra frames of a last partial batch
    warnings.filterwarnings("ignore", message="total_frames .* is not exactly divisible")
    config = agent.Config.from_node(cfg)
    base = Params.from_config(cfg)
    _check_eval(cfg)
    num_learners = int(cfg.get("num_learners", 1))
    points = batch_points(cfg)
    scenarios = [base.with_overrides(p) for p in points]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = (resume or {}).get("scenario") or scenario or scenario_name(cfg)
    name = str(cfg.algo.get("name", method))
    atomic_write_text(out / "config.yaml", OmegaConf.to_yaml(cfg))
    logger = make_logger(
        cfg.logger.backend,
        f"{scenario}__{name}__{cfg.seed}",
        out / "logs",
        project=cfg.logger.project,
        mode=cfg.logger.mode,
        config=OmegaConf.to_container(cfg, resolve=True),
    )
    if resume is not None:
        print(
            f"resumed from {Path(str(cfg.resume)).expanduser()} at {resume['frames']} env steps; "
            f"training to {cfg.algo.total_frames}, files in {out}",
            flush=True,
        )
    scorers = [ExactScorer(build_model(p), gamma=float(cfg.optimum_gamma)) for p in scenarios]
    progress = RunProgress(config.env_steps(base.env.horizon), bool(cfg.progress), logger, name)
    config_plain = OmegaConf.to_container(cfg, resolve=True)
    with stop_on_signals() as stop:
        hooks = Hooks(
            on_eval=progress.on_eval,
            on_batch=progress.on_batch,
            on_start=progress.on_start,
            on_checkpoint=lambda state: save_checkpoint(
                out, {**state, "scenario": scenario}, config_plain
            ),
            checkpoint_every_frames=int(cfg.get("checkpoint", {}).get("every_frames", 0) or 0),
            should_stop=stop,
        )
        record = agent.train(
            scenarios,
            config,
            num_learners=num_learners,
            seed=int(cfg.seed),
            device=cfg.device,
            scorers=scorers,
            eval_every_frames=int(cfg.eval.every_frames),
            hooks=hooks,
            resume=resume,
        )
        progress.close()
        comparisons = {} if record.interrupted else comparison_rows(cfg, base)
        summary = finish_run(
            name, cfg, out, scenario, record, scenarios, scorers, points, num_learners, comparisons
        )
    if not record.interrupted and (warning := end_warning(record.history)):
        print(warning, flush=True)
    log_scalars(logger, {"final/optimality_ratio": summary["optimality_ratio"]}, record.env_steps)
    if logger is not None and cfg.logger.backend == "wandb":
        sync_dir = Path(logger.experiment.dir).parent
        logger.experiment.finish()
        if resolve_wandb_mode(cfg.logger.mode) == "offline":
            print(f"W&B: offline run in {sync_dir}; upload it with: wandb sync {sync_dir}")
    if record.interrupted:
        signum = stop.signal or signal.SIGINT
        how = (
            f"go on with: python recipes/{method}.py resume={out / 'checkpoint.pt'} "
            "(it goes on in the same directory with the same configuration)"
            if record.state is not None
            else f"{method} runs do not resume: start again"
        )
        raise RunInterrupted(
            f"stopped by {signal.Signals(signum).name} at {record.env_steps} env steps; the files "
            f"so far are in {out}; {how}",
            code=128 + int(signum),
        )
    return summary


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
    # Only the cached policy is trusted, and its metrics are recomputed exactly: an edited or
    # truncated cache entry cannot print a wrong number.
    model = build_model(params)
    try:
        table = read_policy_csv(cache / "policy.csv", model.num_states)
    except ValueError as err:
        if (cache / "policy.csv").exists():
            print(f"comparison: ignoring the cache entry ({err})")
        print("\ncomparison: training Q-learning's paper profile (cached for next time)")
        run_learner(qlearning.NAME, qcfg, cache, scenario="comparison")
        table = read_policy_csv(cache / "policy.csv", model.num_states)
    return {"qlearning_paper": stationary_metrics(model, table)}


def run_fleet(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """A multi-agent learner on a fleet (``irdrc.experiments.fleet.run_fleet``)."""
    from irdrc.experiments.fleet import run_fleet as run

    return run(cfg, out, scenario)


RUNNERS = {
    "solve": run_solve,
    "fleet": run_fleet,
    "qlearning": run_qlearning,
    "dqn": run_dqn,
    "constrained": run_constrained,
}
"""Method name → run function (what a sweep calls per grid point)."""
