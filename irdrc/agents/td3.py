"""TD3 from TorchRL parts on the radar share ρ ∈ [0, 1] (MODEL.md § D), on the off-policy loop
every learner shares — top to bottom in TorchRL's component order: model (a deterministic actor,
two critics) → exploration (Gaussian noise, and DQN's ε ladder over the rows) → collector → buffer
→ loss → target → optimiser → logger (the caller's hooks) → loop.

Every evaluation scores the Polyak-averaged actor's share in every state *exactly* against the
continuum's optimum (``irdrc.core.exact.continuum.ContinuumScorer``).
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import Actor, ValueOperator
from torchrl.objectives import TD3Loss

from irdrc.agents.base import Hooks, RunContext, RunRecord
from irdrc.agents.configs.continuous import TD3Config
from irdrc.agents.loop import Learner, OffPolicyLoop, start_frames
from irdrc.agents.offpolicy import (
    PolyakUpdate,
    clip_and_step,
    make_body,
    make_buffer,
    make_collector,
    make_optimizer,
    observation_top,
)
from irdrc.agents.shares import Critic, ShareLadder, share_table
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params


def train(
    params: Params,
    cfg: TD3Config | None = None,
    *,
    seed: int = 0,
    device: str = "cpu",
    scorer: Any = None,
    eval_every_frames: int = 40_000,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train TD3 on ``params`` (``env.actions=continuous``); evaluate the actor's shares exactly
    every ``eval_every_frames`` env steps. Returns the record (``greedy`` [1, S] the shares)."""
    if params.env.actions != "continuous":
        raise ValueError(
            f"TD3 acts on radar shares: env.actions=continuous (got {params.env.actions})"
        )
    cfg = cfg or TD3Config()
    torch.manual_seed(seed)
    env = DFRCEnv(params, batch_size=[cfg.num_envs], device=device, seed=seed)
    if scorer is None:
        from irdrc.core.exact.continuum import ContinuumScorer

        scorer = ContinuumScorer(params)
    start = start_frames(resume)
    if start >= cfg.total_frames:
        raise ValueError(f"nothing to resume: the checkpoint is at {start} ≥ algo.total_frames")

    # 1. model: a deterministic actor (a sigmoid onto [0, 1]) and a critic Q(observation, ρ)
    body = nn.Sequential(make_body(observation_top(env), cfg.network, 1), nn.Sigmoid())
    actor = Actor(body, in_keys=["observation"], spec=env.action_spec_unbatched)
    critic = ValueOperator(
        Critic(observation_top(env), cfg.network), in_keys=["observation", "action"]
    )
    # 2. exploration: Gaussian noise on the share, and an ε ladder over the rows
    ladder = ShareLadder(cfg.num_envs, cfg.eps_max, cfg.eps_min, sigma=cfg.sigma)
    explore = TensorDictModule(ladder, in_keys=["action"], out_keys=["action"])
    # 3. collector: every row steps with the actor and its own exploration
    collector = make_collector(env, TensorDictSequential(actor, explore), cfg, seed, start)
    # 4. buffer: prioritised replay of the whole run
    buffer, sampler = make_buffer(cfg)
    # 5. loss: TD3 (two critics, target policy smoothing)
    loss = TD3Loss(
        actor,
        critic,
        action_spec=env.action_spec_unbatched,
        num_qvalue_nets=2,
        policy_noise=cfg.policy_noise,
        noise_clip=cfg.noise_clip,
        loss_function="l2",
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    # 6. target: Polyak averaging of the actor and the critics after each actor update
    target = PolyakUpdate(loss, tau=cfg.tau)
    # 7. optimiser: one Adam over actor and critics, annealed by the loop
    optimizer = make_optimizer(loss, cfg)
    updates = {"n": 0}

    # 8. logger: the caller's hooks; 9. the loop, with what this learner supplies
    def update(sample: TensorDictBase) -> float:
        updates["n"] += 1
        out = loss(sample)
        delayed = updates["n"] % cfg.policy_delay == 0
        total = out["loss_qvalue"] + (out["loss_actor"] if delayed else 0.0)
        value = clip_and_step(loss, optimizer, cfg.max_grad_norm, total)
        if delayed:
            target.step()
        if cfg.prioritized:  # TD3Loss writes the critics' |TD error|
            buffer.update_priority(sample["index"], sample["td_error"].detach().reshape(-1))
        return value

    def policy() -> torch.Tensor:  # the Polyak-averaged actor
        with loss.target_actor_network_params.to_module(actor):
            return share_table(actor, env)

    run = RunContext(scorer, eval_every_frames, hooks, resume)
    loop = OffPolicyLoop(cfg, collector, buffer, sampler, optimizer, run)
    return loop.run(Learner(loss=loss, update=update, policy=policy))
