"""Value decomposition on the fleet (MODEL.md § C): VDN and QMIX from TorchRL parts.

Every vehicle acts on its own observation with one shared agent network (decentralised execution;
with ``agent_index`` the network also sees the vehicle's one-hot index, so vehicles may act
differently in the same local state). Training is centralised: TorchRL's ``QMixerLoss`` mixes the
vehicles' chosen action values into the fleet's — ``VDNMixer`` sums them, ``QMixer`` mixes them
monotonically with weights from the fleet's observations — and regresses that on the team reward
(the sum of the vehicles' rewards). Collection, replay and updates are the off-policy machinery
every value learner shares (``irdrc.agents.offpolicy``) over ``FleetEnv``'s batched fleets, one
row per fleet, each with its rate on the ε ladder. The decentralised policy — each vehicle's greedy
table over its single-vehicle states — is scored exactly against the centralised optimum
(``irdrc.agents.fleet_dqn.FleetScorer``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import QValueModule
from torchrl.modules.models.multiagent import QMixer, VDNMixer
from torchrl.objectives.multiagent import QMixerLoss

from irdrc.agents.base import Hooks, RunRecord, progress_record
from irdrc.agents.fleet_dqn import FleetScorer
from irdrc.agents.offpolicy import (
    LadderExploration,
    OffPolicyConfig,
    OffPolicyLoop,
    PolyakUpdate,
    RewardCenter,
    Scale,
    clip_and_step,
    eps_ladder,
    make_body,
    make_buffer,
    make_collector,
    make_optimizer,
)
from irdrc.core.params import check_bool, check_choice, check_number
from irdrc.fleet.env import GROUP, FleetEnv, fleet_observation, fleet_observation_high
from irdrc.fleet.exact import FleetModel, FleetSpec

MIXERS = ("vdn", "qmix")

STORED_KEYS = (
    (GROUP, "observation"),
    (GROUP, "action"),
    ("next", GROUP, "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)
"""What a fleet transition keeps in replay: every vehicle's observation and action, the team
reward and the fleet's done flags."""


@dataclass(frozen=True)
class MixConfig(OffPolicyConfig):
    """The value-decomposition learner's hyperparameters: the off-policy machinery's
    (``OffPolicyConfig``; ``num_envs`` counts fleets, env steps count fleet steps) and

    Attributes:
        mixer: ``vdn`` (the sum) or ``qmix`` (a monotonic hyper-network mixer).
        mixing_embed_dim: QMIX's mixing width.
        agent_index: each vehicle's network input carries its one-hot index.
    """

    mixer: str = "vdn"
    mixing_embed_dim: int = 32
    agent_index: bool = True
    double_dqn: bool = False
    prioritized: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("algo.mixer", self.mixer, MIXERS)
        object.__setattr__(
            self,
            "mixing_embed_dim",
            check_number("algo.mixing_embed_dim", self.mixing_embed_dim, 1, 4096, integer=True),
        )
        check_bool("algo.agent_index", self.agent_index)
        if self.double_dqn:
            raise ValueError(
                "algo.double_dqn=true: TorchRL's QMixerLoss takes each vehicle's maximum under the "
                "target network (set algo.double_dqn=false)"
            )
        if self.prioritized:
            raise ValueError(
                "algo.prioritized=true: TorchRL's QMixerLoss does not weigh samples by their "
                "importance, and prioritised replay without that correction biases the values "
                "(docs/FLEET.md); set algo.prioritized=false"
            )
        if self.target_update != "soft":
            raise ValueError(f"algo.target_update={self.target_update!r}: only soft is supported")
        if self.frames_per_batch % self.num_envs:
            raise ValueError(
                f"algo.frames_per_batch={self.frames_per_batch} must be a multiple of "
                f"algo.num_envs={self.num_envs} (fleets stepped together)"
            )


class AgentIndex(nn.Module):
    """Appends each agent's one-hot index to its observation ([..., N, W] → [..., N, W + N])."""

    def __init__(self, n_agents: int) -> None:
        super().__init__()
        self.register_buffer("eye", torch.eye(n_agents))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x, self.eye.expand(*x.shape[:-1], self.eye.shape[0])], -1)


