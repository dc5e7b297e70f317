"""``recipes/evaluate.py``: a saved policy on any scenario — a DQN, SAC or PPO run's network, or a
one-stream DQN's (``online.py learner=dqn``; ``checkpoint=…/checkpoint.pt``), or a
single-vehicle run's table (``policy=…/policy.csv``, randomised ones included).

The policy is scored exactly on the scenario the command line composes (long run, and episodic on
models small enough for the dense matrices), by Monte-Carlo episodes on its simulator, and against
that scenario's own optimum and round-robin: transfer and robustness checks in one command. A
network is evaluated on the observations of the new scenario's states, scaled as in its training.

    python recipes/evaluate.py checkpoint=outputs/DATE/TIME/checkpoint.pt env.p1.speed=1.0
    python recipes/evaluate.py policy=outputs/DATE/TIME/policy.csv env=ref_impl
    python recipes/evaluate.py policy=outputs/DATE/TIME/policy.csv target_miss=0.1

With ``target_miss`` a comm/radar policy is also read against the constrained optimum at that
miss-detection target (the LP of ``recipes/constrained.py``): its packets over the LP's, and whether
its own long-run miss detection meets the target.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from irdrc.core import checks
from irdrc.core.checks import build, check_file
from irdrc.core.metrics import Metrics
from irdrc.core.params import Params
from irdrc.runs.compose import Composed
from irdrc.runs.sections import Eval, check_common, scenario_field

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "evaluate"


@dataclass(frozen=True)
class Config:
    """The evaluation's keys (``irdrc/conf/evaluate.yaml``): exactly one of ``checkpoint`` and
    ``policy``; ``target_miss`` (optional) reads a comm/radar policy against the LP at that
    target too."""

    params: Params = scenario_field()
    checkpoint: str | None = None
    policy: str | None = None
    target_miss: float | None = None
    eval: Eval = field(default_factory=Eval)
    optimum_gamma: float = 0.99
    seed: int = 0
    num_threads: int = 1

    def __post_init__(self) -> None:
        check_common(self)
        given = [k for k in ("checkpoint", "policy") if getattr(self, k)]
        if len(given) != 1:
            raise ValueError(
                "evaluate needs exactly one of checkpoint=…/checkpoint.pt (a run's network) or "
                f"policy=…/policy.csv (a single-vehicle run's table); got "
                f"{' and '.join(given) or 'neither'}"
            )
        if self.target_miss is not None:
            target = checks.check_number("target_miss", self.target_miss, 0, 1, open_hi=True)
            object.__setattr__(self, "target_miss", target)
            if self.params.env.actions != "binary":
                raise ValueError(
                    f"target_miss reads a comm/radar policy against the LP; with "
                    f"env.actions={self.params.env.actions} the constrained optimum is "
                    "recipes/constrained.py's (env.actions=continuous: over the radar share)"
                )


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked; the policy's file read and fitted to the scenario."""
    cfg = build(Config, composed.cfg)
    cfg.eval.check_cost(cfg.params)
    _, source, name = load_source(cfg)  # exactly one readable checkpoint / policy that fits
    if name == "rho" and cfg.target_miss is not None:
        raise ValueError(
            f"{source}: target_miss reads a comm/radar policy against the LP; a radar-share "
            "policy's constrained optimum is recipes/constrained.py env.actions=continuous"
        )
    if cfg.target_miss is not None:
        from irdrc.recipes.constrained.lp_cost import check_binary_lp

        check_binary_lp(cfg.params, "use a smaller env.queue_capacity, or leave target_miss out")
    return cfg


