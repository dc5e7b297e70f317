"""The one training loop of every learner (DQN, the Lagrangian DQN, the fleet's learners, SAC, PPO):
collect from many env rows at once, learn from each batch — off-policy, by storing it in replay and
running the gradient updates that are due on what the replay draws; on-policy, by handing it to the
learner — and own what every run needs around that: the exact evaluations on a schedule, the stop
asked for by a signal, the checkpoints, and resuming from one. A learner supplies only its parts:
the update (or its learning from a batch), the policy an evaluation scores, and, where it has them,
what it does with each collected batch (its reward table, its reward centre), after each batch, and
state of its own. What happens to a sample before the update is the learner's replay's own
transforms (``irdrc.agents.dqn``): the loop reads no learner's options.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import TensorDictReplayBuffer

from irdrc.agents.base import BatchSchedule, RunContext, RunRecord, progress_record
from irdrc.agents.offpolicy import STORED_KEYS, EpisodeTracker, anneal


@dataclass
class Learner:
    """What a learner supplies to the loop.

    Attributes:
        loss: its loss module (networks and target networks: checkpointed).
        update: one gradient update on a replay sample; returns the loss value (an off-policy
            learner).
        learn_batch: instead of ``update``, an on-policy learner's learning from each collected
            batch itself; returns (gradient updates done, the last loss value). The loop then keeps
            no replay.
        policy: the table an exact evaluation scores (a greedy table; the fleet's per vehicle).
        collected: optional, each collected batch before it is stored (a reward table and a
            reward centre are fed here).
        after_batch: optional, after each batch's updates: ``(batch, learned) -> scalars`` to
            report beside the loop's own (the Lagrangian DQN adapts its multiplier here).
        state, load: optional, the learner's own checkpoint entries, and their restore.
    """

    loss: nn.Module
    update: Callable[[TensorDictBase], float] | None
    policy: Callable[[], torch.Tensor]
    learn_batch: Callable[[TensorDictBase], tuple[int, float]] | None = None
    collected: Callable[[TensorDictBase], None] | None = None
    after_batch: Callable[[TensorDictBase, bool], dict[str, Any]] | None = None
    state: Callable[[], dict[str, Any]] | None = None
    load: Callable[[dict[str, Any]], None] | None = None


RESUME_KEYS = ("frames", "updates", "history", "loss", "optimizer")
"""What a learner's checkpoint (``TrainingLoop.state``) holds at least."""


def start_frames(resume: dict[str, Any] | None) -> int:
    """The env steps a run starts at: its checkpoint's, or 0.

    Raises:
        ValueError: ``resume`` is not an off-policy learner's checkpoint (naming what it lacks).
    """
    if resume is None:
        return 0
    missing = [k for k in RESUME_KEYS if k not in resume]
    if missing:
        raise ValueError(
            f"resume: the checkpoint has no {', '.join(missing)}: not a checkpoint of this learner"
        )
    return int(resume["frames"])


class TrainingLoop:
    """Collect → store → learn → (evaluate, checkpoint, stop), over one collector and one replay
    (none for an on-policy learner: ``buffer`` and ``sampler`` None).

    Args:
        cfg: the machinery's hyperparameters (``num_envs``, ``total_frames``, ``batch_size``,
            ``init_random_frames``, ``updates_per_batch``, ``lr``, ``lr_end``, ``prioritized``,
            ``name``).
        collector, buffer, sampler, optimizer: the learner's parts.
        run: the scorer of ``Learner.policy``'s tables, the evaluation period, the hooks and the
            checkpoint to go on from (``RunContext``).
        keys: what replay keeps of a transition.
        prepare: rewrites each collected batch before anything reads it (the fleet's value
            decomposition puts the team reward at the root there).
    """

    def __init__(
        self,
        cfg: BatchSchedule,
        collector: Collector,
        buffer: TensorDictReplayBuffer,
        sampler: Any,
        optimizer: torch.optim.Optimizer,
        run: RunContext,
        *,
        keys: tuple[str | tuple[str, ...], ...] = STORED_KEYS,
        prepare: Callable[[TensorDictBase], TensorDictBase] | None = None,
    ) -> None:
        self.cfg, self.collector, self.buffer, self.sampler = cfg, collector, buffer, sampler
        self.optimizer, self.scorer, self.hooks = optimizer, run.scorer, run.hooks
        self.eval_every = int(run.eval_every_frames)
        self.resume = resume = run.resume
        self.keys, self.prepare = keys, prepare
        self.collected: Callable[[TensorDictBase], None] | None = None
        self.record = RunRecord(method=cfg.name, greedy=torch.zeros(1, 1, dtype=torch.int64))
        self.frames = start_frames(resume)
        self.updates = 0
        self.episodes = EpisodeTracker(cfg.num_envs, self.record)
        # a fresh run learns once its random warm-up is stored; a resumed one (its replay is not
        # checkpointed) as soon as it holds a batch
        self.learn_from = (
            cfg.batch_size if resume is not None else max(cfg.batch_size, cfg.init_random_frames)
        )
        self.last_loss = math.nan
        self.seconds = {"collect": 0.0, "store": 0.0, "learn": 0.0, "evaluate": 0.0}
        """Wall seconds spent collecting (policy and env steps), storing (episodes, centre,
        replay), learning (sampling, updates, priorities) and evaluating: where the time goes."""
        self.record.info["replay_sampler"] = (
            "none (on-policy)"
            if buffer is None
            else type(sampler).__name__ + (" (prioritised)" if cfg.prioritized else " (uniform)")
        )
        self.hooks.start(dict(self.record.info))
        self.t0 = time.perf_counter() - (float(resume["wall_seconds"]) if resume else 0.0)

    # -- one batch ------------------------------------------------------------------------------

    def batches(self) -> Iterator[TensorDictBase]:
        """Each collected batch [rows, steps], after it is stored in replay and counted."""
        if self.frames >= self.cfg.total_frames:  # a complete training resumed to finish its files
            return
        batches = iter(self.collector)
        while True:
            t0 = time.perf_counter()
            data = next(batches, None)
            t1 = time.perf_counter()
            self.seconds["collect"] += t1 - t0
            if data is None:
                return
            if self.prepare is not None:
                data = self.prepare(data)
            self.episodes.add(data, self.frames)
            if self.collected is not None:
                self.collected(data)
            if self.buffer is not None:
                self.buffer.extend(data.select(*self.keys).reshape(-1))
            self.frames += data.numel()
            anneal(self.cfg, self.optimizer, self.frames)
            self.seconds["store"] += time.perf_counter() - t1
            yield data

    def learn(self, update: Callable[[TensorDictBase], float]) -> bool:
        """``updates_per_batch`` gradient updates on replay samples (as the replay's transforms
        draw them), once replay holds enough; returns whether it learned."""
        if len(self.buffer) < self.learn_from:
            return False
        t0 = time.perf_counter()
        for _ in range(self.cfg.updates_per_batch):
            self.last_loss = update(self.buffer.sample())
            self.updates += 1
        self.seconds["learn"] += time.perf_counter() - t0
        return True

    def learn_on_policy(
        self, learn_batch: Callable[[TensorDictBase], tuple[int, float]], data: TensorDictBase
    ) -> bool:
        """An on-policy learner's learning from the collected batch ``data``."""
        t0 = time.perf_counter()
        updates, self.last_loss = learn_batch(data)
        self.updates += updates
        self.seconds["learn"] += time.perf_counter() - t0
        return True

    def learning(self, learner: Learner) -> Callable[[TensorDictBase], bool]:
        """What learns from each collected batch: ``learn_on_policy`` with the learner's
        ``learn_batch``, else ``learn`` with its ``update``.

        Raises:
            ValueError: the learner has neither.
        """
        learn_batch, update = learner.learn_batch, learner.update
        if learn_batch is not None:
            return lambda data: self.learn_on_policy(learn_batch, data)
        if update is not None:
            return lambda data: self.learn(update)
        raise ValueError("a Learner needs update (off-policy) or learn_batch (on-policy)")

    def scalars(self, **extra: Any) -> dict[str, Any]:
        """What is reported after each batch: env steps, episodes, the last loss, the replay's
        size, and ``extra``."""
        return {
            "env_steps": self.frames,
            "episodes": len(self.record.episode_rewards),
            "loss": self.last_loss,
            "buffer": 0 if self.buffer is None else len(self.buffer),
            **extra,
        }

    # -- around the batches ---------------------------------------------------------------------

    def evaluate(self, learner: Learner) -> None:
        """Score the learner's policy exactly and report it."""
        t0 = time.perf_counter()
        m = self.scorer.metrics(learner.policy())
        entry = progress_record(
            0,
            self.frames,
            len(self.record.episode_rewards),
            time.perf_counter() - self.t0,
            self.updates,
            m,
            self.scorer.optimal_metrics.avg_reward,
        )
        self.record.history.append(entry)
        self.hooks.eval([entry])
        self.seconds["evaluate"] += time.perf_counter() - t0

    def state(self, learner: Learner) -> dict[str, Any]:
        """The checkpoint: networks, optimiser, counters, history so far, and the learner's own
        entries (its reward centre, …; not the replay, which a resumed run refills)."""
        return {
            "loss": learner.loss.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "frames": self.frames,
            "updates": self.updates,
            "wall_seconds": time.perf_counter() - self.t0,
            "history": list(self.record.history),
            "episode_rewards": list(self.record.episode_rewards),
            **(learner.state() if learner.state is not None else {}),
        }

    def restore(self, learner: Learner) -> None:
        """Load ``resume`` into the learner's parts and the record."""
        resume = self.resume
        if resume is None:
            return
        learner.loss.load_state_dict(resume["loss"])
        self.optimizer.load_state_dict(resume["optimizer"])
        self.updates = int(resume["updates"])
        self.record.history = list(resume.get("history", []))
        self.record.episode_rewards = list(resume.get("episode_rewards", []))
        if learner.load is not None:
            learner.load(resume)

    def run(self, learner: Learner) -> RunRecord:
        """Train to ``total_frames`` (or until a stop is asked for), evaluating every
        ``eval_every_frames`` env steps and at the end, checkpointing when due; returns the record
        (its ``state`` the final checkpoint, ``greedy`` the final policy)."""
        self.collected = learner.collected
        self.restore(learner)
        if self.resume is None:
            self.evaluate(learner)
        total, every = self.cfg.total_frames, self.eval_every
        next_eval = (self.frames // every + 1) * every
        learn = self.learning(learner)
        for data in self.batches():
            before = self.frames - data.numel()
            learned = learn(data)
            extra = learner.after_batch(data, learned) if learner.after_batch else {}
            self.hooks.batch(self.scalars(**extra))
            stop = self.hooks.stop_requested()
            if self.frames >= next_eval or self.frames >= total or stop:
                self.evaluate(learner)
                next_eval = (self.frames // every + 1) * every
            if self.hooks.checkpoint_due(before, self.frames) and self.frames < total:
                self.hooks.checkpoint(self.state(learner))
            if stop:
                self.record.interrupted = True
                break
        self.collector.shutdown()
        record = self.record
        record.env_steps, record.updates = self.frames, self.updates
        record.episodes = len(record.episode_rewards)
        record.greedy = learner.policy()[None]
        record.state = self.state(learner)
        record.wall_seconds = time.perf_counter() - self.t0
        for phase, seconds in self.seconds.items():
            record.info[f"seconds_{phase}"] = seconds
        return record
