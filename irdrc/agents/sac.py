"""SAC from TorchRL parts on the radar share ρ ∈ [0, 1] (MODEL.md § D), learning from many env rows
at once on the off-policy loop every learner shares — top to bottom in TorchRL's component order:
model (actor, critics) → exploration (the actor's own sampling) → collector → buffer → loss → target
→ optimiser → logger (the caller's hooks) → loop.

The actor is a ``TanhNormal`` on [−m, 1 + m] through ``ProbabilisticActor`` (``SHARE_MARGIN``),
its shares clipped to [0, 1]; the rows explore beside it on DQN's ε ladder, replay is prioritised
by the critics' TD error, and the policy is the Polyak-averaged actor. Every evaluation scores its
deterministic share in every state *exactly* against the continuum's optimum
(``irdrc.core.exact.continuum.ContinuumScorer``), which only scores, never steers.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss

from irdrc.agents.base import Hooks, RunContext, RunRecord
from irdrc.agents.configs.continuous import SACConfig
from irdrc.agents.loop import Learner, TrainingLoop
from irdrc.agents.offpolicy import (
    CenteredRewards,
    PolyakUpdate,
    RewardCenter,
    clip_and_step,
    make_body,
    make_buffer,
    make_collector,
    make_optimizer,
    observation_top,
)
from irdrc.agents.shares import Critic, ShareLadder, share_run, share_table
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params

SHARE_MARGIN = 0.1
"""The actor's TanhNormal spans [−m, 1 + m], and its shares are clipped to [0, 1] (by the
collector's ``ShareLadder``, at the critics' input, in ``share_table``). The shares 0 and 1 —
radar the whole step, where the optimum of the riskiest states lies — are then reached at
tanh ≈ ±0.83; on [0, 1] itself only in tanh's saturation, out of which the squashed entropy's
Jacobian pushes the actor. A checkpoint records its margin (``share_margin``; a checkpoint
without one spanned [0, 1])."""


def make_actor(env: DFRCEnv, cfg: SACConfig, margin: float = SHARE_MARGIN) -> ProbabilisticActor:
    """Scaled observation → MLP → (loc, scale) → TanhNormal on [−margin, 1 + margin]."""
    net = nn.Sequential(make_body(observation_top(env), cfg.network, 2), NormalParamExtractor())
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        spec=env.action_spec_unbatched,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -margin, "high": 1.0 + margin},
        default_interaction_type=ExplorationType.RANDOM,
    )


def make_critic(env: DFRCEnv, cfg: SACConfig) -> ValueOperator:
    """Q(observation, ρ): the scaled observation and the share → an MLP → one value."""
    return ValueOperator(
        Critic(observation_top(env), cfg.network), in_keys=["observation", "action"]
    )


def make_loss(actor: ProbabilisticActor, critic: ValueOperator, cfg: SACConfig) -> SACLoss:
    """SAC with two critics, target networks of both critics and the actor, a tuned temperature."""
    loss = SACLoss(
        actor,
        critic,
        num_qvalue_nets=2,
        loss_function="l2",
        delay_qvalue=True,
        delay_actor=True,
        alpha_init=cfg.temperature_init,
        target_entropy=cfg.target_entropy,
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    return loss


def policy_shares(loss: SACLoss, actor: ProbabilisticActor, env: DFRCEnv) -> torch.Tensor:
    """The policy's share in every state [S]: the Polyak-averaged actor's (one noisy update moves
    it little), deterministic."""
    with loss.target_actor_network_params.to_module(actor):
        return share_table(actor, env)


def saved_shares(
    state: dict[str, Any], cfg: SACConfig, trained: Params, params: Params
) -> torch.Tensor:
    """The shares [S] of a checkpoint's policy (``state``, trained on ``trained`` with ``cfg``) on
    the states of ``params``: its networks rebuilt with its margin and loaded."""
    train_env = DFRCEnv(trained, batch_size=[1])
    actor = make_actor(train_env, cfg, checkpoint_margin(state))
    loss = make_loss(actor, make_critic(train_env, cfg), cfg)
    loss.load_state_dict(state["loss"])
    return policy_shares(loss, actor, DFRCEnv(params, batch_size=[1]))


def checkpoint_margin(state: dict[str, Any] | None) -> float:
    """The actor's margin a run goes on with: a fresh run's ``SHARE_MARGIN``, a checkpoint's own
    (0 where it has none: its actor spanned [0, 1])."""
    return SHARE_MARGIN if state is None else float(state.get("share_margin", 0.0))


def train(
    params: Params,
    cfg: SACConfig | None = None,
    *,
    seed: int = 0,
    device: str = "cpu",
    scorer: Any = None,
    eval_every_frames: int = 40_000,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train SAC on ``params`` (``env.actions=continuous``) and evaluate the actor's deterministic
    shares exactly every ``eval_every_frames`` env steps.

    Returns:
        The run's record: ``greedy`` [1, S] the final shares (float64), ``state`` the checkpoint.
    """
    cfg = cfg or SACConfig()
    env, scorer, start = share_run(
        params, cfg, seed=seed, device=device, scorer=scorer, resume=resume
    )

    # 1. model: the actor (TanhNormal on [−m, 1 + m], clipped) and a critic Q(observation, ρ)
    margin = checkpoint_margin(resume)
    actor = make_actor(env, cfg, margin)
    critic = make_critic(env, cfg)
    # 2. exploration: the actor samples its own shares, and an ε ladder over the rows
    ladder = ShareLadder(cfg.num_envs, cfg.eps_max, cfg.eps_min)
    explore = TensorDictModule(ladder, in_keys=["action"], out_keys=["action"])
    # 3. collector: every row steps with the actor and its own exploration
    collector = make_collector(env, TensorDictSequential(actor, explore), cfg, seed, start)
    # 4. buffer: prioritised replay of the whole run, every sample's rewards centred by their
    #    running average (``algo.reward_centering``)
    center = RewardCenter(cfg.reward_centering)
    buffer, sampler = make_buffer(cfg, [CenteredRewards(center)])
    # 5. loss: SAC with two critics and a tuned temperature
    loss = make_loss(actor, critic, cfg)
    # 6. target: Polyak averaging of the critics and the actor after every update
    target = PolyakUpdate(loss, tau=cfg.tau)
    # 7. optimiser: one Adam over actor, critics and temperature, annealed by the loop
    optimizer = make_optimizer(loss, cfg)

    # 8. logger: the caller's hooks; 9. the loop, with what this learner supplies
    def update(sample: TensorDictBase) -> float:
        out = loss(sample)
        total = out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]
        value = clip_and_step(loss, optimizer, cfg.max_grad_norm, total)
        target.step()
        if cfg.prioritized:  # SACLoss writes the critics' largest |TD error|
            buffer.update_priority(sample["index"], sample["td_error"].detach().reshape(-1))
        return value

    run = RunContext(scorer, eval_every_frames, hooks, resume)
    loop = TrainingLoop(cfg, collector, buffer, sampler, optimizer, run)

    def policy() -> torch.Tensor:
        return policy_shares(loss, actor, env)

    learner = Learner(
        loss=loss,
        update=update,
        policy=policy,
        collected=lambda data: center.update(data.get(("next", "reward"))),
        state=lambda: {**center.state(), "share_margin": margin},
        load=center.load,
    )
    return loop.run(learner)