def network_table(path: Path, params: Params) -> tuple[Any, str, str]:
    """The policy, on the states of ``params``, of the network saved at ``path`` — a DQN run's
    greedy table, or a SAC or PPO run's radar shares —, a description of it (method, env steps),
    and its row name (``network`` or ``rho``).

    Raises:
        ValueError: an unreadable checkpoint, one of a recipe evaluate does not read, or a
            scenario whose observations have another shape than the training scenario's.
    """
    from irdrc.agents.base import load_checkpoint
    from irdrc.runs.resume import checkpoint_recipe

    state = load_checkpoint(path, key="checkpoint")
    saved = state["config"]
    recipe = checkpoint_recipe(path, state)
    fleet = "vehicles" in saved.get("env", {})
    if recipe == "online" and saved.get("learner") in ("dqn", "dqn_paper"):
        return stream_dqn_table(path, state, params)
    if recipe not in ("dqn", "sac", "ppo") or "env" not in saved or fleet or "target_miss" in saved:
        table = path.parent / "policy.csv"
        hint = (
            f"; its run's table is scored with policy={table}"
            if table.is_file() and not fleet
            else ""
        )
        raise ValueError(
            f"checkpoint={path}: not a checkpoint of recipes/dqn.py, sac.py, ppo.py or online.py "
            f"learner=dqn (this one: {recipe or 'another recipe'}"
            f"{' learner=' + str(saved['learner']) if recipe == 'online' else ''}); evaluate "
            f"reads a single-vehicle network{hint}"
        )
    trained = Params.from_config(saved)
    check_observations(path, trained, params)
    steps = f"trained {int(state['frames'])} env steps ({path})"
    if recipe in ("sac", "ppo"):
        from irdrc.agents import ppo, sac
        from irdrc.agents.configs.continuous import PPOConfig, SACConfig

        learner, config = (sac, SACConfig) if recipe == "sac" else (ppo, PPOConfig)
        cfg = config.from_sections(saved["algo"], saved["network"])
        rho = learner.saved_shares(state, cfg, trained, params)
        return rho, f"{recipe} radar shares {steps}", "rho"
    table, name = dqn_table(state, saved, trained, params)
    source = f"{name} {steps}"
    table, rho = fit_actions(table, trained.env.shares, params, source)
    return table, source, "rho" if rho else "network"


def stream_dqn_table(path: Path, state: dict[str, Any], params: Params) -> tuple[Any, str, str]:
    """``network_table`` of a one-stream DQN run (``recipes/online.py learner=dqn``): the greedy
    table of the network it scored, on the states of ``params``."""
    from irdrc.online.configs import learner_config
    from irdrc.online.dqn import saved_greedy

    saved = state["config"]
    trained = Params.from_config(saved)
    check_observations(path, trained, params)
    cfg = learner_config(saved["learner"], saved.get("algo"))
    table = saved_greedy(state["learner"], cfg, trained, params)
    source = f"{cfg.name} on one stream, trained {int(state['frames'])} env steps ({path})"
    table, rho = fit_actions(table, trained.env.shares, params, source)
    return table, source, "rho" if rho else "network"


def check_observations(path: Path, trained: Params, params: Params) -> None:
    """A network trained on ``trained`` reads the observations of ``params``: the same width.

    Raises:
        ValueError: another number of observation entries (bursty arrivals add the phase).
    """
    from irdrc.core.dynamics import observation_high

    want, shape = observation_high(trained).shape[0], observation_high(params).shape[0]
    if shape != want:
        raise ValueError(
            f"checkpoint={path}: its network reads {want} observation entries, this scenario has "
            f"{shape} (bursty arrivals add the traffic phase): evaluate it on a scenario of the "
            "same kind"
        )


def dqn_table(
    state: dict[str, Any], saved: dict[str, Any], trained: Params, params: Params
) -> tuple[Any, str]:
    """A DQN checkpoint's greedy table on the states of ``params``, and its profile's name."""
    from torchrl.objectives import DQNLoss

    from irdrc.agents.configs import DQNConfig
    from irdrc.agents.offpolicy import greedy_table, make_qnet, policy_view
    from irdrc.core.env import DFRCEnv

    cfg = DQNConfig.from_sections(saved["algo"], saved["network"])
    train_env = DFRCEnv(trained, batch_size=[1])
    qnet = make_qnet(train_env, cfg.network)
    with warnings.catch_warnings():  # no target updater: this loss only holds the networks
        warnings.filterwarnings("ignore", message="No target network updater")
        loss = DQNLoss(qnet, delay_value=True, action_space=train_env.action_spec_unbatched)
        loss.make_value_estimator(gamma=cfg.gamma)
        loss.load_state_dict(state["loss"])
        with policy_view(loss, cfg):
            return greedy_table(qnet, DFRCEnv(params, batch_size=[1])), cfg.name


