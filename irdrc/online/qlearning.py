"""Tabular Q-learning on one stream (``learner=qlearning`` and ``learner=qlearning_paper``): the
update of ``irdrc.agents.qlearning`` (one table, ε-greedy, step sizes constant or 1/k), on one
vehicle's steps as they come, in plain Python (a few µs a step)."""

from __future__ import annotations

import random
from typing import Any

import torch

from irdrc.agents.configs import QLearningConfig
from irdrc.core.stream import Step
from irdrc.online.loop import StreamLearner


class StreamQLearning(StreamLearner):
    """One Q-table over S states × 2 actions, learning from every step of the stream.

    Args:
        cfg: the profile (``irdrc.online.configs.QLEARNING`` or ``QLEARNING_PAPER``).
        num_states: S.
        seed: the exploration's seed.
    """

    def __init__(self, cfg: QLearningConfig, num_states: int, seed: int = 0) -> None:
        self.cfg, self.name = cfg, cfg.name
        self.num_states = int(num_states)
        self.q = [float(cfg.init_q)] * (2 * self.num_states)
        self.visits = [0] * (2 * self.num_states)
        self.rng = random.Random(seed)
        self.eps = cfg.epsilon(0)
        self.updates = 0

    def begin_episode(self, episode: int) -> None:
        self.eps = self.cfg.epsilon(episode)

    def act(self, state: int) -> int:
        if self.eps > 0 and self.rng.random() < self.eps:
            return int(self.rng.random() < 0.5)
        q = self.q
        return int(q[2 * state + 1] > q[2 * state])  # ties → comm, as argmax

    def observe(self, state: int, action: int, step: Step) -> None:
        cfg, q = self.cfg, self.q
        i, j = 2 * state + action, 2 * step.state
        target = step.reward + cfg.gamma * max(q[j], q[j + 1])
        if cfg.alpha_schedule == "count":
            self.visits[i] += 1
            alpha = max(cfg.alpha_min, cfg.alpha / self.visits[i] ** cfg.alpha_power)
        else:
            alpha = cfg.alpha
        q[i] += alpha * (target - q[i])
        self.updates += 1

    def end_episode(self, episode: int) -> dict[str, float]:
        return {"epsilon": self.eps}

    def table(self) -> torch.Tensor:
        """[S, 2] the Q-table."""
        return torch.tensor(self.q, dtype=torch.float64).view(-1, 2)

    def greedy(self) -> torch.Tensor:
        return self.table().argmax(-1)

    def behaviour(self) -> torch.Tensor:
        probs = torch.nn.functional.one_hot(self.greedy(), 2).to(torch.float64)
        return (1.0 - self.eps) * probs + self.eps / 2.0

    def state_dict(self) -> dict[str, Any]:
        return {
            "q": list(self.q),
            "visits": list(self.visits),
            "rng": self.rng.getstate(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.q, self.visits = list(state["q"]), list(state["visits"])
        self.rng.setstate(tuple_state(state["rng"]))
        self.updates = int(state["updates"])


def tuple_state(state: Any) -> Any:
    """A ``random.Random`` state as ``setstate`` takes it (a checkpoint may hold lists)."""
    if isinstance(state, list | tuple):
        return tuple(tuple_state(x) if isinstance(x, list | tuple) else x for x in state)
    return state
