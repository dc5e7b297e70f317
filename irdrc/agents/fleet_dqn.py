"""Independent DQN with parameter sharing on the fleet (MODEL.md § C): every vehicle acts with one
shared network on its own observation (decentralised execution), each vehicle's step is a row of
DQN's batched learner (``irdrc.agents.dqn``) with the fleet's team reward, and the decentralised
policy — the network's greedy table over the single-vehicle states, applied by every vehicle — is
scored exactly against the fleet's centralised optimum (``FleetScorer``)."""

from __future__ import annotations

from dataclasses import replace

import torch

from irdrc.agents import dqn
from irdrc.agents.base import Hooks, RunRecord
from irdrc.core.metrics import Metrics
from irdrc.core.solve import DEFAULT_OPTIMUM_GAMMA, ExactScorer
from irdrc.fleet.env import FleetRowsEnv
from irdrc.fleet.exact import (
    FleetModel,
    FleetSpec,
    fleet_metrics,
    joint_policy,
    value_iteration_fleet,
)


class FleetScorer(ExactScorer):
    """``ExactScorer`` for the fleet's decentralised policies, against the centralised optimum:
    a table [S] over the single-vehicle states every vehicle applies to its own state, one such
    table per vehicle [N·S] (vehicle-major), or a joint action per joint state [S_fleet]."""

    def __init__(self, model: FleetModel, gamma: float = DEFAULT_OPTIMUM_GAMMA) -> None:
        self.model = model
        self.fleet_optimum = value_iteration_fleet(model, gamma=gamma)
        self.optimal_metrics = fleet_metrics(model, self.fleet_optimum.policy)[0]
        self._cache = {}

    def _evaluate(self, table: torch.Tensor) -> Metrics:
        return fleet_metrics(self.model, joint_policy(self.model, table))[0]


def train(
    spec: FleetSpec,
    cfg: dqn.DQNConfig | None = None,
    *,
    seed: int = 0,
    scorer: FleetScorer | None = None,
    eval_every_frames: int = dqn.DEFAULT_EVAL_EVERY_FRAMES,
    hooks: Hooks | None = None,
    reward: str = "team",
    agent_index: bool = False,
    model: FleetModel | None = None,
) -> RunRecord:
    """Train the shared network on ``cfg.num_envs`` rows (``cfg.num_envs / N`` fleets); env steps
    count vehicle steps. The record's greedy tables are over the single-vehicle states.
    ``scorer``: ``FleetScorer`` (default) or any scorer of such tables
    (``irdrc.fleet.evaluate.FleetMCScorer``); ``model``: the fleet model built from ``spec``."""
    cfg = cfg or dqn.DQNConfig()
    model = model or (scorer.model if scorer is not None else FleetModel(spec))
    N = model.N
    if cfg.num_envs % N:
        raise ValueError(f"algo.num_envs={cfg.num_envs} must be a multiple of the {N} vehicles")
    env = FleetRowsEnv(
        model, fleets=cfg.num_envs // N, seed=seed, reward=reward, agent_index=agent_index
    )
    scorer = scorer or FleetScorer(model)
    record = dqn.train_on(
        env,
        model.spec.vehicle,
        replace(cfg, name="idqn"),
        seed=seed,
        scorers=[scorer],
        eval_every_frames=eval_every_frames,
        hooks=hooks,
    )
    return record