def load_source(cfg: Config) -> tuple[Any, str, str]:
    """The policy to evaluate on the scenario: ([S] actions or [S, 2] probabilities, its
    description, its row name), from ``checkpoint=`` or ``policy=``.

    Raises:
        ValueError: an unreadable file, or one that does not fit the scenario (another number of
            states, another observation shape, a fleet's joint policy).
    """
    params = cfg.params
    if cfg.checkpoint:
        path = check_file("checkpoint", Path(str(cfg.checkpoint)).expanduser(), "checkpoint.pt")
        return network_table(path, params)
    path = check_file("policy", Path(str(cfg.policy)).expanduser(), "policy.csv")
    from irdrc.runs.results import read_csv_table
    from irdrc.runs.tables import read_policy_csv, read_share_csv

    header = read_csv_table(path)[0]
    if "action1" in header:
        raise ValueError(
            f"policy={path}: a fleet run's policy.csv (one joint action per joint state); evaluate "
            "scores single-vehicle policies — a fleet's are scored by recipes/fleet.py and "
            "recipes/solve.py env=fleet"
        )
    if "rho" in header:
        rho = read_share_csv(path, params.env.num_states)
        return rho, f"radar-share policy table {path}", "rho"
    policy = read_policy_csv(path, num_states=params.env.num_states, probabilities=True)
    if bool(((policy[:, 1] == 0) | (policy[:, 1] == 1)).all()):
        table, as_rho = fit_actions(policy[:, 1].long(), (0.0, 1.0), params, f"policy table {path}")
        return table, f"policy table {path}", "rho" if as_rho else "policy"
    source = f"randomised policy table {path}"
    return fit_actions(policy, (0.0, 1.0), params, source)[0], source, "policy"


def fit_actions(
    policy: Any, shares: tuple[float, ...] | None, params: Params, source: str
) -> tuple[Any, bool]:
    """``policy`` — [S] actions indexing ``shares`` (the radar share of each action: (0, 1) for
    comm/radar), or [S, 2] comm/radar probabilities — in the action space of the scenario
    ``params`` (MODEL.md § D), and whether it is now a table of radar shares ρ: unchanged where
    the scenario's actions have the same shares; ρ = shares[action] on ``env.actions=continuous``;
    else each share's action among the scenario's levels (radar, ρ = 1, is the last level).

    Raises:
        ValueError: a randomised table on a scenario of other actions, or a share the scenario's
            levels lack (naming the shares and ``env.actions=continuous``, which takes any).
    """
    import torch

    want = params.env.shares
    if want is not None and tuple(want) == tuple(shares or ()):
        return policy, False
    on = f"env.actions={params.env.actions}" + (
        f" with env.levels={params.env.levels}" if params.env.actions == "levels" else ""
    )
    if policy.ndim == 2:
        raise ValueError(
            f"{source}: a randomised comm/radar table is scored on env.actions=binary "
            f"scenarios only (this one: {on})"
        )
    rho = torch.as_tensor(shares, dtype=torch.float64)[torch.as_tensor(policy).long()]
    if want is None:
        return rho, True
    grid = torch.as_tensor(want, dtype=torch.float64)
    level = (rho[:, None] - grid[None]).abs().argmin(-1)
    missing = sorted({round(float(r), 6) for r in rho[(grid[level] - rho).abs() > 1e-9]})
    if missing:
        raise ValueError(
            f"{source}: its radar shares {missing} are not among the actions of {on} "
            f"(ρ = {', '.join(f'{g:g}' for g in want)}); env.actions=continuous scores any share"
        )
    return level, False