class FleetState(nn.Module):
    """The mixer's state: every vehicle's scaled observation, flattened ([..., N, W] → [..., N·W])."""

    def __init__(self, high: torch.Tensor) -> None:
        super().__init__()
        self.scale = Scale(high)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.scale(obs).flatten(-2)


def observation_top(env: FleetEnv) -> torch.Tensor:
    """[W] the largest value of each entry of a vehicle's observation."""
    return fleet_observation_high(env.model.spec.vehicle, env.n_agents, env.observe).float()


def make_agent_qnet(env: FleetEnv, cfg: MixConfig) -> TensorDictSequential:
    """The shared agent network: each vehicle's observation (and index) → its two action values,
    greedy action and chosen value under the group key."""
    high = observation_top(env)
    n = env.n_agents
    if cfg.agent_index:
        body = make_body(torch.cat([high, torch.ones(n)]), cfg.network, 2, env.device)
        body = nn.Sequential(AgentIndex(n), body)
    else:
        body = make_body(high, cfg.network, 2, env.device)
    values = TensorDictModule(
        body, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "action_value")]
    )
    greedy = QValueModule(
        action_value_key=(GROUP, "action_value"),
        out_keys=[(GROUP, "action"), (GROUP, "action_value"), (GROUP, "chosen_action_value")],
        action_space="categorical",
    )
    return TensorDictSequential(values, greedy)


def make_mixer(env: FleetEnv, cfg: MixConfig) -> TensorDictModule:
    """``VDNMixer`` or ``QMixer`` (its state: the fleet's observations) as a TensorDict module
    writing the fleet's ``chosen_action_value``."""
    n = env.n_agents
    if cfg.mixer == "vdn":
        return TensorDictModule(
            VDNMixer(n_agents=n, device=env.device),
            in_keys=[(GROUP, "chosen_action_value")],
            out_keys=["chosen_action_value"],
        )
    high = observation_top(env)
    state = TensorDictModule(
        FleetState(high), in_keys=[(GROUP, "observation")], out_keys=["mixer_state"]
    )
    width = n * high.shape[0]
    mixer = TensorDictModule(
        QMixer(
            state_shape=(width,),
            mixing_embed_dim=cfg.mixing_embed_dim,
            n_agents=n,
            device=env.device,
        ),
        in_keys=[(GROUP, "chosen_action_value"), "mixer_state"],
        out_keys=["chosen_action_value"],
    )
    return TensorDictSequential(state, mixer)


