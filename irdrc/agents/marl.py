"""The fleet's learners (MODEL.md § C), on the same parts and loop as DQN, every env step a fleet
step (one step of every vehicle of a fleet), every policy scored against the centralised optimum:

- ``idqn``: independent DQN with parameter sharing — each vehicle's step is a row of DQN's batched
  learner (``FleetRowsEnv``) with the team reward and the vehicle's index in its observation;
- ``vdn`` / ``qmix``: value decomposition — one shared agent network acts on each vehicle's own
  observation (decentralised execution), TorchRL's ``QMixerLoss`` mixes the vehicles' chosen values
  into the fleet's (``VDNMixer`` sums them, ``QMixer`` mixes them monotonically from the fleet's
  observations) and regresses that on the team reward;
- ``joint``: DQN over the 2^N joint actions on every vehicle's state (``FleetJointEnv``): one
  network every vehicle executes alike, taking its own bit;
- ``mappo`` / ``ippo``: multi-agent PPO (``irdrc.agents.mappo``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import QValueModule
from torchrl.modules.models.multiagent import QMixer, VDNMixer
from torchrl.objectives.multiagent import QMixerLoss

from irdrc.agents import dqn
from irdrc.agents.base import Hooks, RunContext, RunRecord
from irdrc.agents.configs import (
    MIXERS,
    POLICY_GRADIENT,
    FleetLearnerConfig,
    OffPolicyConfig,
    check_fleet_learner,
)
from irdrc.agents.fleet_parts import AgentIndex, greedy_policy, observation_top
from irdrc.agents.loop import Learner, TrainingLoop, start_frames
from irdrc.agents.mappo import train_ppo
from irdrc.agents.offpolicy import (
    CenteredRewards,
    LadderExploration,
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
from irdrc.fleet.env import GROUP, FleetEnv
from irdrc.fleet.model import FleetModel
from irdrc.fleet.views import FleetJointEnv, FleetRowsEnv

MIXER_KEYS = (
    (GROUP, "observation"),
    (GROUP, "action"),
    ("next", GROUP, "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)
"""What a fleet transition keeps in replay for the mixers: every vehicle's observation and action,
the team reward and the fleet's done flags."""


