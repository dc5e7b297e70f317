"""``recipes/constrained.py``: the most data subject to a miss-detection target (MODEL.md § A),
solved exactly by the LP of ``irdrc.core.cmdp`` beside the reward-optimal policy (``learner=dual``:
the same optimum on the LP's Lagrangian dual, ``irdrc.core.cmdp_dual``); with ``frontier=true`` the
whole frontier against the r4 route (``irdrc.recipes.constrained.frontier``); with
``learner=dqn_lagrangian`` learned too (``irdrc.agents.lagrangian``), scored exactly against the LP.

    python recipes/constrained.py target_miss=0.05               # LP optimum, summary.json, policy.csv
    python recipes/constrained.py learner=dual env.queue_capacity=1000   # the dual: S = 32 032
    python recipes/constrained.py target_miss=0.05 max_drop=0.01 min_radar=0.5
    python recipes/constrained.py frontier=true                  # frontier vs the r4 route
    python recipes/constrained.py learner=dqn_lagrangian target_miss=0.05 seed=3
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from irdrc.agents.configs import OBJECTIVES, LagrangianConfig, OffPolicyConfig
from irdrc.core import checks
from irdrc.core.params import Params
from irdrc.core.sizes import fits_dense
from irdrc.recipes.constrained.grid import FrontierGrid
from irdrc.runs.compose import Composed
from irdrc.runs.limits import check_dense
from irdrc.runs.resume import refuse_finished
from irdrc.runs.sections import Learning, check_speeds, scenario_field

if TYPE_CHECKING:
    from irdrc.core.exact.mdp import ExactMDP
    from irdrc.runs.scaffold import Run

NAME = "constrained"
ALGO_KEYS = OffPolicyConfig.keys()
"""The ``algo.*`` keys of DQN's machinery its learners read (a profile's file lists those that act)."""
SWEEP_DEFAULTS = ("progress=false", "logger=none")
"""What a sweep gives every trial of this recipe before its own overrides (which may change it)."""
RESUMABLE = True
LEARNERS = ("lp", "dual", "dqn_lagrangian")
"""``learner``: ``lp`` solves exactly; ``dqn_lagrangian`` also learns and is scored against it."""
MU_FIELDS = ("env_steps", "mu", "measured_miss", "cumulative_miss")
"""Columns of ``mu.csv``: the multiplier, the learner's measured miss detection, and the cumulative
miss detection of every training step so far (what its own training missed), over training."""


def _lagrangian(data: Any, prefix: str) -> LagrangianConfig:
    return LagrangianConfig.from_sections(
        data["algo"],
        data["network"],
        data.get("target_miss", 0.05),
        data.get("objective", "throughput"),
    )


@dataclass(frozen=True)
class Config(Learning):
    """The constrained recipe's keys (``irdrc/conf/constrained.yaml``)."""

    params: Params = scenario_field()
    algo: LagrangianConfig = field(
        default_factory=LagrangianConfig,
        metadata={"keys": ("algo", "network"), "build": _lagrangian},
    )
    target_miss: float = 0.05
    objective: str = "throughput"
    max_drop: float | None = None
    min_radar: float | None = None
    learner: str = "lp"
    device: str = "cpu"
    frontier: bool = False
    frontier_grid: FrontierGrid = field(default_factory=FrontierGrid)

    def __post_init__(self) -> None:
        super().__post_init__()
        checks.check_choice("objective", self.objective, OBJECTIVES)
        checks.check_choice("learner", self.learner, LEARNERS)
        checks.check_bool("frontier", self.frontier)
        object.__setattr__(
            self, "target_miss", checks.check_number("target_miss", self.target_miss, 0, 1)
        )
        for key, hi in (("max_drop", 1e12), ("min_radar", 1.0)):
            if getattr(self, key) is not None:
                object.__setattr__(self, key, checks.check_number(key, getattr(self, key), 0, hi))
        actions = self.params.env.actions
        if actions != "binary":
            if self.learner == "dqn_lagrangian":
                raise ValueError(
                    f"env.actions={actions}: learner=dqn_lagrangian learns whole-step modes "
                    "(env.actions=binary); over the radar share the region is solved exactly "
                    "(learner=lp)"
                )
            if self.frontier and actions == "levels":
                raise ValueError(
                    "frontier=true draws binary modes against time-sharing over ρ ∈ [0, 1]: "
                    "env.actions=binary or continuous"
                )
            for key in ("max_drop", "min_radar"):
                if actions == "continuous" and getattr(self, key) is not None:
                    raise ValueError(
                        f"{key}={getattr(self, key)}: over ρ ∈ [0, 1] the region bounds "
                        f"target_miss alone; env.actions=levels takes {key} (an LP)"
                    )
        if self.frontier:
            check_speeds("frontier_grid.p1_speed", self.frontier_grid.p1_speed, self.params)
        if self.learner == "dual":
            if self.frontier or actions != "binary":
                raise ValueError(
                    "learner=dual solves one scenario's whole-step modes (env.actions=binary, "
                    "frontier=false); the others are learner=lp's"
                )
            for key in ("max_drop", "min_radar"):
                if getattr(self, key) is not None:
                    raise ValueError(
                        f"{key}={getattr(self, key)}: learner=dual handles target_miss alone "
                        f"(use learner=lp for {key})"
                    )
        if self.learner == "dqn_lagrangian":
            if self.frontier:
                raise ValueError("learner=dqn_lagrangian learns one target: use frontier=false")
            for key in ("max_drop", "min_radar"):
                if getattr(self, key) is not None:
                    raise ValueError(
                        f"{key}={getattr(self, key)}: learner=dqn_lagrangian handles target_miss "
                        f"alone (use learner=lp for {key})"
                    )

    @property
    def constraints(self) -> dict[str, Any]:
        """``solve_cmdp``'s keyword arguments."""
        return {
            "target_miss": self.target_miss,
            "objective": self.objective,
            "max_drop": self.max_drop,
            "min_radar": self.min_radar,
        }


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked; a learner's model must fit the dense scorer, and one target's
    feasibility is the LP itself (``run`` solves it before any file is written)."""
    cfg = checks.build(Config, composed.cfg)
    refuse_unread(cfg, composed)
    if cfg.params.env.actions != "binary":
        from irdrc.recipes.constrained.region import check_share_lp
        from irdrc.recipes.solve import check_shares_fit

        check_shares_fit(cfg.params)
        check_share_lp(cfg.params)
    if cfg.learner == "dqn_lagrangian" or cfg.frontier:
        check_dense(cfg.params)  # the learner's exact scorer and the frontier's LPs: dense models
    if cfg.params.env.actions == "binary" and cfg.learner == "lp":
        from irdrc.recipes.constrained.lp_cost import check_binary_lp

        check_binary_lp(
            cfg.params,
            "use a smaller env.queue_capacity, or for target_miss alone learner=dual (the same "
            "optimum on the LP's dual, which factorises the chain instead)",
        )
    if resume is not None:
        total = cfg.algo.dqn.total_frames
        refuse_finished(cfg.resume, int(resume["frames"]), total, "algo.total_frames", total)
    return cfg


LEARNER_KEYS = ("algo", "network", "checkpoint", "eval")
"""The sections only ``learner=dqn_lagrangian`` reads (its settings, network, checkpoints and
evaluations)."""


def refuse_unread(cfg: Config, composed: Composed) -> None:
    """Refuse what the command line sets and this run would not read: a learner's keys where
    nothing learns, the one target and ``env.p1.speed`` where the frontier sets its own, the
    frontier's grid where no frontier is drawn."""
    if cfg.learner != "dqn_lagrangian":
        solves = "frontier=true solves LPs" if cfg.frontier else f"learner={cfg.learner} solves"
        composed.refuse_unread(
            LEARNER_KEYS,
            f"{solves} exactly and learns nothing; the learner's keys are read with "
            "learner=dqn_lagrangian",
        )
    if not cfg.frontier:
        composed.refuse_unread(("frontier_grid",), "the frontier's grid is read with frontier=true")
        return
    composed.refuse_unread(
        ("target_miss",),
        "frontier=true solves the LP at frontier_grid.points targets from 0 up and tabulates "
        "frontier_grid.targets=[…]",
    )
    composed.refuse_unread(
        ("env.p1.speed",), "frontier=true draws one frontier per frontier_grid.p1_speed=[…]"
    )


