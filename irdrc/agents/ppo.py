"""PPO from TorchRL parts on the radar share ρ ∈ [0, 1] (MODEL.md § D), learning from many env rows
at once on the training loop every learner shares — top to bottom in TorchRL's component order:
model (actor, critic) → exploration (the actor's own sampling) → collector → advantage (GAE) →
loss (``ClipPPOLoss``) → optimiser → logger (the caller's hooks) → loop.

The actor is a Beta distribution of shares through ``ProbabilisticActor`` (``ShareBeta``: bounded
to [0, 1], its mode the deterministic share); each collection of ``frames_per_batch`` env steps is
one rollout, its rewards centred by the running average reward, its advantages by GAE, then
``epochs`` passes of minibatches. Every evaluation scores the actor's deterministic share in every
state *exactly* against the continuum's optimum, which only scores, never steers.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from irdrc.agents.base import Hooks, RunContext, RunRecord
from irdrc.agents.configs.continuous import PPOConfig
from irdrc.agents.loop import Learner, TrainingLoop
from irdrc.agents.offpolicy import (
    RewardCenter,
    clip_and_step,
    make_body,
    make_collector,
    make_optimizer,
    observation_top,
)
from irdrc.agents.shares import BetaConcentrations, ShareBeta, share_run, share_table
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params


def make_actor(env: DFRCEnv, cfg: PPOConfig) -> ProbabilisticActor:
    """Scaled observation → MLP → (α, β) > 1 → Beta on [0, 1], writing its log-probability."""
    net = nn.Sequential(make_body(observation_top(env), cfg.network, 2), BetaConcentrations())
    module = TensorDictModule(
        net, in_keys=["observation"], out_keys=["concentration1", "concentration0"]
    )
    return ProbabilisticActor(
        module,
        in_keys=["concentration1", "concentration0"],
        spec=env.action_spec_unbatched,
        distribution_class=ShareBeta,
        return_log_prob=True,
        default_interaction_type=ExplorationType.RANDOM,
    )


def make_critic(env: DFRCEnv, cfg: PPOConfig) -> ValueOperator:
    """V(observation): the scaled observation → an MLP → one value."""
    return ValueOperator(make_body(observation_top(env), cfg.network, 1), in_keys=["observation"])


def make_loss(actor: ProbabilisticActor, critic: ValueOperator, cfg: PPOConfig) -> ClipPPOLoss:
    """The clipped surrogate, the critic's regression and the entropy bonus."""
    return ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=cfg.clip_epsilon,
        entropy_coeff=cfg.entropy_coeff,
        critic_coeff=cfg.critic_coeff,
        loss_critic_type="l2",
        normalize_advantage=True,
    )


def saved_shares(
    state: dict[str, Any], cfg: PPOConfig, trained: Params, params: Params
) -> torch.Tensor:
    """The shares [S] of a checkpoint's actor (``state``, trained on ``trained`` with ``cfg``)
    on the states of ``params``: its networks rebuilt and loaded."""
    train_env = DFRCEnv(trained, batch_size=[1])
    actor = make_actor(train_env, cfg)
    make_loss(actor, make_critic(train_env, cfg), cfg).load_state_dict(state["loss"])
    return share_table(actor, DFRCEnv(params, batch_size=[1]))


def learn_rollout(
    loss: Any, optimizer: torch.optim.Optimizer, cfg: Any, data: TensorDictBase
) -> tuple[int, float]:
    """``cfg.epochs`` passes over a rollout whose advantages are in ``data``, in shuffled
    minibatches of ``cfg.batch_size``; returns (updates, the last loss value)."""
    flat = data.reshape(-1)
    updates, value = 0, float("nan")
    for _ in range(cfg.epochs):
        order = torch.randperm(flat.shape[0], device=flat.device)
        for i in range(0, flat.shape[0], cfg.batch_size):
            out = loss(flat[order[i : i + cfg.batch_size]])
            total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
            value = clip_and_step(loss, optimizer, cfg.max_grad_norm, total)
            updates += 1
    return updates, value


def train(
    params: Params,
    cfg: PPOConfig | None = None,
    *,
    seed: int = 0,
    device: str = "cpu",
    scorer: Any = None,
    eval_every_frames: int = 128_000,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train PPO on ``params`` (``env.actions=continuous``) and evaluate the actor's deterministic
    shares exactly every ``eval_every_frames`` env steps.

    Returns:
        The run's record: ``greedy`` [1, S] the final shares (float64), ``state`` the checkpoint.
    """
    cfg = cfg or PPOConfig()
    env, scorer, start = share_run(
        params, cfg, seed=seed, device=device, scorer=scorer, resume=resume
    )

    # 1. model: the actor (Beta on [0, 1]) and a critic V(observation)
    actor = make_actor(env, cfg)
    critic = make_critic(env, cfg)
    # 2. exploration: the actor's own sampling; 3. collector: one rollout per batch
    collector = make_collector(env, actor, cfg, seed, start)
    # 4. advantage: GAE over each rollout (a time limit bootstraps, it does not terminate)
    advantage = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False)
    # 5. loss: the clipped surrogate, the critic's regression and the entropy bonus
    loss = make_loss(actor, critic, cfg)
    # 6. optimiser: one Adam over actor and critic, annealed by the loop
    optimizer = make_optimizer(loss, cfg)

    # 7. logger: the caller's hooks; 8. the loop, with what this learner supplies: each rollout's
    # rewards centred by their running average (``algo.reward_centering``), then GAE and the epochs
    center = RewardCenter(cfg.reward_centering)

    def learn_batch(data: TensorDictBase) -> tuple[int, float]:
        data = center.center(data)
        with torch.no_grad():
            advantage(data)
        return learn_rollout(loss, optimizer, cfg, data)

    run = RunContext(scorer, eval_every_frames, hooks, resume)
    loop = TrainingLoop(cfg, collector, None, None, optimizer, run)
    learner = Learner(
        loss=loss,
        update=None,
        policy=lambda: share_table(actor, env),
        learn_batch=learn_batch,
        collected=lambda data: center.update(data.get(("next", "reward"))),
        state=center.state,
        load=center.load,
    )
    return loop.run(learner)
