"""A saved policy on any scenario: ``python recipes/evaluate.py checkpoint=… env=…`` (a DQN
network) or ``policy=…/policy.csv`` (any run's table, randomised ones included).

The policy is scored exactly on the scenario the command line composes (long run, and episodic on
models small enough for the dense matrices), by Monte-Carlo episodes on its simulator, and against
that scenario's own optimum and round-robin: transfer and robustness checks in one command. A
network is evaluated on the observations of the new scenario's states, scaled as in its training.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from irdrc.core.env import DFRCEnv
from irdrc.core.evaluate import evaluate
from irdrc.core.factored import exact_scorer
from irdrc.core.metrics import Metrics, format_table
from irdrc.core.model import ExactModel
from irdrc.core.params import Params
from irdrc.core.policies import table_policy
from irdrc.core.solve import episodic_metrics, stationary_metrics
from irdrc.experiments.config import scenario_name
from irdrc.experiments.finish import table_dict
from irdrc.experiments.results import (
    policy_differences,
    read_policy_csv,
    summary_dict,
    write_policy_csv,
    write_summary,
)


def network_table(path: Path, params: Params) -> tuple[torch.Tensor, str]:
    """The greedy table, on the states of ``params``, of the DQN network saved at ``path``, and a
    description of it (method, training scenario's key values that differ, env steps).

    Raises:
        ValueError: an unreadable checkpoint, or a scenario whose observations have another shape
            than the training scenario's.
    """
    from irdrc.agents import dqn, dqn_variants
    from irdrc.agents.offpolicy import greedy_table, make_dqn_loss, make_qnet, policy_view

    state = dqn.load_checkpoint(path)
    saved = OmegaConf.create(state["config"])
    cfg = dqn.DQNConfig.from_node(saved)
    trained = Params.from_config(saved)
    train_env = DFRCEnv(trained, batch_size=[1])
    target_env = DFRCEnv(params, batch_size=[1])
    shape, want = target_env.dynamics.obs.shape[-1], train_env.dynamics.obs.shape[-1]
    if shape != want:
        raise ValueError(
            f"checkpoint={path}: its network reads {want} observation entries, this scenario has "
            f"{shape} (bursty arrivals add the traffic phase): evaluate it on a scenario of the "
            "same kind"
        )
    with warnings.catch_warnings():  # no target updater: this loss only holds the networks
        warnings.filterwarnings("ignore", message="No target network updater")
        if cfg.distributional:
            qnet, loss = dqn_variants.make_distributional(train_env, cfg)
        else:
            qnet = make_qnet(train_env, cfg.network)
            loss = make_dqn_loss(qnet, train_env, cfg)
    loss.load_state_dict(state["loss"])
    with policy_view(loss, cfg):
        table = greedy_table(qnet, target_env)
    return table, f"{cfg.name} trained {int(state['frames'])} env steps ({path})"


def load_source(cfg: DictConfig, params: Params) -> tuple[torch.Tensor, str, str]:
    """The policy to evaluate on ``params``: ([S] actions or [S, 2] probabilities, its
    description, its row name), from ``checkpoint=`` or ``policy=`` (exactly one).

    Raises:
        ValueError: neither or both given, an unreadable file, or one that does not fit the
            scenario (another number of states, another observation shape).
    """
    given = [k for k in ("checkpoint", "policy") if cfg.get(k)]
    if len(given) != 1:
        raise ValueError(
            "evaluate needs exactly one of checkpoint=…/checkpoint.pt (a DQN run's network) or "
            f"policy=…/policy.csv (any run's table); got {' and '.join(given) or 'neither'}"
        )
    if cfg.get("checkpoint"):
        path = Path(str(cfg.checkpoint)).expanduser()
        table, source = network_table(path, params)
        return table, source, "network"
    path = Path(str(cfg.policy)).expanduser()
    policy = read_policy_csv(path, num_states=params.env.num_states, probabilities=True)
    if bool(((policy[:, 1] == 0) | (policy[:, 1] == 1)).all()):
        return policy[:, 1].long(), f"policy table {path}", "policy"
    return policy, f"randomised policy table {path}", "policy"


def run_evaluate(cfg: DictConfig, out: Path) -> dict[str, Any]:
    """Score the policy of ``checkpoint=`` or ``policy=`` on the composed scenario; write
    summary.json and policy.csv (the policy on this scenario's states), print the table."""
    torch.set_num_threads(int(cfg.get("num_threads", 1)))
    params = Params.from_config(cfg)
    scenario = scenario_name(cfg)
    t0 = time.perf_counter()
    scorer = exact_scorer(params, float(cfg.optimum_gamma))
    model = scorer.model
    S = params.env.num_states
    policy, source, name = load_source(cfg, params)
    dense = isinstance(model, ExactModel)
    if policy.ndim == 2 and not dense:
        raise ValueError(f"{source}: randomised tables are scored on dense models only (S = {S})")
    learned = scorer.metrics(policy) if policy.ndim == 1 else stationary_metrics(model, policy)
    opt = scorer.optimal_metrics
    rows: dict[str, Metrics] = {f"{name} (exact, long run)": learned}
    errs: dict[str, dict[str, float]] = {}
    if dense:
        rows[f"{name} (exact, episodic)"] = episodic_metrics(model, policy)
    if int(cfg.eval.mc_episodes):
        env = DFRCEnv(params, batch_size=[int(cfg.eval.mc_num_envs)], seed=int(cfg.seed))
        pol = table_policy(policy, seed=int(cfg.seed))
        ev = evaluate(pol, env, episodes=int(cfg.eval.mc_episodes))
        label = f"{name} (Monte-Carlo, episodic)"
        rows[label], errs[label] = ev.metrics, ev.ci95
    rows["optimal (exact, long run)"] = opt
    if dense:
        rows["optimal (exact, episodic)"] = episodic_metrics(model, scorer.optimal.policy)
        rows["round_robin (exact, long run)"] = stationary_metrics(model, "round_robin")
    ratio = learned.avg_reward / opt.avg_reward
    wall = time.perf_counter() - t0

    print(f"scenario={scenario} (S = {S}): {source}\n")
    print(format_table(rows, errors=errs))
    print(
        "long run: the policy's stationary average; episodic: episodes of "
        f"{params.env.horizon} steps from a uniform reset, as the Monte-Carlo row samples"
    )
    print(f"\n{name}: {ratio:.4f} of this scenario's optimum (average reward, exact)")
    if policy.ndim == 1 and dense:
        print(policy_differences(model, policy, scorer.optimal.policy))
    out = Path(out)
    summary = summary_dict(
        method="evaluate",
        scenario=scenario,
        seed=int(cfg.seed),
        env_steps=0,
        wall_seconds=wall,
        metrics=learned,
        optimal=opt,
        source=source,
        states_differing_from_optimum=(
            int((policy != scorer.optimal.policy).sum()) if policy.ndim == 1 else None
        ),
        table=table_dict(rows, errs),
    )
    write_summary(out / "summary.json", summary)
    write_policy_csv(out / "policy.csv", policy, params.env.levels)
    print(f"\nwrote summary.json and policy.csv to {out}")
    return summary