def run(cfg: Config, run: Run) -> dict[str, Any]:
    """One exact solve (and the learner, with ``learner=dqn_lagrangian``), or the frontier."""
    run.threads(cfg.num_threads)
    if cfg.frontier:
        from irdrc.recipes.constrained.frontier import run_frontier

        summary = run_frontier(cfg, run)
    elif cfg.learner == "dqn_lagrangian":
        summary = run_learned(cfg, run)
    elif cfg.params.env.actions != "binary":
        from irdrc.recipes.constrained.region import solve_shares

        summary = solve_shares(cfg, run)
    else:
        summary = solve_lp(cfg, run)
    if summary is not None:
        run.finish(summary)
    return summary


DUAL_HINT = "learner=dual finds the same optimum on the LP's dual, faster on deep queues"
"""What the LP's notice adds where the miss target is the only constraint (docs/CONSTRAINED.md:
8.3–9.0 s against 57 s at 100 packets)."""


def lp_model(params: Params) -> ExactMDP:
    """The exact model the LP runs on: dense while it fits, else factored (its transitions reach
    the LP as sparse matrices built from the factors)."""
    from irdrc.core.exact import build_factored, build_model

    return build_model(params) if fits_dense(params) else build_factored(params)


def describe_randomised(sol: Any, levels: Sequence[int] | None = None) -> list[str]:
    """One line per randomised state: its factors and P(radar)."""
    from irdrc.runs.tables import state_label

    return [
        f"  {state_label(s, levels)}: radar with probability {float(sol.p_radar[s]):.4f} (this "
        f"state is {float(sol.occupancy[:, s].sum()):.4f} of the time)"
        for s in sol.randomised
    ]


