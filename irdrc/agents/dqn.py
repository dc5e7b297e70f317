"""DQN from TorchRL parts, learning from many env rows at once: the one training loop every recipe
and sweep calls.

Components are built in a fixed order (``irdrc.agents.offpolicy``): Q-network → ε ladder over the
env rows → prioritised replay → ``DQNLoss`` → target updater → Adam → collector; then the loop
collects a batch from every row, stores it, runs the updates that are due, and evaluates the greedy
network *exactly* on all states on a schedule. ``irdrc.agents.dqn_variants`` holds the variants
(distributional values, final-policy selection).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictSequential

from irdrc.agents import dqn_variants as variants
from irdrc.agents.base import Hooks, RunRecord, make_scorers, progress_record, scenario_list
from irdrc.agents.offpolicy import (
    NetworkConfig,
    OffPolicyConfig,
    OffPolicyLoop,
    RewardCenter,
    clip_and_step,
    greedy_table,
    make_buffer,
    make_collector,
    make_dqn_loss,
    make_exploration,
    make_optimizer,
    make_qnet,
    make_target_updater,
    policy_view,
)
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params, check_bool, check_number
from irdrc.core.solve import ExactScorer

NAME = "dqn"
DEFAULT_EVAL_EVERY_FRAMES = 25_000
"""Exact evaluation period when the caller gives none, env steps."""

__all__ = ["NAME", "DQNConfig", "NetworkConfig", "load_checkpoint", "train"]


@dataclass(frozen=True)
class DQNConfig(OffPolicyConfig):
    """DQN's hyperparameters (config group ``algo``): the machinery's (``OffPolicyConfig``) and
    the variants' (``irdrc.agents.dqn_variants``).

    Attributes:
        distributional: learn the distribution of the (centred) discounted return on ``atoms``
            points over ±``support_span`` × the largest |reward| (C51, TorchRL's
            ``DistributionalDQNLoss``; ``loss_function`` and ``n_steps`` are unused).
        select_every_frames: 0 (off), or the period of snapshots of the greedy policy from
            ``select_after_frames`` on; the final policy is the snapshot whose mean reward,
            measured on ``select_envs`` chains of ``select_burn_in`` + ``select_steps`` steps with
            common random numbers, beats the last network's by more than ``select_z`` standard
            errors (the last network's when none does). The measurement steps are counted.
    """

    distributional: bool = False
    atoms: int = 51
    support_span: float = 6.0
    select_every_frames: int = 0
    select_after_frames: int = 250_000
    select_envs: int = 64
    select_steps: int = 1_000
    select_burn_in: int = 200
    select_z: float = 2.58

    def __post_init__(self) -> None:
        super().__post_init__()

        def num(key: str, lo: float, hi: float = math.inf, **kw: Any) -> None:
            object.__setattr__(
                self, key, check_number(f"algo.{key}", getattr(self, key), lo, hi, **kw)
            )

        check_bool("algo.distributional", self.distributional)
        num("atoms", 2, 100_000, integer=True)
        num("support_span", 0, 1e6, open_lo=True)
        num("select_every_frames", 0, 10**12, integer=True)
        num("select_after_frames", 0, 10**12, integer=True)
        num("select_envs", 2, 10**7, integer=True)
        num("select_steps", 1, 10**9, integer=True)
        num("select_burn_in", 0, 10**9, integer=True)
        num("select_z", 0, 100)
        if self.distributional and not self.double_dqn:
            raise ValueError(
                "algo.distributional=true needs algo.double_dqn=true (TorchRL's distributional "
                "loss always picks the next action with the online network)"
            )
        if self.distributional and self.n_steps > 1:
            raise ValueError(
                f"algo.distributional=true with algo.n_steps={self.n_steps}: the distributional "
                "loss takes one-step transitions (set algo.n_steps=1)"
            )
        if self.select_every_frames and self.select_after_frames >= self.total_frames:
            raise ValueError(
                f"algo.select_after_frames={self.select_after_frames} must be < "
                f"algo.total_frames={self.total_frames} when algo.select_every_frames > 0 (there "
                "would be nothing to choose from)"
            )


Config = DQNConfig
"""This learner's config class (the interface of ``irdrc.agents.base``)."""


def train(
    params: Params | Sequence[Params],
    cfg: DQNConfig | None = None,
    *,
    num_learners: int = 1,
    seed: int = 0,
    device: str = "cpu",
    scorers: ExactScorer | Sequence[ExactScorer] | None = None,
    eval_every_frames: int = DEFAULT_EVAL_EVERY_FRAMES,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train DQN on the batched env and evaluate the greedy network exactly on a schedule (the
    learner interface of ``irdrc.agents.base``; ``train_on`` with ``DFRCEnv(params)``)."""
    return train_on(
        None,
        params,
        cfg,
        num_learners=num_learners,
        seed=seed,
        device=device,
        scorers=scorers,
        eval_every_frames=eval_every_frames,
        hooks=hooks,
        resume=resume,
    )


def train_on(
    env: DFRCEnv | None,
    params: Params | Sequence[Params],
    cfg: DQNConfig | None = None,
    *,
    num_learners: int = 1,
    seed: int = 0,
    device: str = "cpu",
    scorers: ExactScorer | Sequence[ExactScorer] | None = None,
    eval_every_frames: int = DEFAULT_EVAL_EVERY_FRAMES,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
) -> RunRecord:
    """Train DQN on the batched env and evaluate the greedy network exactly on a schedule.

    ``env``: the batched env to learn from (None: ``DFRCEnv(params)``) — one with
    ``cfg.num_envs`` rows and DFRCEnv's keys and ``dynamics.obs`` (e.g. the fleet's rows,
    ``irdrc.fleet.env.FleetRowsEnv``, scored by ``scorers`` of its own).

    The interface of ``irdrc.agents.base``: one scenario and one network per run (``num_learners``
    1); ``hooks.on_batch`` gets ``env_steps``, ``episodes``, ``loss``, ``beta``, ``buffer`` after
    each collected batch; ``resume`` is an earlier run's ``RunRecord.state``; the returned
    record's ``state`` is the checkpoint (networks, optimiser, counters; not the replay, which a
    resumed run refills).
    """
    cfg = cfg or DQNConfig()
    hooks = hooks or Hooks()
    scenarios = scenario_list(params)
    if len(scenarios) != 1 or num_learners != 1:
        raise ValueError("DQN trains one network on one scenario per run (num_learners=1)")
    if eval_every_frames < 1:
        raise ValueError(f"eval.every_frames={eval_every_frames!r} must be >= 1")
    (params,) = scenarios
    (scorer,) = make_scorers(scenarios, scorers)
    torch.manual_seed(seed)
    if env is None:
        env = DFRCEnv(params, batch_size=[cfg.num_envs], device=device, seed=seed)
    elif tuple(env.batch_size) != (cfg.num_envs,):
        raise ValueError(f"env has {list(env.batch_size)} rows, algo.num_envs={cfg.num_envs}")

    # Components in a fixed order: model → exploration → buffer → loss → target → optimiser.
    if cfg.distributional:
        qnet, loss = variants.make_distributional(env, cfg)
    else:
        qnet = make_qnet(env, cfg.network)
        loss = make_dqn_loss(qnet, env, cfg)
    exploration = make_exploration(env, cfg)
    buffer, sampler = make_buffer(cfg)
    target = make_target_updater(loss, cfg)
    optimizer = make_optimizer(loss, cfg)
    record = RunRecord(method=cfg.name, greedy=torch.zeros(1, env.num_states, dtype=torch.int64))
    record.info["replay_sampler"] = type(sampler).__name__ + (
        " (prioritised)" if cfg.prioritized else " (uniform)"
    )
    hooks.start(dict(record.info))
    center = RewardCenter(cfg.reward_centering, cfg.gamma)
    selection = variants.Selection(cfg)
    start = _restore(resume, loss, optimizer, record, center, selection)
    if start >= cfg.total_frames:
        raise ValueError(f"nothing to resume: the checkpoint is at {start} ≥ algo.total_frames")
    # ... and the collector, which steps every row with the network and its row's exploration.
    policy = TensorDictSequential(qnet, exploration)
    collector = make_collector(env, policy, cfg, cfg.total_frames - start, seed + start)
    if resume is not None:
        collector.init_random_frames = 0  # a resumed run acts with its network from the start
    loop = OffPolicyLoop(
        cfg, collector, buffer, sampler, optimizer, center, record, hooks, start_frames=start
    )

    def update(sample) -> float:
        out = loss(sample)
        value = clip_and_step(loss, optimizer, cfg.max_grad_norm, out["loss"])
        target.step()
        if cfg.prioritized:
            buffer.update_priority(sample["index"], variants.priority(sample, cfg))
        return value

    t0 = time.perf_counter() - (float(resume["wall_seconds"]) if resume is not None else 0.0)
    optimal = scorer.optimal_metrics.avg_reward

    def policy() -> tuple[torch.Tensor, torch.Tensor]:
        """The learner's greedy table [S] and action values [S, 2] (``policy_network``'s)."""
        with policy_view(loss, cfg):
            return greedy_table(qnet, env), variants.values(qnet, env)

    def evaluate_now() -> None:
        start = time.perf_counter()
        table, q = policy()
        m = scorer.metrics(table)
        wall = time.perf_counter() - t0
        entry = progress_record(
            0, loop.frames, len(record.episode_rewards), wall, loop.updates, m, optimal
        )
        record.history.append(entry)
        hooks.eval([entry])
        hooks.values(loop.frames, q[None])
        record.info["seconds_evaluate"] = (
            record.info.get("seconds_evaluate", 0.0) + time.perf_counter() - start
        )

    if resume is None:
        evaluate_now()
    next_eval = (loop.frames // eval_every_frames + 1) * eval_every_frames
    for data in loop.batches():
        loop.learn(update)
        before = loop.frames - data.numel()
        if selection.due(before, loop.frames):
            selection.take(loop.frames, *policy())
        hooks.batch(loop.scalars())
        stop = loop.stop_due()
        if loop.frames >= next_eval or loop.frames >= cfg.total_frames or stop:
            evaluate_now()
            next_eval = (loop.frames // eval_every_frames + 1) * eval_every_frames
        if hooks.checkpoint_due(before, loop.frames) and loop.frames < cfg.total_frames:
            wall = time.perf_counter() - t0
            hooks.on_checkpoint(_checkpoint(loss, optimizer, record, loop, wall, center, selection))
        if stop:
            record.interrupted = True
            break
    loop.shutdown()
    record.env_steps = loop.frames
    record.episodes = len(record.episode_rewards)
    table, q = policy()
    record.greedy, record.q = table[None], q[None]
    record.state = _checkpoint(loss, optimizer, record, loop, 0.0, center, selection)
    if selection.on and not record.interrupted:
        selection.finish(record, params, seed, scorer, optimal)
    record.wall_seconds = time.perf_counter() - t0
    record.state["wall_seconds"] = record.wall_seconds
    return record


def _checkpoint(loss, optimizer, record, loop, wall, center, selection) -> dict[str, Any]:
    """The resumable state: networks, optimiser, counters, history so far, the reward centre and
    the selection's snapshots (when those are on)."""
    return {
        "loss": loss.state_dict(),
        "optimizer": optimizer.state_dict(),
        "frames": loop.frames,
        "updates": loop.updates,
        "wall_seconds": wall,
        "history": list(record.history),
        "episode_rewards": list(record.episode_rewards),
        **({"reward_center": center.value} if center.on and center.value is not None else {}),
        **selection.state(),
    }