def train(
    model: FleetModel,
    cfg: FleetLearnerConfig,
    *,
    observe: str = "own",
    seed: int = 0,
    scorer: Any,
    eval_every_frames: int = 50_000,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train ``cfg.learner`` on the fleet ``model``; its history and env steps count fleet steps.
    ``scorer``: ``irdrc.fleet.scorer.FleetScorer`` (exact, against the centralised optimum) or
    ``irdrc.fleet.evaluate.FleetMCScorer``; ``resume``: a checkpoint of the same learner."""
    check_fleet_learner(cfg.learner, model, observe)
    run = RunContext(scorer, eval_every_frames, hooks, resume)
    if cfg.learner in MIXERS:
        return train_mixer(model, cfg, run, observe=observe, seed=seed)
    if cfg.learner in POLICY_GRADIENT:
        return train_ppo(model, cfg, run, observe=observe, seed=seed)
    if cfg.learner == "joint":
        env = FleetJointEnv(model, fleets=cfg.dqn.num_envs, seed=seed)
        return dqn.train(
            env,
            cfg.dqn,
            seed=seed,
            scorer=scorer,
            eval_every_frames=eval_every_frames,
            hooks=hooks,
            resume=resume,
        )
    return train_idqn(model, cfg.dqn, run, seed=seed)


def train_idqn(model: FleetModel, cfg: OffPolicyConfig, run: RunContext, *, seed: int) -> RunRecord:
    """Independent DQN with parameter sharing: a row per vehicle, so N rows per fleet step; the
    hooks and the record count fleet steps (a checkpoint's ``frames`` stay rows)."""
    N, hooks, resume = model.N, run.hooks, run.resume
    rows = replace(
        cfg,
        num_envs=cfg.num_envs * N,
        frames_per_batch=cfg.frames_per_batch * N,
        total_frames=cfg.total_frames * N,
    )

    def per_fleet(record: dict[str, Any]) -> dict[str, Any]:
        return {**record, "env_steps": record["env_steps"] // N}

    checkpoint = hooks.on_checkpoint
    per_fleet_hooks = replace(
        hooks,
        on_eval=lambda records: hooks.eval([per_fleet(r) for r in records]),
        on_batch=lambda info: hooks.batch(per_fleet(info)),
        on_checkpoint=(lambda state: checkpoint(fleet_state(state, N))) if checkpoint else None,
        checkpoint_every_frames=hooks.checkpoint_every_frames * N,
    )
    env = FleetRowsEnv(model, fleets=cfg.num_envs, seed=seed, agent_index=True)
    record = dqn.train(
        env,
        replace(rows, name="idqn"),
        seed=seed,
        scorer=run.scorer,
        eval_every_frames=run.eval_every_frames * N,
        hooks=per_fleet_hooks,
        resume=rows_state(resume, N) if resume is not None else None,
    )
    record.history = [per_fleet(r) for r in record.history]
    record.env_steps //= N
    if record.state is not None:
        record.state = fleet_state(record.state, N)
    return record


def fleet_state(state: dict[str, Any], n: int) -> dict[str, Any]:
    """A checkpoint of independent DQN's rows with its history in fleet steps, and ``env_steps``
    (what a resumed run counts) beside ``frames`` (what the loop counts: rows)."""
    history = [{**r, "env_steps": r["env_steps"] // n} for r in state["history"]]
    return {**state, "history": history, "env_steps": state["frames"] // n}


def rows_state(state: dict[str, Any], n: int) -> dict[str, Any]:
    """``fleet_state`` undone: the checkpoint as the loop over the rows counts it."""
    history = [{**r, "env_steps": r["env_steps"] * n} for r in state["history"]]
    return {**state, "history": history}


# -- value decomposition ---------------------------------------------------------------------------


class FleetState(nn.Module):
    """The mixer's state: every vehicle's scaled observation, flattened ([..., N, W] → [..., N·W])."""

    def __init__(self, high: torch.Tensor) -> None:
        super().__init__()
        self.scale = Scale(high)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.scale(obs).flatten(-2)


def make_agent_qnet(env: FleetEnv, cfg: FleetLearnerConfig) -> TensorDictSequential:
    """The shared agent network: each vehicle's observation (and index) → its two action values,
    greedy action and chosen value under the group key."""
    high, n, net = observation_top(env), env.n_agents, cfg.dqn.network
    if cfg.agent_index:
        body = make_body(torch.cat([high, torch.ones(n)]), net, 2, env.device)
        body = nn.Sequential(AgentIndex(n), body)
    else:
        body = make_body(high, net, 2, env.device)
    values = TensorDictModule(
        body, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "action_value")]
    )
    greedy = QValueModule(
        action_value_key=(GROUP, "action_value"),
        out_keys=[(GROUP, "action"), (GROUP, "action_value"), (GROUP, "chosen_action_value")],
        action_space="categorical",
    )
    return TensorDictSequential(values, greedy)


def make_mixer(env: FleetEnv, cfg: FleetLearnerConfig) -> TensorDictModule:
    """``VDNMixer`` or ``QMixer`` (its state: the fleet's observations) as a TensorDict module
    writing the fleet's ``chosen_action_value``."""
    n = env.n_agents
    if cfg.learner == "vdn":
        return TensorDictModule(
            VDNMixer(n_agents=n, device=env.device),
            in_keys=[(GROUP, "chosen_action_value")],
            out_keys=["chosen_action_value"],
        )
    high = observation_top(env)
    state = TensorDictModule(
        FleetState(high), in_keys=[(GROUP, "observation")], out_keys=["mixer_state"]
    )
    mixer = TensorDictModule(
        QMixer(
            state_shape=(n * high.shape[0],),
            mixing_embed_dim=cfg.mixing_embed_dim,
            n_agents=n,
            device=env.device,
        ),
        in_keys=[(GROUP, "chosen_action_value"), "mixer_state"],
        out_keys=["chosen_action_value"],
    )
    return TensorDictSequential(state, mixer)


def team_reward(data: TensorDictBase) -> TensorDictBase:
    """The fleet's reward at the root: the sum of its vehicles' (``QMixerLoss`` regresses the mixed
    value on it)."""
    data.set(("next", "reward"), data.get(("next", GROUP, "reward")).sum(-2))
    return data


def make_loss(
    qnet: TensorDictSequential, mixer: TensorDictModule, dq: OffPolicyConfig
) -> tuple[QMixerLoss, PolyakUpdate]:
    """TorchRL's ``QMixerLoss`` (squared TD error of the mixed value against the team reward, the
    target network's maxima) and its Polyak target update."""
    loss = QMixerLoss(qnet, mixer, loss_function="l2", delay_value=True, action_space="categorical")
    loss.make_value_estimator(gamma=dq.gamma)
    return loss, PolyakUpdate(loss, tau=dq.tau)


def train_mixer(
    model: FleetModel, cfg: FleetLearnerConfig, run: RunContext, *, observe: str, seed: int
) -> RunRecord:
    """VDN or QMIX (``cfg.learner``) on ``cfg.dqn.num_envs`` fleets, in DQN's component order."""
    dq = cfg.dqn
    torch.manual_seed(seed)
    env = FleetEnv(model, batch_size=dq.num_envs, seed=seed, observe=observe)
    resume = run.resume
    start = start_frames(resume)
    qnet, mixer = make_agent_qnet(env, cfg), make_mixer(env, cfg)  # the model: agents and mixer
    exploration = LadderExploration(
        eps_ladder(dq.num_envs, dq.eps_max, dq.eps_min),
        dq.eps_duration_max,
        2,
        action_key=(GROUP, "action"),
    )
    collector = make_collector(env, TensorDictSequential(qnet, exploration), dq, seed, start)
    # the team reward (at the root, ``team_reward``), centred by its running average
    center = RewardCenter(dq.reward_centering)
    buffer, sampler = make_buffer(dq, [CenteredRewards(center)])
    loss, target = make_loss(qnet, mixer, dq)
    optimizer = make_optimizer(loss, dq)

    def update(sample: TensorDictBase) -> float:
        value = clip_and_step(loss, optimizer, dq.max_grad_norm, loss(sample)["loss"])
        target.step()
        return value

    def policy() -> torch.Tensor:
        with loss.target_local_value_network_params.to_module(loss.local_value_network):
            return greedy_policy(qnet, env)

    loop = TrainingLoop(
        dq, collector, buffer, sampler, optimizer, run, keys=MIXER_KEYS, prepare=team_reward
    )
    learner = Learner(
        loss=loss,
        update=update,
        policy=policy,
        collected=lambda data: center.update(data.get(("next", "reward"))),
        state=center.state,
        load=center.load,
    )
    return loop.run(learner)
