"""What the fleet's learners share (``irdrc.agents.marl``, ``irdrc.agents.mappo``): a vehicle's
index in its network's input, the size of its observation, and the greedy tables an evaluation
scores."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from irdrc.fleet.env import GROUP, FleetEnv, fleet_observation, fleet_observation_high


class AgentIndex(nn.Module):
    """Appends each agent's one-hot index to its observation ([..., N, W] → [..., N, W + N])."""

    eye: torch.Tensor

    def __init__(self, n_agents: int) -> None:
        super().__init__()
        self.register_buffer("eye", torch.eye(n_agents))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x, self.eye.expand(*x.shape[:-1], self.eye.shape[0])], -1)


def observation_top(env: FleetEnv) -> torch.Tensor:
    """[W] the largest value of each entry of a vehicle's observation."""
    return fleet_observation_high(env.model.spec.vehicle, env.n_agents, env.observe).float()


def greedy_policy(qnet: TensorDictModule, env: FleetEnv) -> torch.Tensor:
    """The vehicles' greedy policy (a Q-network's greedy actions, an actor's most likely) as
    ``FleetScorer`` reads it: with ``own`` observations each
    vehicle's action in every single-vehicle state ([N·S], vehicle-major); with ``full``
    observations the joint action of every joint state ([S_fleet])."""
    n, model = env.n_agents, env.model
    if env.observe == "own":
        states = torch.arange(model.single.num_states)[:, None].expand(-1, n)
    else:
        states = model.vehicle_states()
    obs = fleet_observation(env.sim.dyn.obs[states], env.own, env.observe)  # [rows, N, W]
    td = TensorDict({GROUP: TensorDict({"observation": obs}, list(obs.shape[:2]))}, [len(obs)])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        action = qnet(td).get((GROUP, "action")).long().cpu()  # [rows, N]
    if env.observe == "own":
        return action.T.reshape(-1)
    return (action << torch.arange(n)).sum(1)
