"""The fleet's runs (MODEL.md § C): ``run_fleet`` trains one multi-agent learner and finishes it like
every run; ``run_solve_fleet`` prints the centralised optimum and what cooperation is worth.

Where the exact fleet model reaches (N = 2 on the paper's sizes) every policy is scored exactly
against the centralised optimum; beyond it by Monte-Carlo (``irdrc.fleet.evaluate``) against the
best of the baselines.
"""

from __future__ import annotations

import logging
import math
import signal
import time
import warnings
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from irdrc.agents import fleet_learners
from irdrc.agents.base import Hooks, RunRecord
from irdrc.agents.fleet_dqn import FleetScorer
from irdrc.experiments.config import scenario_name
from irdrc.experiments.finish import curve_file, plot_learning_curve
from irdrc.experiments.guard import RunInterrupted, stop_on_signals
from irdrc.experiments.progress import RunProgress
from irdrc.experiments.results import (
    atomic_write_text,
    clean_number,
    summary_dict,
    write_rows_csv,
    write_summary,
)
from irdrc.experiments.tracking import log_scalars, make_logger
from irdrc.fleet.config import fleet_from_config
from irdrc.fleet.evaluate import FleetMCScorer, baseline_rules
from irdrc.fleet.exact import (
    PRINTED,
    FleetModel,
    FleetSpec,
    baselines,
    fleet_metrics,
    joint_policy,
    single_optima,
    value_iteration_fleet,
)


def differences(spec: FleetSpec) -> dict[str, list[Any]]:
    """The model keys whose values differ between the vehicles, each with every vehicle's value."""

    def flat(prefix: str, node: Any) -> dict[str, Any]:
        if isinstance(node, dict):
            return {
                k: v for key, sub in node.items() for k, v in flat(f"{prefix}{key}.", sub).items()
            }
        return {prefix[:-1]: node}

    per = [flat("", p.to_dict()) for p in spec.vehicle_params]
    return {k: [d.get(k) for d in per] for k in per[0] if len({repr(d.get(k)) for d in per}) > 1}


def describe(spec: FleetSpec, observe: str, model: FleetModel) -> str:
    """One line naming the fleet."""
    reach = "exact" if model.exact else "beyond the exact model: Monte-Carlo"
    differ = differences(spec)
    alike = (
        "vehicles alike"
        if not differ
        else "vehicles differ in " + ", ".join(f"{k}={v}" for k, v in differ.items())
    )
    return (
        f"fleet: {spec.vehicles} vehicles ({alike}), {spec.channels} channel(s), {spec.access} "
        f"access, share {spec.share:g}, observe {observe}; {model.num_states:,} joint states "
        f"({reach})"
    )


def format_rows(rows: dict[str, list[dict]], reference: float) -> str:
    """The per-vehicle table: one line per vehicle and one for the fleet with its ratio to
    ``reference``."""
    head = f"{'policy':<34} {'vehicle':>7} " + " ".join(f"{c:>14}" for c in PRINTED)
    lines = [head, "-" * len(head)]
    for name, per in rows.items():
        for row in per:
            cells = " ".join(f"{row.get(c, math.nan):>14.4f}" for c in PRINTED)
            label = name if row["vehicle"] == 1 else ""
            lines.append(f"{label:<34} {row['vehicle']!s:>7} {cells}")
        lines.append(
            f"{'':<34} {'':>7} fleet reward / reference: {per[-1]['avg_reward'] / reference:.4f}"
        )
    return "\n".join(lines)


def _clean(rows: list[dict]) -> list[dict]:
    return [
        {k: (clean_number(v) if isinstance(v, float) else v) for k, v in r.items()} for r in rows
    ]


def exact_rows(model: FleetModel, policies: dict[str, Any]) -> dict[str, list[dict]]:
    """Each policy's exact per-vehicle and fleet metrics."""
    return {name: fleet_metrics(model, pol)[1] for name, pol in policies.items()}


