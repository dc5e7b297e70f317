"""``recipes/solve.py``: the exact optimum (value iteration) and the exact metrics of the optimum
beside the baselines — on the dense model, on the factored operator above its size (up to
millions of states, with an estimate of time and memory before it starts and progress while it
solves), or for a fleet (``env=fleet``: the centralised optimum, and what cooperation is worth).

    python recipes/solve.py                            # paper scenario
    python recipes/solve.py env.p1.speed=1.0 reward.r4=50
    python recipes/solve.py env=large                  # S = 100 800, on the factored operator
    python recipes/solve.py env=fleet env.share=1.0    # two vehicles: the joint optimum
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from irdrc.core.checks import INT, build, check_number, check_numbers, grouped
from irdrc.core.params import Params
from irdrc.core.sizes import DENSE_LIMIT_BYTES, fits_dense
from irdrc.runs.compose import Composed
from irdrc.runs.limits import available_memory
from irdrc.runs.sections import ONE_OR_FLEET, Eval, check_common, scenario_field

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "solve"

EPISODIC_LIMIT_FLOPS = 2e11
"""Exact episodic metrics step a distribution through ``env.horizon`` matrix-vector products
(2·S² flops each) unless S is small enough for repeated squaring; above this estimate they are
refused (minutes on this class of machine)."""
BYTES_PER_STATE = 750
"""Peak memory of a factored solve beyond the imports, per state, for the estimate a solve prints
before it starts and the refusal past free memory: the optimum's value iteration and stationary
distribution, the baselines' and ``policy.csv`` (``large`` at S = 1 000 080: 948 MB resident, 234
MB of it the imports)."""
SWEEPS_GUESS = 550
"""Operator applications' worth of time a factored solve takes in all, for its estimate: value
iteration's sweeps, then the optimum's and the four baselines' stationary distributions (``large``
at S = 1 000 080: 450 sweeps' time; a smaller model's fixed costs weigh more: 1 300 at 100 800)."""


@dataclass(frozen=True)
class Config:
    """The solve's keys (``irdrc/conf/solve.yaml``)."""

    model: Any = scenario_field(ONE_OR_FLEET)
    eval: Eval = field(default_factory=Eval)
    optimum_gamma: float = 0.99
    tol: float = 1e-9
    max_iter: int = 100_000
    seed: int = 0
    max_minutes: float = 30.0

    def __post_init__(self) -> None:
        check_common(self)
        check_numbers(self, "", (("max_iter", 1, 10**8, INT),))
        object.__setattr__(self, "tol", check_number("tol", self.tol, 0, 1, open_lo=True))
        check_numbers(self, "", (("max_minutes", 0, 10**6, {"open_lo": True}),))


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked: values, and what the exact solve costs."""
    cfg = build(Config, composed.cfg)
    if not isinstance(cfg.model, Params):
        unchecked = "the fleet's optimum"
    elif cfg.model.env.actions == "continuous":
        unchecked = "the optimum over ρ"
    elif not fits_dense(cfg.model):
        unchecked = f"a model of {grouped(cfg.model.env.num_states)} states (the factored solve)"
    else:
        unchecked = None
    if unchecked is not None:
        composed.refuse_unread(
            ("eval",),
            f"{unchecked} is scored exactly, with no Monte-Carlo check (eval.* sets the dense "
            "single-vehicle solve's)",
        )
    if isinstance(cfg.model, Params) and cfg.model.env.actions != "binary":
        check_shares_fit(cfg.model)
    if isinstance(cfg.model, Params) and fits_dense(cfg.model):
        check_episodic_cost(cfg.model)
        cfg.eval.check_cost(cfg.model)
    elif not isinstance(cfg.model, Params):
        from irdrc.fleet.model import FleetModel  # the fleet's kernels: cheap beside the solve

        FleetModel(cfg.model[0]).check_exact()
    return cfg


def check_shares_fit(params: Params) -> None:
    """Refuse time-sharing (MODEL.md § D) on a model too large for its exact solve: it is built on
    the dense model, one S × S matrix per radar share (``continuous``: four per segment)."""
    env = params.env
    from irdrc.core.share import breakpoints

    actions = env.levels if env.actions == "levels" else 3 * (len(breakpoints(params)) - 1) + 1
    need = 8 * actions * env.num_states**2
    if not fits_dense(params) or need > 2 * DENSE_LIMIT_BYTES:
        raise ValueError(
            f"env.actions={env.actions}: the exact solve over radar shares is built on the dense "
            f"model, {actions} S × S matrices: ~{need / 2**30:.1f} GB for S = {grouped(env.num_states)} "
            "states; use a smaller scenario (env.queue_capacity) or env.actions=binary"
        )


def check_episodic_cost(params: Params, key: str = "env.horizon") -> None:
    """Refuse exact episodic metrics that would run for long (``EPISODIC_LIMIT_FLOPS``)."""
    from irdrc.core.exact.solve import DOUBLING_MAX_STATES

    S, T = params.env.num_states, params.env.horizon
    if S <= DOUBLING_MAX_STATES:
        return  # repeated squaring: log2(T) matrix products
    flops = 2.0 * S * S * T * 5
    if flops > EPISODIC_LIMIT_FLOPS:
        raise ValueError(
            f"{key}={T} with S = {S} states: exact episodic metrics would take ~{flops:.1e} flops "
            f"(limit {EPISODIC_LIMIT_FLOPS:.0e}); use a shorter horizon"
        )


def run(cfg: Config, run: Run) -> dict[str, Any]:
    """Solve, print the policy and the comparison table, write summary.json and policy.csv."""
    run.threads(1)
    if not isinstance(cfg.model, Params):
        from irdrc.recipes.fleet.report import solve_fleet

        summary = solve_fleet(cfg.model, cfg.optimum_gamma, cfg.tol, cfg.max_iter, cfg.seed, run)
    elif cfg.model.env.actions == "continuous":
        summary = solve_continuous(cfg, run)
    elif fits_dense(cfg.model):
        summary = solve_dense(cfg, run)
    else:
        summary = solve_factored(cfg, run)
    run.finish(summary)
    return summary


def solve_dense(cfg: Config, run: Run) -> dict[str, Any]:
    """Value iteration on the dense model; the optimum's and the baselines' exact long-run and
    episodic metrics, and a Monte-Carlo check of the optimum."""
    from irdrc.core.env import DFRCEnv
    from irdrc.core.evaluate import evaluate
    from irdrc.core.exact import build_model, episodic_metrics, stationary_metrics, value_iteration
    from irdrc.core.metrics import format_table
    from irdrc.core.policies import table_policy
    from irdrc.runs.report import degenerate_note
    from irdrc.runs.tables import closest_decisions, policy_table, share_table

    params, gamma = cfg.model, cfg.optimum_gamma
    t0 = time.perf_counter()
    model = build_model(params)
    sol = value_iteration(model, gamma=gamma, tol=cfg.tol, max_iter=cfg.max_iter)
    wall = time.perf_counter() - t0
    print(
        f"scenario={run.scenario}: value iteration, γ={gamma}, {sol.iterations} sweeps, {wall:.2f} s"
    )
    if params.env.actions == "binary":
        print(
            f"optimal policy ({int(sol.policy.sum())} of {model.num_states} states in radar mode):\n"
        )
        print(policy_table(model, sol.policy))
        print(
            "\nthe optimum's closest decisions (a learner needs the most samples to choose right "
            "where the margin is small against the spread of one step's value r + γ·V*(s′); "
            "samples of the combination that tell its modes apart at 95 %, and the episodes in "
            "which the optimum visits it that often):\n"
        )
        print(closest_decisions(model, sol, gamma))
    else:
        print(f"optimal policy over {model.num_actions} radar shares (env.actions=levels):\n")
        print(share_table(model, model.radar[sol.policy]))
    rows, errs = {}, {}
    opt = rows["optimal (stationary)"] = stationary_metrics(model, sol.policy)
    rows["optimal (episodic)"] = episodic_metrics(model, sol.policy)
    if cfg.eval.mc_episodes:
        env = DFRCEnv(params, batch_size=[cfg.eval.mc_batch], seed=cfg.seed)
        acting = table_policy(sol.policy, num_actions=model.num_actions)
        ev = evaluate(acting, env, episodes=int(cfg.eval.mc_episodes))
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
    episodic = rows["optimal (episodic)"].as_dict()
    return optimum_files(cfg, run, sol.policy, rows, errs, wall, episodic=episodic)


def solve_continuous(cfg: Config, run: Run) -> dict[str, Any]:
    """The optimum over ρ ∈ [0, 1] (MODEL.md § D) with its error bound, beside the binary optimum
    and the baselines, all exact and long-run; ``policy.csv`` holds each state's ``rho``."""
    import torch

    from irdrc.core.exact import build_model, episodic_metrics, stationary_metrics, value_iteration
    from irdrc.core.exact.continuum import solve_continuum
    from irdrc.core.metrics import format_table
    from irdrc.runs.tables import share_table

    params, gamma = cfg.model, cfg.optimum_gamma
    t0 = time.perf_counter()
    sol = solve_continuum(params, gamma=gamma)
    wall = time.perf_counter() - t0
    env = params.env
    print(
        f"scenario={run.scenario}: optimum over the radar share ρ ∈ [0, 1] (MODEL.md § D, "
        f"{env.sensing} sensing{f', κ = {env.dwell_gain:g}' if env.sensing == 'dwell' else ''}), "
        f"γ={gamma}, {sol.iterations} policy-iteration steps, {wall:.2f} s; each maximisation over "
        f"ρ within {sol.step_bound:.1e} of exact, values within {sol.value_bound:.1e} of the optimum's"
    )
    print("optimal radar shares:\n")
    print(share_table(sol.model, sol.rho))
    binary = build_model(params, shares=(0.0, 1.0))
    best = value_iteration(binary, gamma=gamma, tol=cfg.tol, max_iter=cfg.max_iter).policy
    still = torch.zeros(env.num_states, dtype=torch.int64)
    rows: dict[str, Any] = {}
    opt = rows["optimal (stationary)"] = stationary_metrics(sol.model, still)
    rows["optimal (episodic)"] = episodic_metrics(sol.model, still)
    rows["binary optimum (stationary)"] = stationary_metrics(binary, best)
    for name in ("round_robin", "always_comm", "always_radar", "random"):
        rows[f"{name} (stationary)"] = stationary_metrics(binary, name)
    print("\nexact metrics (stationary = long run; binary: comm or radar each step):\n")
    print(format_table(rows))
    bin_ = rows["binary optimum (stationary)"]
    print(
        f"\ntime-sharing earns {opt.avg_reward:.4f} per step against the binary optimum's "
        f"{bin_.avg_reward:.4f} (×{opt.avg_reward / bin_.avg_reward:.3f}) and misses "
        f"{100 * opt.miss_detection:.1f} % of events against {100 * bin_.miss_detection:.1f} %"
    )
    return optimum_files(
        cfg,
        run,
        sol.rho,
        rows,
        {},
        wall,
        episodic=rows["optimal (episodic)"].as_dict(),
        binary_optimum=bin_.as_dict(),
        step_bound=sol.step_bound,
        value_bound=sol.value_bound,
    )