def make_loss(qnet: TensorDictSequential, mixer: TensorDictModule, cfg: MixConfig) -> QMixerLoss:
    """TorchRL's ``QMixerLoss`` with target networks and TD(0) at γ (n-step transitions
    discounted by γ^n)."""
    loss = QMixerLoss(
        qnet, mixer, loss_function=cfg.loss_function, delay_value=True, action_space="categorical"
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    return loss


def greedy_policy(qnet: TensorDictSequential, env: FleetEnv) -> torch.Tensor:
    """The vehicles' greedy policy as ``FleetScorer`` reads it: with ``own`` observations each
    vehicle's action in every single-vehicle state ([N·S], vehicle-major); with ``full``
    observations the joint action of every joint state ([S_fleet])."""
    n, model = env.n_agents, env.model
    if env.observe == "own":
        states = torch.arange(model.single.num_states)[:, None].expand(-1, n)
    else:
        states = model.vehicle_states()
    obs = env.sim.dyn.obs[states]  # [rows, N, W]
    obs = fleet_observation(obs, env.own, env.observe)
    td = TensorDict({GROUP: TensorDict({"observation": obs}, list(obs.shape[:2]))}, [len(obs)])
    with torch.no_grad():
        action = qnet(td).get((GROUP, "action")).long().cpu()  # [rows, N]
    if env.observe == "own":
        return action.T.reshape(-1)
    return (action << torch.arange(n)).sum(1)


def team_reward(data: TensorDictBase) -> TensorDictBase:
    """The fleet's reward at the root: the sum of its vehicles' (``QMixerLoss`` regresses the mixed
    value on it)."""
    data.set(("next", "reward"), data.get(("next", GROUP, "reward")).sum(-2))
    return data


def train(
    spec: FleetSpec | FleetModel,
    cfg: MixConfig | None = None,
    *,
    seed: int = 0,
    scorer: FleetScorer | None = None,
    eval_every_frames: int = 25_000,
    hooks: Hooks | None = None,
    observe: str = "own",
) -> RunRecord:
    """Train VDN or QMIX (``cfg.mixer``) on ``cfg.num_envs`` fleets for ``cfg.total_frames``
    fleet steps, each vehicle observing ``observe`` (``irdrc.fleet.env.OBSERVE``), evaluating the
    vehicles' greedy policy exactly every ``eval_every_frames``.

    The record's ``greedy`` is [1, ·] (``greedy_policy``); its history counts fleet steps.
    """
    cfg = cfg or MixConfig()
    hooks = hooks or Hooks()
    if eval_every_frames < 1:
        raise ValueError(f"eval.every_frames={eval_every_frames!r} must be >= 1")
    model = spec if isinstance(spec, FleetModel) else FleetModel(spec)
    scorer = scorer or FleetScorer(model)
    torch.manual_seed(seed)
    env = FleetEnv(model, batch_size=cfg.num_envs, seed=seed, observe=observe)

    # Components in a fixed order: model → exploration → buffer → loss → target → optimiser.
    qnet = make_agent_qnet(env, cfg)
    exploration = LadderExploration(
        eps_ladder(cfg.num_envs, cfg.eps_max, cfg.eps_min),
        cfg.eps_duration_max,
        2,
        action_key=(GROUP, "action"),
    )
    buffer, sampler = make_buffer(cfg)
    loss = make_loss(qnet, make_mixer(env, cfg), cfg)
    target = PolyakUpdate(loss, tau=cfg.tau)
    optimizer = make_optimizer(loss, cfg)
    record = RunRecord(method=cfg.mixer, greedy=torch.zeros(1, 1, dtype=torch.int64))
    record.info["replay_sampler"] = type(sampler).__name__
    hooks.start(dict(record.info))
    center = RewardCenter(cfg.reward_centering, cfg.gamma)
    collector = make_collector(
        env, TensorDictSequential(qnet, exploration), cfg, cfg.total_frames, seed
    )
    loop = OffPolicyLoop(
        cfg,
        collector,
        buffer,
        sampler,
        optimizer,
        center,
        record,
        hooks,
        keys=STORED_KEYS,
        prepare=team_reward,
    )

    def update(sample: TensorDictBase) -> float:
        out = loss(sample)
        value = clip_and_step(loss, optimizer, cfg.max_grad_norm, out["loss"])
        target.step()
        return value

    t0 = time.perf_counter()
    optimal = scorer.optimal_metrics.avg_reward

    def policy() -> torch.Tensor:
        with loss.target_local_value_network_params.to_module(loss.local_value_network):
            return greedy_policy(qnet, env)

    def evaluate_now() -> None:
        m = scorer.metrics(policy())
        wall = time.perf_counter() - t0
        entry = progress_record(
            0, loop.frames, len(record.episode_rewards), wall, loop.updates, m, optimal
        )
        record.history.append(entry)
        hooks.eval([entry])

    evaluate_now()
    next_eval = eval_every_frames
    for _ in loop.batches():
        loop.learn(update)
        hooks.batch(loop.scalars())
        stop = loop.stop_due()
        if loop.frames >= next_eval or loop.frames >= cfg.total_frames or stop:
            evaluate_now()
            next_eval = (loop.frames // eval_every_frames + 1) * eval_every_frames
        if stop:
            record.interrupted = True
            break
    loop.shutdown()
    record.env_steps = loop.frames
    record.episodes = len(record.episode_rewards)
    record.greedy = policy()[None]
    record.wall_seconds = time.perf_counter() - t0
    record.state = {"loss": loss.state_dict(), "frames": loop.frames, "updates": loop.updates}
    return record


def config_keys() -> set[str]:
    """Every ``algo.*`` key this learner reads."""
    return MixConfig.keys()