def reference_policies(model: FleetModel, single_optimum: torch.Tensor) -> dict[str, Any]:
    """The baselines of MODEL.md § C and radar always, as exact joint policies."""
    S = model.num_states
    return {
        **baselines(model, single_optimum),
        "always radar": torch.full((S,), 2**model.N - 1, dtype=torch.int64),
    }


def run_solve_fleet(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """``recipes/solve.py env=fleet``: the fleet's centralised optimum (value iteration over the
    joint state and the 2^N joint actions), exact per-vehicle and fleet metrics beside the
    baselines, and what cooperation is worth: the optimum against N independent single-vehicle
    optima. Writes summary.json and policy.csv (joint state → joint action)."""
    torch.set_num_threads(1)
    spec, observe = fleet_from_config(cfg)
    model = FleetModel(spec)
    model.check_exact()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    t0 = time.perf_counter()
    sol = value_iteration_fleet(
        model, gamma=float(cfg.optimum_gamma), tol=float(cfg.tol), max_iter=int(cfg.max_iter)
    )
    single = single_optima(model, gamma=float(cfg.optimum_gamma))
    wall = time.perf_counter() - t0
    print(describe(spec, observe, model))
    print(
        f"value iteration over {2**model.N} joint actions: {sol.iterations} sweeps, {wall:.1f} s\n"
    )
    rows = exact_rows(
        model, {"centralised optimum": sol.policy, **reference_policies(model, single)}
    )
    optimum = rows["centralised optimum"][-1]["avg_reward"]
    print(format_rows(rows, optimum))
    copies = rows["N copies of the single optimum"][-1]["avg_reward"]
    worth = optimum - copies
    print(
        f"\ncooperation is worth {worth:+.4f} per fleet step: the centralised optimum "
        f"{optimum:.4f} against {spec.vehicles} independent single-vehicle optima {copies:.4f} "
        f"({copies / optimum:.4f} of the optimum)"
    )
    summary = summary_dict(
        method="optimal",
        scenario=scenario,
        seed=int(cfg.seed),
        env_steps=0,
        wall_seconds=wall,
        metrics=fleet_metrics(model, sol.policy)[0],
        optimal=fleet_metrics(model, sol.policy)[0],
        fleet=_fleet_info(spec, observe, model),
        sweeps=sol.iterations,
        table={name: _clean(per) for name, per in rows.items()},
        cooperation={
            "optimum": optimum,
            "independent_optima": copies,
            "worth": worth,
            "independent_over_optimum": copies / optimum if optimum else None,
        },
    )
    write_summary(out / "summary.json", summary)
    if model.N <= 4:
        write_joint_policy_csv(out / "policy.csv", model, sol.policy)
    print(f"\nwrote {out / 'summary.json'} and {out / 'policy.csv'}")
    return summary


def _fleet_info(spec: FleetSpec, observe: str, model: FleetModel) -> dict[str, Any]:
    return {
        "vehicles": spec.vehicles,
        "channels": spec.channels,
        "access": spec.access,
        "share": spec.share,
        "observe": observe,
        "joint_states": model.num_states,
        "exact": model.exact,
        "per_vehicle": differences(spec),
    }


def write_joint_policy_csv(
    path: Path, model: FleetModel, policy: torch.Tensor, optimal: torch.Tensor | None = None
) -> None:
    """``policy.csv`` of a fleet: one row per joint state — r, w, each vehicle's d, c, v, m, each
    vehicle's action (0 comm, 1 radar) and, with ``optimal``, the centralised optimum's."""
    from irdrc.core.env import decode_state

    states = model.vehicle_states()  # [S, N]
    cols = decode_state(states.reshape(-1), model.spec.vehicle.env.levels)
    cols = cols.reshape(states.shape[0], model.N, -1)
    own = [0, 1, *range(4, cols.shape[-1])]
    names = ["d", "c", "v", "m", "phase"][: len(own)]
    header = ["r", "w"] + [f"{n}{i + 1}" for i in range(model.N) for n in names]
    header += [f"action{i + 1}" for i in range(model.N)]
    blocks = [cols[:, 0, 2:4]] + [cols[:, i, own] for i in range(model.N)]
    bits = (policy.long()[:, None] >> torch.arange(model.N)) & 1
    blocks.append(bits)
    if optimal is not None:
        header += [f"optimal{i + 1}" for i in range(model.N)]
        blocks.append((optimal.long()[:, None] >> torch.arange(model.N)) & 1)
    table = torch.cat(blocks, 1).tolist()
    lines = [",".join(header)] + [",".join(map(str, row)) for row in table]
    atomic_write_text(Path(path), "\n".join(lines) + "\n")


def run_fleet(cfg: DictConfig, out: Path, scenario: str | None = None) -> dict[str, Any]:
    """Train ``cfg.learner`` on the fleet, then write metrics.csv, summary.json (per-vehicle and
    fleet metrics of the learner beside the optimum and the baselines), policy.csv (N = 2 and
    wherever the exact model reaches: joint state → joint action) and the learning curve."""
    torch.set_num_threads(int(cfg.get("num_threads", 1)))
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message="total_frames .* is not exactly divisible")
    spec, observe = fleet_from_config(cfg)
    learner = str(cfg.learner)
    config = fleet_learners.config(learner, cfg.algo, cfg.network)
    model = FleetModel(spec)
    fleet_learners.check(learner, model, observe)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario or scenario_name(cfg)
    atomic_write_text(out / "config.yaml", OmegaConf.to_yaml(cfg))
    print(describe(spec, observe, model), flush=True)
    gamma = float(cfg.optimum_gamma)
    single = single_optima(model, gamma=gamma)
    mc = {
        "fleets": int(cfg.eval.mc_fleets),
        "steps": int(cfg.eval.mc_steps),
        "burn_in": int(cfg.eval.mc_burn_in),
        "seed": int(cfg.seed) + 1,
    }
    t0 = time.perf_counter()
    if model.exact:
        scorer: Any = FleetScorer(model, gamma=gamma)
        reference = "centralised optimum (exact)"
    else:
        scorer = FleetMCScorer(model, single, **mc)
        reference = f"best baseline: {scorer.reference} (Monte-Carlo)"
    print(
        f"reference: {reference}, {scorer.optimal_metrics.avg_reward:.4f} per fleet step "
        f"({time.perf_counter() - t0:.1f} s)",
        flush=True,
    )
    logger = make_logger(
        cfg.logger.backend,
        f"{scenario}__fleet_{learner}__{cfg.seed}",
        out / "logs",
        project=cfg.logger.project,
        mode=cfg.logger.mode,
        config=OmegaConf.to_container(cfg, resolve=True),
    )
    progress = RunProgress(config.total_frames, bool(cfg.progress), logger, learner)
    with stop_on_signals() as stop:
        hooks = Hooks(
            on_eval=progress.on_eval,
            on_batch=progress.on_batch,
            on_start=progress.on_start,
            should_stop=stop,
        )
        record = fleet_learners.train(
            learner,
            model,
            config,
            observe=observe,
            seed=int(cfg.seed),
            scorer=scorer,
            eval_every_frames=int(cfg.eval.every_frames),
            hooks=hooks,
        )
        progress.close()
    summary = finish_fleet(cfg, out, scenario, learner, model, observe, record, scorer, single, mc)
    log_scalars(logger, {"final/optimality_ratio": summary["optimality_ratio"]}, record.env_steps)
    if record.interrupted:
        signum = stop.signal or signal.SIGINT
        raise RunInterrupted(
            f"stopped by {signal.Signals(signum).name} at {record.env_steps} fleet steps; the "
            f"files so far are in {out}; fleet runs do not resume: start again",
            code=128 + int(signum),
        )
    return summary