def against_optimum(learned: Metrics, opt: Metrics, what: str) -> str:
    """The policy's average reward read against the scenario's ``what``: as a ratio where the
    optimum earns more than 0, else as the reward it falls short by (a ratio to an optimum that
    earns ≤ 0 would not rank policies)."""
    if opt.avg_reward > 0:
        return f"{learned.avg_reward / opt.avg_reward:.4f} of this scenario's {what} (average reward, exact)"
    return (
        f"{learned.avg_reward:.4f} per step, {opt.avg_reward - learned.avg_reward:.4f} below this "
        f"scenario's {what} ({opt.avg_reward:.4g} per step: no ratio to an optimum that earns ≤ 0)"
    )


def run(cfg: Config, run: Run) -> dict[str, Any]:
    """Score the policy of ``checkpoint=`` or ``policy=`` on the composed scenario; write
    summary.json and policy.csv (the policy on this scenario's states), print the table."""
    from irdrc.core.env import DFRCEnv
    from irdrc.core.evaluate import evaluate
    from irdrc.core.exact import DenseModel, episodic_metrics, exact_scorer, stationary_metrics
    from irdrc.core.metrics import format_table
    from irdrc.core.policies import table_policy
    from irdrc.runs.report import table_dict
    from irdrc.runs.results import summary_dict
    from irdrc.runs.tables import policy_differences, write_policy_csv

    run.threads(cfg.num_threads)
    params = cfg.params
    t0 = time.perf_counter()
    policy, source, name = load_source(cfg)
    if name == "rho":
        return score_shares(cfg, run, policy, source, t0)
    scorer = exact_scorer(params, cfg.optimum_gamma)
    model = scorer.model
    S = params.env.num_states
    dense = isinstance(model, DenseModel)
    if policy.ndim == 2 and not dense:
        raise ValueError(f"{source}: randomised tables are scored on dense models only (S = {S})")
    learned = scorer.metrics(policy) if policy.ndim == 1 else stationary_metrics(model, policy)
    opt = scorer.optimal_metrics
    rows = {f"{name} (exact, long run)": learned}
    errs: dict[str, dict[str, float]] = {}
    if dense:
        rows[f"{name} (exact, episodic)"] = episodic_metrics(model, policy)
    if cfg.eval.mc_episodes:
        env = DFRCEnv(params, batch_size=[cfg.eval.mc_batch], seed=cfg.seed)
        acting = table_policy(policy, seed=cfg.seed, num_actions=model.num_actions)
        ev = evaluate(acting, env, episodes=int(cfg.eval.mc_episodes))
        label = f"{name} (Monte-Carlo, episodic)"
        rows[label], errs[label] = ev.metrics, ev.ci95
    rows["optimal (exact, long run)"] = opt
    if dense:
        rows["optimal (exact, episodic)"] = episodic_metrics(model, scorer.optimal.policy)
        rows["round_robin (exact, long run)"] = stationary_metrics(model, "round_robin")
    constrained = against_lp(model, learned, cfg.target_miss, rows)
    wall = time.perf_counter() - t0
    print(f"scenario={run.scenario} (S = {S}): {source}\n")
    print(format_table(rows, errors=errs))
    print(
        "long run: the policy's stationary average; episodic: episodes of "
        f"{params.env.horizon} steps from a uniform reset, as the Monte-Carlo row samples"
    )
    print(f"\n{name}: {against_optimum(learned, opt, 'optimum')}")
    if constrained:
        print(constrained.pop("line"))
    if policy.ndim == 1 and dense:
        print(policy_differences(model, policy, scorer.optimal.policy))
    write_policy_csv(run.dir / "policy.csv", policy, params.env.factor_levels)
    summary = summary_dict(
        method="evaluate",
        scenario=run.scenario,
        seed=cfg.seed,
        env_steps=0,
        wall_seconds=wall,
        metrics=learned,
        optimal=opt,
        source=source,
        states_differing_from_optimum=(
            int((policy != scorer.optimal.policy).sum()) if policy.ndim == 1 else None
        ),
        table=table_dict(rows, errs),
        **constrained,
    )
    run.finish(summary)
    return summary


