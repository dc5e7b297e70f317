"""The constrained design run (``recipes/constrained.py``): the most data subject to a miss-detection
target, solved exactly by the LP of ``irdrc.core.cmdp``, beside the reward-optimal policy; with
``learner=dqn_lagrangian``, also learned (``irdrc.agents.lagrangian``) and scored exactly against
the LP."""

from __future__ import annotations

import logging
import signal
import time
import warnings
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from irdrc.agents import lagrangian
from irdrc.agents.base import Hooks, progress_fields
from irdrc.core.cmdp import CMDPSolution, solve_cmdp
from irdrc.core.metrics import format_table
from irdrc.core.model import build_model
from irdrc.core.params import Params, to_plain
from irdrc.core.solve import ExactScorer, stationary_metrics, value_iteration
from irdrc.experiments.config import scenario_name
from irdrc.experiments.finish import table_dict
from irdrc.experiments.guard import RunInterrupted, stop_on_signals
from irdrc.experiments.progress import RunProgress
from irdrc.experiments.results import (
    atomic_write_text,
    state_label,
    summary_dict,
    write_policy_csv,
    write_rows_csv,
    write_summary,
)
from irdrc.experiments.tracking import log_scalars, make_logger

LEARNERS = ("lp", "dqn_lagrangian")
"""``learner``: ``lp`` solves exactly; ``dqn_lagrangian`` also learns and is scored against it."""
MU_FIELDS = ("env_steps", "mu", "measured_miss")
"""Columns of ``mu.csv``: the multiplier and the learner's measured miss detection over training."""


def objective_ratio(entries: list[dict[str, Any]], sol: CMDPSolution) -> list[dict[str, Any]]:
    """Evaluations read against the LP: each entry's ``optimality_ratio`` becomes its objective
    over the LP optimum's (the entries are the learner's history, so it keeps these)."""
    for e in entries:
        e["optimality_ratio"] = e[sol.objective] / sol.value if sol.value else float("nan")
    return entries


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


def describe_randomised(sol: CMDPSolution, levels=None) -> list[str]:
    """One line per randomised state: its factors and P(radar) (``levels`` as in
    ``Params.env.levels``; None: v1)."""
    lines = []
    for s in sol.randomised:
        lines.append(
            f"  {state_label(s, levels)}: radar with probability "
            f"{float(sol.p_radar[s]):.4f} (this state is {float(sol.occupancy[:, s].sum()):.4f} "
            "of the time)"
        )
    return lines


def lp_exact_model(params: Params):
    """The exact model the LP runs on: dense while its transition tensor fits
    ``DENSE_MODEL_LIMIT_BYTES`` (the limit ``recipes/solve.py`` switches at), else the factored one
    (its transitions reach the LP as sparse matrices built from the factors)."""
    from irdrc.core.factored import build_factored
    from irdrc.core.model import DENSE_MODEL_LIMIT_BYTES

    if 16 * params.env.num_states**2 <= DENSE_MODEL_LIMIT_BYTES:
        return build_model(params)
    return build_factored(params)


def _reward_optimal(model, gamma: float):
    """Exact stationary metrics of the reward-optimal policy, on either kind of model."""
    from irdrc.core.factored import (
        FactoredModel,
        stationary_metrics_factored,
        value_iteration_factored,
    )

    if isinstance(model, FactoredModel):
        sol = value_iteration_factored(model, gamma=gamma)
        return stationary_metrics_factored(model, sol.policy)
    return stationary_metrics(model, value_iteration(model, gamma=gamma).policy)