def finish_fleet(
    cfg: DictConfig,
    out: Path,
    scenario: str,
    learner: str,
    model: FleetModel,
    observe: str,
    record: RunRecord,
    scorer: Any,
    single: torch.Tensor,
    mc: dict[str, int],
) -> dict[str, Any]:
    """Write a fleet run's files, print its table, return its summary."""
    greedy = record.greedy[0].cpu()
    write_rows_csv(out / "metrics.csv", record.history)
    plot_learning_curve(record, out / curve_file(cfg), title=f"{learner} on {scenario}")
    errors: dict[str, float] = {}
    if model.exact:
        joint = joint_policy(model, greedy)
        optimum = scorer.fleet_optimum.policy
        rows = exact_rows(
            model,
            {
                f"{learner} (exact)": joint,
                "centralised optimum": optimum,
                **reference_policies(model, single),
            },
        )
        write_joint_policy_csv(out / "policy.csv", model, joint, optimum)
        learned = fleet_metrics(model, joint)[0]
        extra: dict[str, Any] = {
            "joint_states_differing_from_optimum": int((joint != optimum).sum()),
        }
    else:
        measured = {f"{learner} (Monte-Carlo)": scorer.measure(greedy)}
        rules = baseline_rules(model, single)
        for name in rules:
            measured[f"{name} (Monte-Carlo)"] = scorer.baselines[name]
        rows = {name: m.per_vehicle for name, m in measured.items()}
        errors = {name: m.ci95 for name, m in measured.items()}
        learned = measured[f"{learner} (Monte-Carlo)"].fleet
        extra = {"monte_carlo": {**mc, "ci95": errors}}
        write_rows_csv(out / "policy.csv", _table_rows(model, greedy))
    ref = scorer.optimal_metrics.avg_reward
    print(f"\n{learner}: {record.env_steps} fleet steps, {record.wall_seconds:.0f} s\n")
    print(format_rows(rows, ref))
    if errors:
        print(
            "\nMonte-Carlo 95 % half-widths of the fleet reward: "
            + ", ".join(f"{k} ± {v:.4f}" for k, v in errors.items())
        )
    summary = summary_dict(
        method=learner,
        scenario=scenario,
        seed=int(cfg.seed),
        env_steps=record.env_steps,
        wall_seconds=record.wall_seconds,
        metrics=learned,
        optimal=scorer.optimal_metrics,
        reference="centralised optimum (exact)" if model.exact else "best baseline (Monte-Carlo)",
        fleet=_fleet_info(model.spec, observe, model),
        vehicle_steps=record.env_steps * model.N,
        updates=record.updates,
        env_steps_to_95=record.first_reaching(0.95),
        env_steps_to_99=record.first_reaching(0.99),
        interrupted=record.interrupted,
        per_vehicle=_clean(rows[next(iter(rows))]),
        table={name: _clean(per) for name, per in rows.items()},
        **extra,
        **record.info,
    )
    write_summary(out / "summary.json", summary)
    print(f"\nwrote {out / 'summary.json'}, {out / 'metrics.csv'}, {out / 'policy.csv'}")
    return summary


def _table_rows(model: FleetModel, greedy: torch.Tensor) -> list[dict[str, int]]:
    """Each vehicle's action in every single-vehicle state (policy.csv beyond the exact model)."""
    from irdrc.core.env import decode_state

    S = model.single.num_states
    per = greedy.long().reshape(-1, S)
    cols = decode_state(torch.arange(S), model.spec.vehicle.env.levels).tolist()
    names = ("d", "c", "r", "w", "v", "m", "phase")
    rows = []
    for s in range(S):
        row = dict(zip(names, cols[s], strict=False))
        for i in range(per.shape[0]):
            row[f"action{i + 1}" if per.shape[0] > 1 else "action"] = int(per[i, s])
        rows.append(row)
    return rows