def against_lp(
    model: Any, learned: Any, target_miss: float | None, rows: dict[str, Any]
) -> dict[str, Any]:
    """With ``target_miss``, the policy read against the LP at that target (its row added to
    ``rows``): summary.json's ``target_miss``, ``lp`` (throughput, miss detection; None where no
    policy meets the target), ``lp_ratio`` (packets per step over the LP's), ``meets_target``, and
    the printed ``line``. Without it, {}."""
    if target_miss is None:
        return {}
    from irdrc.core.cmdp import InfeasibleTarget, lp_standing, solve_cmdp
    from irdrc.runs.progress import lp_notice

    lp_notice(model.num_states)
    try:
        lp = solve_cmdp(model, target_miss)
    except InfeasibleTarget:
        lp = None
    ratio, meets = lp_standing(learned, lp.value if lp else 0.0, target_miss)
    verdict = "meets it" if meets else "over it"
    own = f"its long-run miss detection {learned.miss_detection:.4f} {verdict}"
    if lp is None:
        line = f"target_miss={target_miss}: no policy meets it on this scenario; {own}"
    else:
        rows[f"LP at target_miss={target_miss} (exact, long run)"] = lp.metrics
        line = (
            f"target_miss={target_miss}: {ratio:.4f} of the LP's packets "
            f"({learned.throughput:.4f} against {lp.value:.4f} per step); {own}"
        )
    return {
        "target_miss": target_miss,
        "lp": None
        if lp is None
        else {"throughput": lp.value, "miss_detection": lp.metrics.miss_detection},
        "lp_ratio": None if lp is None else ratio,
        "meets_target": meets,
        "line": line,
    }


def score_shares(cfg: Config, run: Run, rho: Any, source: str, t0: float) -> dict[str, Any]:
    """A radar-share policy (``rho`` [S], MODEL.md § D) scored exactly against the optimum over
    ρ ∈ [0, 1] and the binary optimum, and by Monte-Carlo on ``env.actions=continuous``."""
    from irdrc.core.env import DFRCEnv
    from irdrc.core.evaluate import evaluate
    from irdrc.core.exact import exact_scorer
    from irdrc.core.exact.continuum import ContinuumScorer
    from irdrc.core.metrics import format_table
    from irdrc.core.policies import share_table_policy
    from irdrc.runs.report import table_dict
    from irdrc.runs.results import summary_dict
    from irdrc.runs.tables import write_policy_csv

    binary = cfg.params.with_overrides({"env.actions": "binary"})
    continuous = cfg.params.with_overrides({"env.actions": "continuous"})
    scorer = ContinuumScorer(continuous, cfg.optimum_gamma)
    learned, opt = scorer.metrics(rho), scorer.optimal_metrics
    rows = {"policy (exact, long run)": learned}
    errs: dict[str, dict[str, float]] = {}
    if cfg.eval.mc_episodes:
        env = DFRCEnv(continuous, batch_size=[cfg.eval.mc_batch], seed=cfg.seed)
        ev = evaluate(share_table_policy(rho), env, episodes=int(cfg.eval.mc_episodes))
        label = "policy (Monte-Carlo, episodic)"
        rows[label], errs[label] = ev.metrics, ev.ci95
    rows["optimal over ρ (exact, long run)"] = opt
    rows["optimal binary (exact, long run)"] = exact_scorer(
        binary, cfg.optimum_gamma
    ).optimal_metrics
    S = cfg.params.env.num_states
    print(f"scenario={run.scenario} (S = {S}): {source}\n")
    print(format_table(rows, errors=errs))
    print(f"\npolicy: {against_optimum(learned, opt, 'optimum over ρ ∈ [0, 1]')}")
    write_policy_csv(run.dir / "policy.csv", rho, cfg.params.env.factor_levels, shares=())
    summary = summary_dict(
        method="evaluate",
        scenario=run.scenario,
        seed=cfg.seed,
        env_steps=0,
        wall_seconds=time.perf_counter() - t0,
        metrics=learned,
        optimal=opt,
        source=source,
        reference="optimum over ρ ∈ [0, 1] (exact)",
        table=table_dict(rows, errs),
    )
    run.finish(summary)
    return summary
