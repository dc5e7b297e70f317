"""Multi-agent PPO on the fleet (MODEL.md § C) from TorchRL parts — ``MAPPOLoss`` with a centralised
critic, or ``IPPOLoss`` with each vehicle's own — on the training loop every learner shares, top to
bottom in TorchRL's component order: model (actor, critic) → exploration (the actor's sampling) →
collector → advantage (``MultiAgentGAE``, inside the loss) → loss → optimiser → loop.

Both act on each vehicle's own observation (decentralised execution) through one shared categorical
actor that also sees the vehicle's one-hot index, so the vehicles may take different roles; both
learn from the team reward (``FleetEnv(reward="team")``). MAPPO's critic values the fleet from the
root ``state`` (every vehicle's d, c, v, m and the shared r, w) with the vehicle's index; IPPO's
from the vehicle's own observation. Every evaluation scores the vehicles' greedy tables exactly
against the centralised optimum (or by Monte-Carlo beyond the exact model).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor
from torchrl.objectives.multiagent import IPPOLoss, MAPPOLoss

from irdrc.agents.base import RunContext, RunRecord
from irdrc.agents.configs import FleetLearnerConfig
from irdrc.agents.fleet_parts import AgentIndex, greedy_policy, observation_top
from irdrc.agents.loop import Learner, TrainingLoop, start_frames
from irdrc.agents.offpolicy import RewardCenter, make_body, make_collector, make_optimizer
from irdrc.agents.ppo import learn_rollout
from irdrc.fleet.env import GROUP, FleetEnv, critic_state_high
from irdrc.fleet.model import FleetModel


class StatePerAgent(nn.Module):
    """The fleet's ``state`` [..., F] repeated for each of N agents with its one-hot index
    [..., N, F + N]: one centralised value per vehicle from one shared network."""

    def __init__(self, n_agents: int) -> None:
        super().__init__()
        self.index = AgentIndex(n_agents)
        self.n = n_agents

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.index(state.unsqueeze(-2).expand(*state.shape[:-1], self.n, state.shape[-1]))


def make_actor(env: FleetEnv, cfg: FleetLearnerConfig) -> ProbabilisticActor:
    """Each vehicle's observation and index → two logits → a categorical action (and its
    log-probability) under the group key."""
    n, high = env.n_agents, observation_top(env)
    body = make_body(torch.cat([high, torch.ones(n)]), cfg.ppo.network, 2, env.device)
    module = TensorDictModule(
        nn.Sequential(AgentIndex(n), body),
        in_keys=[(GROUP, "observation")],
        out_keys=[(GROUP, "logits")],
    )
    return ProbabilisticActor(
        module,
        in_keys={"logits": (GROUP, "logits")},
        out_keys=[(GROUP, "action")],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
        log_prob_key=(GROUP, "action_log_prob"),
        default_interaction_type=ExplorationType.RANDOM,
    )


def make_critic(env: FleetEnv, cfg: FleetLearnerConfig) -> TensorDictModule:
    """MAPPO: the fleet's ``state`` and the vehicle's index → its value; IPPO: the vehicle's own
    observation and index → its value. Writes ``(GROUP, "state_value")`` [..., N, 1]."""
    n, net = env.n_agents, cfg.ppo.network
    if cfg.learner == "mappo":
        high = critic_state_high(env.model.spec.vehicle, n).float()
        body = make_body(torch.cat([high, torch.ones(n)]), net, 1, env.device)
        return TensorDictModule(
            nn.Sequential(StatePerAgent(n), body),
            in_keys=["state"],
            out_keys=[(GROUP, "state_value")],
        )
    high = observation_top(env)
    body = make_body(torch.cat([high, torch.ones(n)]), net, 1, env.device)
    return TensorDictModule(
        nn.Sequential(AgentIndex(n), body),
        in_keys=[(GROUP, "observation")],
        out_keys=[(GROUP, "state_value")],
    )


def team_reward(data: TensorDictBase) -> TensorDictBase:
    """The team reward at the root as well (every vehicle's is the fleet's: ``reward="team"``),
    where the loop tracks episodes."""
    data.set(("next", "reward"), data.get(("next", GROUP, "reward"))[..., 0, :])
    return data


def train_ppo(
    model: FleetModel, cfg: FleetLearnerConfig, run: RunContext, *, observe: str, seed: int
) -> RunRecord:
    """MAPPO or IPPO (``cfg.learner``) on ``cfg.ppo.num_envs`` fleets."""
    pc = cfg.ppo
    torch.manual_seed(seed)
    env = FleetEnv(model, batch_size=pc.num_envs, seed=seed, observe=observe, reward="team")
    start = start_frames(run.resume)
    # 1. model: one actor all vehicles share, and the critic
    actor, critic = make_actor(env, cfg), make_critic(env, cfg)
    # 2. exploration: the actor's own sampling; 3. collector: one rollout of every fleet a batch
    collector = make_collector(env, actor, pc, seed, start)
    # 4–5. loss: the clipped surrogate of every vehicle, the critic's regression on GAE's targets
    #      (MultiAgentGAE: the fleet's done flags broadcast over the vehicles), the entropy bonus
    loss_class = MAPPOLoss if cfg.learner == "mappo" else IPPOLoss
    loss = loss_class(
        actor,
        critic,
        clip_epsilon=pc.clip_epsilon,
        entropy_coeff=pc.entropy_coeff,
        critic_coeff=pc.critic_coeff,
        loss_critic_type="l2",
    )
    loss.set_keys(
        action=(GROUP, "action"),
        sample_log_prob=(GROUP, "action_log_prob"),
        value=(GROUP, "state_value"),
        reward=(GROUP, "reward"),
        done="done",
        terminated="terminated",
    )
    loss.make_value_estimator(gamma=pc.gamma, lmbda=pc.gae_lambda)
    # 6. optimiser: one Adam over actor and critic, annealed by the loop
    optimizer = make_optimizer(loss, pc)

    # each rollout's team rewards centred by their running average (``ppo.reward_centering``)
    key = ("next", GROUP, "reward")
    center = RewardCenter(pc.reward_centering)

    def learn_batch(data: TensorDictBase) -> tuple[int, float]:
        data = center.center(data, key)
        with torch.no_grad():
            loss.value_estimator(data)
        return learn_rollout(loss, optimizer, pc, data)

    loop = TrainingLoop(pc, collector, None, None, optimizer, run, prepare=team_reward)
    learner = Learner(
        loss=loss,
        update=None,
        policy=lambda: greedy_policy(actor, env),
        learn_batch=learn_batch,
        collected=lambda data: center.update(data.get(key)),
        state=center.state,
        load=center.load,
    )
    return loop.run(learner)