def _restore(resume, loss, optimizer, record, center, selection) -> int:
    """Load a checkpoint into the components and the record; returns its env steps (0 if none)."""
    if resume is None:
        return 0
    loss.load_state_dict(resume["loss"])
    optimizer.load_state_dict(resume["optimizer"])
    if center.on and resume.get("reward_center") is not None:
        center.value = float(resume["reward_center"])
    selection.load(resume)
    record.updates = int(resume["updates"])
    record.history = list(resume.get("history", []))
    record.episode_rewards = list(resume.get("episode_rewards", []))
    return int(resume["frames"])


CHECKPOINT_KEYS = ("loss", "optimizer", "frames", "updates", "wall_seconds", "history", "config")


def load_checkpoint(path) -> dict[str, Any]:
    """Load a checkpoint (``RunRecord.state`` plus the run's ``config``) written by a DQN run.

    Raises:
        ValueError: one line naming the file when it is missing, truncated, corrupt or not a DQN
            checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"resume={path}: no such checkpoint file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated or corrupt: EOFError, RuntimeError, UnpicklingError …
        raise ValueError(
            f"resume={path}: not a readable checkpoint ({type(err).__name__}); it may be truncated "
            "or from another program"
        ) from err
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(state, dict) or k not in state]
    if missing:
        raise ValueError(f"resume={path}: not an irdrc DQN checkpoint (no {', '.join(missing)})")
    return state


def config_keys() -> set[str]:
    """Every ``algo.*`` key DQN reads."""
    return {f.name for f in fields(DQNConfig) if f.name != "network"}
