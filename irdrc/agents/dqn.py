"""DQN with a reward table, from TorchRL parts, learning from many env rows at once — the main job's
learner, top to bottom in TorchRL's component order: model → exploration → collector → buffer →
loss → target → optimiser → logger (the caller's hooks) → loop.

What happens to a replay sample is built here, as the replay's own transforms: each sampled reward
is replaced by the mean of every reward collected at its (observation, action) (the reward table,
``algo.reward_means``), then centred by the collected rewards' running average r̄
(``algo.reward_centering``), which moves with the values the network gives the states it collects
(``algo.center_on=values``) so that the values it fits stay near zero; the TD(0) target of double
DQN is then r − r̄ + γ·Q_target(s′, argmax Q(s′, ·)), in l2, importance-weighted. ``algo=dqn_plain``
is DQN without the table and without centering. The other parts are ``irdrc.agents.offpolicy``'s and
the loop ``irdrc.agents.loop``'s, shared with the Lagrangian DQN and the fleet's learners;
docs/DQN.md lists every departure from textbook DQN. Every evaluation scores the policy network's
greedy table *exactly* (``scorer``): the exact model only scores, it never steers the learner.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.objectives import DQNLoss

from irdrc.agents.base import Hooks, RunContext, RunRecord
from irdrc.agents.configs.value import DQNConfig
from irdrc.agents.loop import Learner, TrainingLoop, start_frames
from irdrc.agents.offpolicy import (
    CenteredRewards,
    PolyakUpdate,
    RewardCenter,
    action_values,
    clip_and_step,
    greedy_table,
    make_buffer,
    make_collector,
    make_exploration,
    make_optimizer,
    make_qnet,
    observation_top,
    policy_view,
)
from irdrc.agents.reward_table import RewardTable
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params

DEFAULT_EVAL_EVERY_FRAMES = 25_000
"""Exact evaluation period when the caller gives none, env steps."""


def train(
    params: Params | Any,
    cfg: DQNConfig | None = None,
    *,
    seed: int = 0,
    device: str = "cpu",
    scorer: Any = None,
    eval_every_frames: int = DEFAULT_EVAL_EVERY_FRAMES,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train DQN and evaluate its greedy policy exactly every ``eval_every_frames`` env steps.

    Args:
        params: the scenario (``DFRCEnv(params)`` with ``cfg.num_envs`` rows), or a batched env
            of that many rows with DFRCEnv's keys and an observation table (``dynamics.obs``, or
            ``observation_table``: e.g. the fleet's views, ``irdrc.fleet.env``).
        cfg: the hyperparameters (``DQNConfig()``: our profile).
        scorer: scores greedy tables (``irdrc.core.exact.exact_scorer(params)`` by default).
        hooks: ``on_batch`` gets ``env_steps``, ``episodes``, ``loss``, ``beta``, ``buffer`` after
            each batch; ``on_eval`` each evaluation; ``on_checkpoint`` the resumable state.
        resume: an earlier run's ``RunRecord.state`` (a checkpoint) to go on from.

    Returns:
        The run's record: ``greedy`` [1, S] and ``q`` [1, S, A] of the policy network, ``state``
        the checkpoint (networks, optimiser, counters; not the replay, which a resumed run refills).
    """
    cfg = cfg or DQNConfig()
    torch.manual_seed(seed)
    if isinstance(params, Params):
        env = DFRCEnv(params, batch_size=[cfg.num_envs], device=device, seed=seed)
    else:
        env = params
        if tuple(env.batch_size) != (cfg.num_envs,):
            raise ValueError(f"env has {list(env.batch_size)} rows, algo.num_envs={cfg.num_envs}")
    if scorer is None:
        from irdrc.core.exact import exact_scorer

        scorer = exact_scorer(params)
    start = start_frames(resume)

    # 1. model: scaled observation → MLP → one Q-value per action, greedy action; every pass
    #    evaluates each distinct observation of its batch once (``DistinctRows``: the same values)
    qnet = make_qnet(env, cfg.network)
    # 2. exploration: an ε ladder over the env rows, random actions held for several steps
    exploration = make_exploration(env, cfg)
    # 3. collector: every row steps with the network and its own exploration
    collector = make_collector(env, TensorDictSequential(qnet, exploration), cfg, seed, start)
    # 4. buffer: proportional prioritised replay of the whole run; every sample's rewards, as it
    #    is drawn, read from the reward table, then centred (the replay's transforms)
    table = None
    if cfg.reward_means:
        table = RewardTable(observation_top(env), env.action_spec_unbatched.space.n)
    center = RewardCenter(cfg.reward_centering)
    transforms = [t for t in (table, CenteredRewards(center)) if t is not None]
    buffer, sampler = make_buffer(cfg, transforms)

    def collected(data: TensorDictBase) -> None:
        """Each collected batch feeds r̄ and the table; r̄ moves by (1 − γ)·the batch's mean
        greedy value, so the values the network fits stay near zero."""
        center.update(data.get(("next", "reward")))
        if table is not None:
            table.add(data)
        if cfg.center_on == "values":
            level = data.get("action_value").max(-1).values.double().mean()
            center.follow(float(level), cfg.gamma)

    # 5. loss: TD(0) in l2, double DQN, importance-weighted by the prioritised sampler
    loss = DQNLoss(
        qnet,
        loss_function="l2",
        delay_value=True,
        double_dqn=cfg.double_dqn,
        action_space=env.action_spec_unbatched,
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    # 6. target: Polyak averaging after every update
    target = PolyakUpdate(loss, tau=cfg.tau)
    # 7. optimiser: Adam, its learning rate annealed by the loop
    optimizer = make_optimizer(loss, cfg)

    # 8. logger: the caller's hooks; 9. the loop, with what this learner supplies
    def update(sample: TensorDictBase) -> float:
        value = clip_and_step(loss, optimizer, cfg.max_grad_norm, loss(sample)["loss"])
        target.step()
        if cfg.prioritized:  # |δ|: DQNLoss writes δ²
            buffer.update_priority(sample["index"], sample["td_error"].detach().sqrt().reshape(-1))
        return value

    def policy() -> torch.Tensor:
        with policy_view(loss, cfg):
            return greedy_table(qnet, env)

    run = RunContext(scorer, eval_every_frames, hooks, resume)
    loop = TrainingLoop(cfg, collector, buffer, sampler, optimizer, run)
    learner = Learner(
        loss=loss,
        update=update,
        policy=policy,
        collected=collected,
        state=center.state,
        load=center.load,
    )
    record = loop.run(learner)
    with policy_view(loss, cfg):
        record.q = action_values(qnet, env)[None]
    return record
