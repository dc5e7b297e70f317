"""PQN (Gallici et al. 2024), the alternative to DQN's replay: Q(λ) on each fresh batch of rollouts
from many env rows, without replay or target network, on a normalised network.

Built from the same parts as DQN (``irdrc.agents.offpolicy``: network, ε ladder, collector) and
TorchRL's ``DQNLoss`` with its TD(λ) value estimator (Peng's Q(λ): the λ-return over each row's
``frames_per_batch / num_envs`` steps, bootstrapped on max_a Q of the current network). Each
collection is trained on for ``epochs`` passes, in ``minibatches`` groups of rows.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict.nn import TensorDictSequential
from torchrl.objectives import DQNLoss, ValueEstimators

from irdrc.agents.base import Hooks, RunRecord, make_scorers, progress_record, scenario_list
from irdrc.agents.offpolicy import (
    STORED_KEYS,
    EpisodeTracker,
    OffPolicyConfig,
    RewardCenter,
    anneal,
    clip_and_step,
    greedy_table,
    make_collector,
    make_exploration,
    make_optimizer,
    make_qnet,
)
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params, check_number
from irdrc.core.solve import ExactScorer

NAME = "pqn"


@dataclass(frozen=True)
class PQNConfig(OffPolicyConfig):
    """PQN's hyperparameters: the machinery's (replay, batch, target and n-step keys unused) and
    ``lmbda`` (λ of the returns), ``epochs`` (passes over each collection), ``minibatches``
    (groups of rows per pass)."""

    frames_per_batch: int = 32_000
    lr: float = 1e-3
    prioritized: bool = False  # no replay
    policy_network: str = "online"  # no target network
    lmbda: float = 0.65
    epochs: int = 2
    minibatches: int = 4
    name: str = NAME

    def __post_init__(self) -> None:
        super().__post_init__()
        for key, lo, hi, integer in (
            ("lmbda", 0.0, 1.0, False),
            ("epochs", 1, 1000, True),
            ("minibatches", 1, 10**6, True),
        ):
            object.__setattr__(
                self, key, check_number(f"algo.{key}", getattr(self, key), lo, hi, integer=integer)
            )
        if self.minibatches > self.num_envs:
            raise ValueError(
                f"algo.minibatches={self.minibatches} must be <= algo.num_envs={self.num_envs}"
            )


Config = PQNConfig


def train(
    params: Params | Sequence[Params],
    cfg: PQNConfig | None = None,
    *,
    num_learners: int = 1,
    seed: int = 0,
    device: str = "cpu",
    scorers: ExactScorer | Sequence[ExactScorer] | None = None,
    eval_every_frames: int = 25_000,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train PQN; the interface of ``irdrc.agents.base`` (one scenario, no resume)."""
    cfg = cfg or PQNConfig()
    hooks = hooks or Hooks()
    if resume is not None:
        raise ValueError(f"{NAME} runs do not resume: start again")
    scenarios = scenario_list(params)
    if len(scenarios) != 1 or num_learners != 1:
        raise ValueError(f"{NAME} trains one network on one scenario per run (num_learners=1)")
    (params,) = scenarios
    (scorer,) = make_scorers(scenarios, scorers)
    torch.manual_seed(seed)
    env = DFRCEnv(params, batch_size=[cfg.num_envs], device=device, seed=seed)
    qnet = make_qnet(env, cfg.network)
    exploration = make_exploration(env, cfg)
    loss = DQNLoss(
        qnet,
        loss_function=cfg.loss_function,
        delay_value=False,
        action_space=env.action_spec_unbatched,
    )
    loss.make_value_estimator(ValueEstimators.TDLambda, gamma=cfg.gamma, lmbda=cfg.lmbda)
    optimizer = make_optimizer(loss, cfg)
    collector = make_collector(
        env, TensorDictSequential(qnet, exploration), cfg, cfg.total_frames, seed
    )
    record = RunRecord(method=cfg.name, greedy=torch.zeros(1, env.num_states, dtype=torch.int64))
    episodes = EpisodeTracker(cfg.num_envs, record)
    center = RewardCenter(cfg.reward_centering, cfg.gamma)
    t0 = time.perf_counter()
    frames, optimal = 0, scorer.optimal_metrics.avg_reward

    def evaluate_now() -> None:
        m = scorer.metrics(greedy_table(qnet, env))
        entry = progress_record(
            0,
            frames,
            len(record.episode_rewards),
            time.perf_counter() - t0,
            record.updates,
            m,
            optimal,
        )
        record.history.append(entry)
        hooks.eval([entry])

    evaluate_now()
    next_eval, last = eval_every_frames, math.nan
    for data in collector:
        episodes.add(data, frames)
        center.update(data["next", "reward"])
        frames += data.numel()
        anneal(cfg, optimizer, None, frames)
        batch = center.center(data.select(*STORED_KEYS).clone())
        for _ in range(cfg.epochs):
            for rows in torch.randperm(cfg.num_envs).chunk(cfg.minibatches):
                last = clip_and_step(loss, optimizer, cfg.max_grad_norm, loss(batch[rows])["loss"])
                record.updates += 1
        hooks.batch({"env_steps": frames, "episodes": len(record.episode_rewards), "loss": last})
        stop = hooks.stop_requested()
        if frames >= next_eval or frames >= cfg.total_frames or stop:
            evaluate_now()
            next_eval = (frames // eval_every_frames + 1) * eval_every_frames
        if stop:
            record.interrupted = True
            break
    collector.shutdown()
    record.env_steps, record.episodes = frames, len(record.episode_rewards)
    record.greedy = greedy_table(qnet, env)[None]
    record.wall_seconds = time.perf_counter() - t0
    return record