def optimum_files(
    cfg: Config,
    run: Run,
    policy: Any,
    rows: dict[str, Any],
    errs: dict[str, Any],
    wall: float,
    **extra: Any,
) -> dict[str, Any]:
    """Write the optimal ``policy`` (``policy.csv``); return the summary of a solve whose metric
    ``rows`` start with the optimum's, ``extra`` added."""
    from irdrc.runs.report import table_dict
    from irdrc.runs.results import summary_dict
    from irdrc.runs.tables import write_policy_csv

    env = cfg.model.env
    shares = None if env.actions == "binary" else () if env.actions == "continuous" else env.shares
    write_policy_csv(run.dir / "policy.csv", policy, env.factor_levels, shares)
    opt = rows["optimal (stationary)"]
    return summary_dict(
        method="optimal",
        scenario=run.scenario,
        seed=cfg.seed,
        env_steps=0,
        wall_seconds=wall,
        metrics=opt,
        optimal=opt,
        **extra,
        table=table_dict(rows, errs),
    )


def duration(seconds: float) -> str:
    """``seconds`` for a person: ``0.4 s``, ``12 s``, ``3.5 min``, ``2.1 h``."""
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def size(nbytes: float) -> str:
    """``nbytes`` for a person: ``3 MB``, ``1.2 GB``."""
    if nbytes < 2**30:
        return f"{max(nbytes / 2**20, 1):.0f} MB"
    return f"{nbytes / 2**30:.1f} GB"