def solve_lp(cfg: Config, run: Run) -> dict[str, Any]:
    """Solve the constrained problem exactly (the LP, or with ``learner=dual`` its Lagrangian
    dual); print it beside the reward-optimal policy; write ``policy.csv`` (with ``p_radar``);
    return the summary (the optimum's exact metrics under ``optimal`` and ``metrics``)."""
    from irdrc.core.cmdp import solve_cmdp
    from irdrc.core.cmdp_dual import solve_cmdp_dual
    from irdrc.core.exact import build_factored, stationary_metrics, value_iteration
    from irdrc.core.metrics import format_table
    from irdrc.runs.progress import lp_notice
    from irdrc.runs.report import table_dict
    from irdrc.runs.results import summary_dict
    from irdrc.runs.tables import write_policy_csv

    t0 = time.perf_counter()
    if cfg.learner == "dual":  # the factored model: its sparse chain holds the arrivals' reach
        model: ExactMDP = build_factored(cfg.params)
        sol = solve_cmdp_dual(model, cfg.target_miss, cfg.objective)
        how = f"the LP's Lagrangian dual over {checks.grouped(model.num_states)} states"
    else:
        model = lp_model(cfg.params)
        alone = cfg.max_drop is None and cfg.min_radar is None
        lp_notice(model.num_states, DUAL_HINT if alone else "")
        sol = solve_cmdp(model, **cfg.constraints)
        variables = checks.grouped(model.num_actions * model.num_states)
        how = f"exact LP over {variables} occupation variables"
    wall = time.perf_counter() - t0
    tol = 1e-9 if fits_dense(cfg.params) else 1e-6
    reward_opt = stationary_metrics(
        model, value_iteration(model, gamma=cfg.optimum_gamma, tol=tol).policy
    )
    bounds = ", ".join(
        f"{name} {'≥' if name == 'radar_fraction' else '≤'} {bound:g}"
        for name, (_, bound) in sol.constraints.items()
    )
    print(
        f"scenario={run.scenario}: maximise {sol.objective} subject to {bounds} — {how}, "
        f"{wall:.2f} s"
    )
    print(
        f"optimum: {sol.objective} {sol.value:.6g} per step; randomises in "
        f"{len(sol.randomised)} state(s); {len(sol.unvisited)} state(s) never visited (radar there)"
    )
    for line in describe_randomised(sol, cfg.params.env.factor_levels):
        print(line)
    name = (
        "constrained optimum (LP's dual)" if cfg.learner == "dual" else "constrained optimum (LP)"
    )
    rows = {name: sol.metrics, "reward-optimal (value iteration)": reward_opt}
    print("\nexact long-run metrics:\n")
    print(format_table(rows))
    write_policy_csv(run.dir / "policy.csv", sol.policy, cfg.params.env.factor_levels)
    return summary_dict(
        method="constrained",
        scenario=run.scenario,
        seed=cfg.seed,
        env_steps=0,
        wall_seconds=wall,
        metrics=sol.metrics,
        optimal=sol.metrics,
        target_miss=cfg.target_miss,
        objective=sol.objective,
        value=sol.value,
        constraints={k: {"value": v, "bound": b} for k, (v, b) in sol.constraints.items()},
        randomised_states=len(sol.randomised),
        unvisited_states=len(sol.unvisited),
        reward_optimal=reward_opt.as_dict(),
        table=table_dict(rows, {}),
    )


def objective_ratio(entries: list[dict[str, Any]], sol: Any) -> list[dict[str, Any]]:
    """Evaluations read against the LP: each entry's ``optimality_ratio`` becomes its objective
    over the LP optimum's (the entries are the learner's history, so it keeps these)."""
    for e in entries:
        e["optimality_ratio"] = e[sol.objective] / sol.value if sol.value else float("nan")
    return entries