def run_constrained(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """Solve the constrained problem exactly; print it beside the reward-optimal policy; write
    ``summary.json`` (the LP optimum's exact metrics under ``optimal`` and ``metrics``) and
    ``policy.csv`` (with ``p_radar``)."""
    if str(cfg.get("learner", "lp")) == "dqn_lagrangian":
        return run_constrained_learned(cfg, out, scenario)
    torch.set_num_threads(1)
    params = Params.from_config(cfg)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    kwargs = constraint_kwargs(cfg)
    t0 = time.perf_counter()
    model = lp_exact_model(params)
    sol = solve_cmdp(model, **kwargs)
    wall = time.perf_counter() - t0
    reward_opt = _reward_optimal(model, float(cfg.optimum_gamma))
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
    for line in describe_randomised(sol, model.params.env.levels):
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
    write_policy_csv(out / "policy.csv", sol.policy, model.params.env.levels)
    print(f"\nwrote {out / 'summary.json'} and {out / 'policy.csv'}")
    return summary


def run_constrained_learned(
    cfg: DictConfig, out: Path, scenario: str | None = None
) -> dict[str, Any]:
    """Train the Lagrangian DQN (``learner=dqn_lagrangian``) and score its final policy exactly
    against the LP optimum: ``summary.json`` (the learned policy's exact metrics under ``metrics``,
    the LP's under ``optimal``, training and measurement env steps, μ), ``policy.csv`` (with
    ``p_radar``), ``metrics.csv`` (exact evaluations of the greedy table at the current μ; its
    ``optimality_ratio`` is the objective over the LP optimum's) and ``mu.csv`` (μ and the measured
    miss detection over training)."""
    torch.set_num_threads(int(cfg.get("num_threads", 1)))
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message="total_frames .* is not exactly divisible")
    warnings.filterwarnings("ignore", message="The name .* wasn't part of the annotations")
    params = Params.from_config(cfg)
    config = lagrangian.LagrangianConfig.from_node(cfg)
    kwargs = constraint_kwargs(cfg)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    atomic_write_text(out / "config.yaml", OmegaConf.to_yaml(cfg))
    model = build_model(params)
    t0 = time.perf_counter()
    sol = solve_cmdp(model, **kwargs)
    print(
        f"scenario={scenario}: the exact constrained optimum (LP, {time.perf_counter() - t0:.2f} s): "
        f"{sol.objective} {sol.value:.6g}, miss detection {sol.metrics.miss_detection:.4f}"
    )
    logger = make_logger(
        cfg.logger.backend,
        f"{scenario}__{config.name}__{cfg.seed}",
        out / "logs",
        project=cfg.logger.project,
        mode=cfg.logger.mode,
        config=OmegaConf.to_container(cfg, resolve=True),
    )
    scorer = ExactScorer(model, gamma=float(cfg.optimum_gamma))
    progress = RunProgress(config.dqn.total_frames, bool(cfg.progress), logger, config.name)
    with stop_on_signals() as stop:
        record = lagrangian.train(
            params,
            config,
            seed=int(cfg.seed),
            device=cfg.device,
            scorers=scorer,
            eval_every_frames=int(cfg.eval.every_frames),
            hooks=Hooks(
                on_eval=lambda entries: progress.on_eval(objective_ratio(entries, sol)),
                on_batch=progress.on_batch,
                on_start=progress.on_start,
                should_stop=stop,
            ),
        )
        progress.close()
    mu_trace = record.info.pop("mu_trace")
    write_rows_csv(out / "metrics.csv", record.history, progress_fields(record.history))
    write_rows_csv(out / "mu.csv", mu_trace, MU_FIELDS)
    if record.interrupted:
        signum = stop.signal or signal.SIGINT
        raise RunInterrupted(
            f"stopped by {signal.Signals(signum).name} at {record.env_steps} env steps; the files "
            f"so far are in {out}; {config.name} runs do not resume: start again",
            code=128 + int(signum),
        )
    learned = stationary_metrics(model, record.policy[0])
    reward_opt = stationary_metrics(
        model, value_iteration(model, gamma=float(cfg.optimum_gamma)).policy
    )
    rows = {
        f"{config.name} (exact)": learned,
        "constrained optimum (LP)": sol.metrics,
        "reward-optimal (value iteration)": reward_opt,
    }
    value = float(getattr(learned, sol.objective))
    ratio = value / sol.value if sol.value else float("nan")
    print("\nexact long-run metrics:\n")
    print(format_table(rows))
    print(
        f"\n{config.name}: {sol.objective} {value:.4f} = {ratio:.3f} of the LP optimum, miss "
        f"detection {learned.miss_detection:.4f} (target {kwargs['target_miss']:g}); "
        f"{record.training_env_steps} training + {record.measurement_env_steps} measurement = "
        f"{record.env_steps} env steps, {record.wall_seconds:.0f} s"
    )
    info = {k: v for k, v in record.info.items() if k != "replay_sampler"}
    summary = summary_dict(
        method=config.name,
        scenario=scenario,
        seed=int(cfg.seed),
        env_steps=record.env_steps,
        wall_seconds=record.wall_seconds,
        metrics=learned,
        optimal=sol.metrics,
        training_env_steps=record.training_env_steps,
        measurement_env_steps=record.measurement_env_steps,
        target_miss=float(kwargs["target_miss"]),
        objective=sol.objective,
        value=value,
        optimal_value=sol.value,
        objective_ratio=ratio,
        learner=info,
        reward_optimal=reward_opt.as_dict(),
        table=table_dict(rows, {}),
    )
    write_summary(out / "summary.json", summary)
    write_policy_csv(out / "policy.csv", record.policy[0], model.params.env.levels)
    log_scalars(
        logger,
        {"final/objective_ratio": ratio, "final/miss_detection": learned.miss_detection},
        record.env_steps,
    )
    if logger is not None and cfg.logger.backend == "wandb":
        logger.experiment.finish()
    print(f"\nwrote {out / 'summary.json'}, {out / 'policy.csv'}, {out / 'mu.csv'}")
    return summary