def estimate(params: Params, model: Any) -> tuple[float, float]:
    """(seconds, bytes) a factored solve of ``model`` should take here: two operator
    applications timed, times ``SWEEPS_GUESS``; ``BYTES_PER_STATE`` a state."""
    import torch

    V = torch.zeros(model.num_states, dtype=torch.float64)
    t0 = time.perf_counter()
    for _ in range(2):
        model.expect(V)
    per = (time.perf_counter() - t0) / 2
    return per * SWEEPS_GUESS, BYTES_PER_STATE * float(model.num_states)


def solve_factored(cfg: Config, run: Run) -> dict[str, Any]:
    """Value iteration (McQueen's bounds, ``tol``) and exact long-run metrics on the factored
    operator, beside round-robin, always-comm, always-radar and random; refused past this machine's memory or
    ``max_minutes``, with progress while it runs."""
    from irdrc.core.exact import (
        as_probs,
        build_factored,
        metrics_from_occupancy,
        stationary_distribution_factored,
        stationary_metrics,
        value_iteration,
    )
    from irdrc.core.metrics import format_table
    from irdrc.runs.progress import Heartbeat
    from irdrc.runs.tables import policy_table

    params, gamma = cfg.model, cfg.optimum_gamma
    t0 = time.perf_counter()
    model = build_factored(params)
    S = model.num_states
    seconds, need = estimate(params, model)
    print(
        f"scenario={run.scenario}: S = {grouped(S)} states, factored value iteration; estimate here "
        f"~{duration(seconds)} and ~{size(need)} (two sweeps timed)",
        flush=True,
    )
    free = available_memory() or math.inf  # unknown: no bound
    if need > 0.8 * free:
        raise ValueError(
            f"env.queue_capacity={params.env.queue_capacity}: S = {grouped(S)} states would need "
            f"~{need / 2**30:.1f} GB, more than this machine has free ({free / 2**30:.1f} GB)"
        )
    if seconds > 60 * cfg.max_minutes:
        raise ValueError(
            f"env.queue_capacity={params.env.queue_capacity}: S = {grouped(S)} states would take "
            f"~{duration(seconds)} here, above max_minutes={cfg.max_minutes:g}; raise "
            "max_minutes to solve it anyway"
        )
    beat = Heartbeat("solve")
    sol = value_iteration(
        model,
        gamma=gamma,
        tol=cfg.tol,
        max_iter=cfg.max_iter,
        progress=lambda i, b: beat.beat(f"value iteration: sweep {i}, values within {b:.1e} of V*"),
    )
    print(f"value iteration: {sol.iterations} sweeps, within {sol.bound:.1e} of V*", flush=True)
    mu, _ = stationary_distribution_factored(
        model,
        sol.policy,
        progress=lambda i, c: beat.beat(f"stationary distribution: step {i}, change {c:.1e}"),
    )
    probs = as_probs(sol.policy, S, model.num_actions)
    opt = metrics_from_occupancy(model, (mu[:, None] * probs).T.contiguous())
    wall = time.perf_counter() - t0
    print(
        f"exact stationary metrics, {wall:.2f} s in all\n"
        f"optimal policy ({int(sol.policy.sum())} of {S} states in radar mode):\n"
    )
    print(policy_table(model, sol.policy))
    rows = {"optimal (stationary)": opt}
    for name in ("round_robin", "always_comm", "always_radar", "random"):
        beat.beat(f"long-run metrics of {name}")
        rows[f"{name} (stationary)"] = stationary_metrics(model, name)
    print("\nexact long-run metrics (factored operator; no episodic metrics at this size):\n")
    print(format_table(rows))
    return optimum_files(
        cfg,
        run,
        sol.policy,
        rows,
        {},
        wall,
        num_states=S,
        solver="factored",
        sweeps=sol.iterations,
        value_bound=sol.bound,
    )
