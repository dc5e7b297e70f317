"""``recipes/fleet.py``: a multi-agent learner on a fleet of vehicles (MODEL.md § C), scored exactly
against the centralised optimum where the exact model reaches (N = 2 on the paper's sizes), by
Monte-Carlo against the best baseline beyond it; checkpoints, resumes and stops like every learner.

    python recipes/fleet.py                                      # VDN, 2 vehicles, own observations
    python recipes/fleet.py learner=joint env.observe=full       # one network over the joint actions
    python recipes/fleet.py learner=qmix env.share=1.0 env.channels=2
    python recipes/fleet.py learner=idqn env.vehicles=4          # beyond the exact model
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from irdrc.agents.configs import (
    FLEET_LEARNERS,
    POLICY_GRADIENT,
    FleetLearnerConfig,
    OffPolicyConfig,
    check_fleet_learner,
)
from irdrc.core.checks import INT, build, check_choice, check_numbers
from irdrc.runs.compose import Composed
from irdrc.runs.resume import refuse_finished
from irdrc.runs.sections import (
    A_FLEET,
    Learning,
    Plot,
    scenario_field,
)

if TYPE_CHECKING:
    from irdrc.agents.base import RunRecord
    from irdrc.fleet.model import FleetModel
    from irdrc.runs.scaffold import Run

NAME = "fleet"
ALGO_KEYS = OffPolicyConfig.keys()
"""The ``algo.*`` keys of DQN's machinery its learners read (a profile's file lists those that act)."""
SWEEP_DEFAULTS = ("progress=false", "logger=none")
"""What a sweep gives every trial of this recipe before its own overrides (which may change it)."""
RESUMABLE = True
UNIT = "fleet steps"


@dataclass(frozen=True)
class FleetEval:
    """``eval.*``: the evaluation period (fleet steps) and, beyond the exact model, the
    Monte-Carlo evaluation: ``mc_fleets`` fleets of ``mc_steps`` steps after ``mc_burn_in``."""

    every_frames: int = 50_000
    mc_fleets: int = 256
    mc_steps: int = 2_000
    mc_burn_in: int = 200

    def __post_init__(self) -> None:
        check_numbers(
            self,
            "eval.",
            (
                ("every_frames", 1, 10**12, INT),
                ("mc_fleets", 2, 10**6, INT),
                ("mc_steps", 1, 10**7, INT),
                ("mc_burn_in", 0, 10**7, INT),
            ),
        )


def _learner(data: Any, prefix: str) -> FleetLearnerConfig:
    return FleetLearnerConfig.from_sections(
        data.get("learner"), data["algo"], data["network"], data.get("ppo")
    )


@dataclass(frozen=True)
class Config(Learning):
    """The fleet recipe's keys (``irdrc/conf/fleet.yaml``)."""

    fleet: Any = scenario_field(A_FLEET)
    learner: FleetLearnerConfig = field(
        default_factory=FleetLearnerConfig,
        metadata={"keys": ("learner", "algo", "network", "ppo"), "build": _learner},
    )
    eval: FleetEval = field(default_factory=FleetEval)  # type: ignore[assignment]  # keys of its own
    plot: Plot = field(default_factory=Plot)

    def __post_init__(self) -> None:
        super().__post_init__()

    @property
    def total(self) -> int:
        """Fleet steps of the run."""
        return self.learner.machinery.total_frames


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked: values, the fleet, that the learner can serve it."""
    learner = composed.cfg.get("learner")
    check_choice("learner", learner, FLEET_LEARNERS)
    own, other = ("ppo", "algo") if learner in POLICY_GRADIENT else ("algo", "ppo")
    stray = sorted(k for k in composed.explicit if k.startswith(f"{other}."))
    if stray:
        raise ValueError(
            f"{stray[0]}: learner={learner} reads {own}.* ({'PPO' if own == 'ppo' else 'DQN'}'s "
            f"keys); {other}.* are for learner="
            + ("|".join(POLICY_GRADIENT) if other == "ppo" else "idqn|vdn|qmix|joint")
        )
    cfg = build(Config, composed.cfg)
    spec, observe = cfg.fleet

    def model() -> FleetModel:  # torch and the kernels: only for a learner on joint states
        from irdrc.fleet.model import FleetModel

        return FleetModel(spec)

    check_fleet_learner(cfg.learner.learner, model, observe)
    if cfg.eval.every_frames > cfg.total:
        raise ValueError(
            f"eval.every_frames={cfg.eval.every_frames} is more than the run's {cfg.total} "
            f"{UNIT}; use a smaller value"
        )
    if resume is not None:
        done = int(resume.get("env_steps", resume["frames"]))
        refuse_finished(cfg.resume, done, cfg.total, "algo.total_frames", cfg.total, unit=UNIT)
    return cfg


def recorded(config: Config, cfg: dict[str, Any]) -> dict[str, Any]:
    """The composed config ``cfg`` as the run records it: a value learner's ``algo.prioritized``
    and ``algo.double_dqn`` as it resolved them (null in ``fleet.yaml``: the learner's default)."""
    if config.learner.learner in POLICY_GRADIENT:
        return cfg
    dqn = config.learner.dqn
    return {
        **cfg,
        "algo": {**cfg["algo"], "prioritized": dqn.prioritized, "double_dqn": dqn.double_dqn},
    }


def run(cfg: Config, run: Run) -> dict[str, Any]:
    """Train the learner on the fleet, finish its run directory (``finish_fleet``)."""
    from irdrc.agents import marl
    from irdrc.core.exact import require_ratio
    from irdrc.fleet.evaluate import FleetMCScorer
    from irdrc.fleet.model import FleetModel
    from irdrc.fleet.policies import single_optima
    from irdrc.fleet.scorer import FleetScorer
    from irdrc.recipes.fleet.report import describe

    run.threads(cfg.num_threads)
    spec, observe = cfg.fleet
    model = FleetModel(spec)
    print(describe(spec, observe, model), flush=True)
    single = single_optima(model, gamma=cfg.optimum_gamma)
    t0 = time.perf_counter()
    if model.exact:
        scorer: Any = FleetScorer(model, gamma=cfg.optimum_gamma)
        reference = "centralised optimum (exact)"
    else:
        scorer = FleetMCScorer(model, single, **mc_keys(cfg))
        reference = f"best baseline: {scorer.reference} (Monte-Carlo)"
    require_ratio(scorer)
    print(
        f"reference: {reference}, {scorer.optimal_metrics.avg_reward:.4f} per fleet step "
        f"({time.perf_counter() - t0:.1f} s)",
        flush=True,
    )
    name = cfg.learner.learner
    logger = run.make_logger(cfg.logger, f"fleet_{name}")
    with run.training(cfg.total, name, checkpoint=cfg.checkpoint, unit=UNIT) as hooks:
        record = marl.train(
            model,
            cfg.learner,
            observe=observe,
            seed=cfg.seed,
            scorer=scorer,
            eval_every_frames=cfg.eval.every_frames,
            hooks=hooks,
            resume=run.resume_state,
        )
    summary = finish_fleet(cfg, run, model, observe, record, scorer, single)
    from irdrc.runs.tracking import log_scalars

    log_scalars(logger, {"final/optimality_ratio": summary["optimality_ratio"]}, record.env_steps)
    run.finish(summary, interrupted_at=record.env_steps if record.interrupted else None, unit=UNIT)
    return summary


def mc_keys(cfg: Config) -> dict[str, int]:
    """The Monte-Carlo evaluation's settings (beyond the exact model)."""
    e = cfg.eval
    return {
        "fleets": e.mc_fleets,
        "steps": e.mc_steps,
        "burn_in": e.mc_burn_in,
        "seed": cfg.seed + 1,
    }


def finish_fleet(
    cfg: Config,
    run: Run,
    model: Any,
    observe: str,
    record: RunRecord,
    scorer: Any,
    single: Any,
) -> dict[str, Any]:
    """Write a fleet run's files (checkpoint, metrics.csv, policy.csv, the learning curve), print
    its table, return its summary."""
    from irdrc.fleet.evaluate import baseline_rules
    from irdrc.fleet.policies import joint_policy
    from irdrc.fleet.scorer import fleet_metrics
    from irdrc.recipes.fleet.report import (
        clean_rows,
        exact_rows,
        fleet_info,
        format_rows,
        reference_policies,
        single_tables,
        starvation,
        write_joint_policy_csv,
    )
    from irdrc.runs.curves import plot_learning_curve
    from irdrc.runs.results import summary_dict, write_metrics_csv, write_rows_csv

    name = cfg.learner.learner
    run.checkpoint(record.state)
    greedy = record.greedy[0].cpu()
    write_metrics_csv(run.dir / "metrics.csv", record.history)
    curve = run.dir / f"learning_curve.{cfg.plot.format}"
    plot_learning_curve(record, curve, title=f"{name} on {run.scenario}", unit=UNIT)
    errors: dict[str, float] = {}
    if model.exact:
        joint = joint_policy(model, greedy)
        optimum = scorer.optimal.policy
        policies = {f"{name} (exact)": joint, "centralised optimum": optimum}
        rows = exact_rows(model, {**policies, **reference_policies(model, single)})
        write_joint_policy_csv(run.dir / "policy.csv", model, joint, optimum)
        learned = fleet_metrics(model, joint)[0]
        extra: dict[str, Any] = {
            "joint_states_differing_from_optimum": int((joint != optimum).sum())
        }
    else:
        measured = {f"{name} (Monte-Carlo)": scorer.measure(greedy)}
        for rule in baseline_rules(model, single):
            measured[f"{rule} (Monte-Carlo)"] = scorer.baselines[rule]
        rows = {label: m.per_vehicle for label, m in measured.items()}
        errors = {label: m.ci95 for label, m in measured.items()}
        learned = measured[f"{name} (Monte-Carlo)"].fleet
        extra = {"monte_carlo": {**mc_keys(cfg), "ci95": errors}}
        write_rows_csv(run.dir / "policy.csv", single_tables(model, greedy))
    print(f"\n{name}: {record.env_steps} {UNIT}, {record.wall_seconds:.0f} s\n")
    reference = "the centralised optimum" if model.exact else f"{scorer.reference} (Monte-Carlo)"
    print(format_rows(rows, scorer.optimal_metrics.avg_reward, reference))
    if line := starvation(name, rows[next(iter(rows))]):
        extra["starvation"] = line
        print("\n" + line)
    if errors:
        print(
            "\nMonte-Carlo 95 % half-widths of the fleet reward: "
            + ", ".join(f"{k} ± {v:.4f}" for k, v in errors.items())
        )
        extra["verdict"] = verdict(name, measured, scorer.reference)
        print("\n" + extra["verdict"])
    elif not record.interrupted and (line := fleet_warning(name, observe, learned, scorer)):
        print("\n" + line)
    return summary_dict(
        method=name,
        scenario=run.scenario,
        seed=cfg.seed,
        env_steps=record.env_steps,
        wall_seconds=record.wall_seconds,
        metrics=learned,
        optimal=scorer.optimal_metrics,
        reference="centralised optimum (exact)" if model.exact else "best baseline (Monte-Carlo)",
        fleet=fleet_info(model.spec, observe, model),
        vehicle_steps=record.env_steps * model.N,
        updates=record.updates,
        env_steps_to_95=record.first_reaching(0.95),
        env_steps_to_99=record.first_reaching(0.99),
        interrupted=record.interrupted,
        per_vehicle=clean_rows(rows[next(iter(rows))]),
        table={label: clean_rows(per) for label, per in rows.items()},
        **extra,
        **record.info,
    )


def verdict(name: str, measured: dict[str, Any], best: str) -> str:
    """Beyond the exact model: the learner against the best baseline (Monte-Carlo), which wins —
    or that the two are within their 95 % intervals of each other."""
    mine, theirs = measured[f"{name} (Monte-Carlo)"], measured[f"{best} (Monte-Carlo)"]
    a, b = mine.fleet.avg_reward, theirs.fleet.avg_reward
    half = (mine.ci95**2 + theirs.ci95**2) ** 0.5
    head = (
        f"{name} earns {a:.4f} ± {mine.ci95:.4f} per fleet step, the best baseline ({best}) "
        f"{b:.4f} ± {theirs.ci95:.4f} (Monte-Carlo, 95 %): "
    )
    note = (
        " (no optimum is known beyond the exact model: a win over the best baseline is no verdict "
        "on the optimum)"
    )
    if a - b > half:
        return head + f"{name} earns {a - b:.4f} more than the best baseline" + note
    if b - a > half:
        return head + (
            f"the baseline wins by {b - a:.4f}; a longer run (algo.total_frames, or ppo."
            "total_frames for mappo and ippo) is the first thing to try"
        )
    return head + "neither wins: the difference is within the intervals"


def fleet_warning(name: str, observe: str, learned: Any, scorer: Any) -> str | None:
    """Within the exact model: a warning when the learner ends below 0.99 of the centralised
    optimum, with the one override most likely to help — every vehicle's state where it saw its
    own only (the gap may be information no own-observation policy has: docs/FLEET.md), else a
    longer run."""
    ratio = learned.avg_reward / scorer.optimal_metrics.avg_reward
    if ratio >= 0.99:
        return None
    head = f"warning: {name} ends at {ratio:.4f} of the centralised optimum; "
    if observe == "own":
        return head + (
            "with its own state a vehicle may not reach it at all (docs/FLEET.md: the best "
            "decentralised policy found per cell); learner=joint env.observe=full sees every "
            "vehicle's state"
        )
    key = "ppo.total_frames" if name in POLICY_GRADIENT else "algo.total_frames"
    return head + f"a longer run ({key}) is the first thing to try"