def run_learned(cfg: Config, run: Run) -> dict[str, Any]:
    """Train the Lagrangian DQN and score its final policy exactly against the LP optimum:
    ``summary.json`` (the learned policy's exact metrics under ``metrics``, the LP's under
    ``optimal``, training and measurement env steps, μ), ``policy.csv`` (with ``p_radar``),
    ``metrics.csv`` (exact evaluations of the greedy table at the current μ; its
    ``optimality_ratio`` is the objective over the LP optimum's) and ``mu.csv``."""
    from irdrc.agents import lagrangian
    from irdrc.core.cmdp import solve_cmdp
    from irdrc.core.exact import Scorer, build_model, stationary_metrics
    from irdrc.core.metrics import format_table
    from irdrc.runs.progress import lp_notice
    from irdrc.runs.report import table_dict
    from irdrc.runs.results import summary_dict, write_metrics_csv, write_rows_csv
    from irdrc.runs.tables import write_policy_csv
    from irdrc.runs.tracking import log_scalars

    config = cfg.algo
    model = build_model(cfg.params)
    t0 = time.perf_counter()
    lp_notice(model.num_states)
    sol = solve_cmdp(model, **cfg.constraints)
    print(
        f"scenario={run.scenario}: the exact constrained optimum (LP, {time.perf_counter() - t0:.2f} "
        f"s): {sol.objective} {sol.value:.6g}, miss detection {sol.metrics.miss_detection:.4f}"
    )
    logger = run.make_logger(cfg.logger, config.name)
    scorer = Scorer(model, gamma=cfg.optimum_gamma)
    with run.training(config.dqn.total_frames, config.name, checkpoint=cfg.checkpoint) as hooks:
        on_eval = hooks.on_eval
        hooks.on_eval = lambda entries: on_eval(objective_ratio(entries, sol))
        record = lagrangian.train(
            cfg.params,
            config,
            seed=cfg.seed,
            device=cfg.device,
            scorer=scorer,
            eval_every_frames=cfg.eval.every_frames or 1000,
            hooks=hooks,
            resume=run.resume_state,
        )
    if record.interrupted:
        run.checkpoint(record.state)
        run.finish(None, interrupted_at=record.env_steps)
    mu_trace = record.info.pop("mu_trace")
    write_metrics_csv(run.dir / "metrics.csv", record.history)
    write_rows_csv(run.dir / "mu.csv", mu_trace, MU_FIELDS)
    run.checkpoint(record.state)
    policy = record.policy
    if policy is None:
        raise RuntimeError("the Lagrangian DQN returned no final policy")
    learned = stationary_metrics(model, policy[0])
    rows = {
        f"{config.name} (exact)": learned,
        "constrained optimum (LP)": sol.metrics,
        "reward-optimal (value iteration)": stationary_metrics(model, scorer.optimal.policy),
    }
    value = float(getattr(learned, sol.objective))
    ratio = value / sol.value if sol.value else float("nan")
    print("\nexact long-run metrics:\n")
    print(format_table(rows))
    print(
        f"\n{config.name}: {sol.objective} {value:.4f} = {ratio:.3f} of the LP optimum, miss "
        f"detection {learned.miss_detection:.4f} (target {cfg.target_miss:g}); "
        f"{record.training_env_steps} training + {record.measurement_env_steps} measurement = "
        f"{record.env_steps} env steps, {record.wall_seconds:.0f} s"
    )
    write_policy_csv(run.dir / "policy.csv", policy[0], cfg.params.env.factor_levels)
    log_scalars(
        logger,
        {"final/objective_ratio": ratio, "final/miss_detection": learned.miss_detection},
        record.env_steps,
    )
    info = {k: v for k, v in record.info.items() if k != "replay_sampler"}
    return summary_dict(
        method=config.name,
        scenario=run.scenario,
        seed=cfg.seed,
        env_steps=record.env_steps,
        wall_seconds=record.wall_seconds,
        metrics=learned,
        optimal=sol.metrics,
        training_env_steps=record.training_env_steps,
        measurement_env_steps=record.measurement_env_steps,
        target_miss=cfg.target_miss,
        objective=sol.objective,
        value=value,
        optimal_value=sol.value,
        objective_ratio=ratio,
        interrupted=record.interrupted,
        learner=info,
        reward_optimal=rows["reward-optimal (value iteration)"].as_dict(),
        table=table_dict(rows, {}),
    )
