"""Choosing a learner's final policy by its own measured returns.

A value-based learner's greedy policy can flip late in training (a near-tie, a noisy batch), so
its last network is not always its best. ``Snapshots`` keeps the greedy tables a learner had at
regular points of its run; ``choose_final`` runs each distinct one on the simulator with common
random numbers (``irdrc.core.evaluate.chain_rewards``) and returns the one whose measured mean
reward beats the last table's by a significant margin, or the last table when none does. Only the
learner's own interaction is used: the exact model never steers the choice. Every measurement
step is counted.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from irdrc.core.evaluate import chain_rewards


class Snapshots:
    """Greedy tables ([S] actions) and their action values ([S, 2]) taken every ``every`` env
    steps from ``after`` on (the last one is added at the end of the run); stored in, and restored
    from, a learner's checkpoint."""

    def __init__(self, every: int, after: int) -> None:
        self.every = int(every)
        self.after = int(after)
        self.frames: list[int] = []
        self.tables: list[torch.Tensor] = []
        self.values: list[torch.Tensor] = []

    @property
    def on(self) -> bool:
        """Whether snapshots are taken at all (``every`` > 0)."""
        return self.every > 0

    def due(self, before: int, now: int) -> bool:
        """Whether a snapshot falls in (before, now]: a multiple of ``every`` at or after
        ``after``."""
        if not self.on or now < self.after:
            return False
        return now // self.every > max(before, self.after - 1) // self.every

    def take(self, frames: int, table: torch.Tensor, values: torch.Tensor) -> None:
        """Keep ``table`` and its action ``values`` (copied to CPU) as taken at ``frames`` env
        steps."""
        self.frames.append(int(frames))
        self.tables.append(table.detach().reshape(-1).to("cpu", torch.int64).clone())
        self.values.append(values.detach().to("cpu").clone())

    def pop(self) -> None:
        """Forget the last snapshot."""
        self.frames.pop()
        self.tables.pop()
        self.values.pop()

    def state(self) -> dict[str, Any]:
        """The checkpointable state."""
        return {
            "frames": list(self.frames),
            "tables": [t.clone() for t in self.tables],
            "values": [v.clone() for v in self.values],
        }

    def load(self, state: dict[str, Any] | None) -> None:
        """Restore from ``state`` (a no-op for None)."""
        if state is None:
            return
        self.frames = [int(f) for f in state["frames"]]
        self.tables = [torch.as_tensor(t, dtype=torch.int64).clone() for t in state["tables"]]
        self.values = [torch.as_tensor(v).clone() for v in state["values"]]


def choose_final(
    params,
    snapshots: Snapshots,
    *,
    envs: int,
    steps: int,
    burn_in: int,
    z: float,
    seed: int,
) -> tuple[int, dict[str, Any]]:
    """The index of the final table among ``snapshots`` (its last entry is the run's last table),
    and facts about the choice.

    Each distinct table is measured once (``chain_rewards``, common random numbers). A table other
    than the last is chosen only if its per-chain mean reward exceeds the last table's by more than
    ``z`` standard errors of the paired difference; among those, the one with the highest mean.
    Facts: ``select_candidates`` (distinct tables), ``select_env_steps`` (measurement steps),
    ``select_chosen_frames`` (when the chosen table was taken), ``select_gain`` (its measured
    mean-reward gain over the last table per step) and ``select_z`` (that gain in standard errors).
    """
    if not snapshots.tables:
        raise ValueError("no snapshots to choose from")
    last = len(snapshots.tables) - 1
    # Distinct tables, each represented by its latest snapshot.
    latest: dict[bytes, int] = {}
    for i, table in enumerate(snapshots.tables):
        latest[table.to(torch.uint8).numpy().tobytes()] = i
    order = sorted(latest.values())  # ends with ``last``: it is its own table's latest
    facts: dict[str, Any] = {
        "select_candidates": len(order),
        "select_env_steps": 0,
        "select_chosen_frames": snapshots.frames[last],
        "select_gain": 0.0,
        "select_z": 0.0,
    }
    if len(order) == 1:
        return last, facts
    tables = torch.stack([snapshots.tables[i] for i in order])
    rewards = chain_rewards(params, tables, envs=envs, steps=steps, burn_in=burn_in, seed=seed)
    facts["select_env_steps"] = len(order) * envs * (burn_in + steps)
    diff = rewards - rewards[-1]
    gain = diff.mean(dim=1)
    se = diff.std(dim=1) / math.sqrt(envs)
    score = torch.where(se > 0, gain / se.clamp_min(1e-300), torch.zeros_like(gain))
    significant = [k for k in range(len(order) - 1) if float(score[k]) > z]
    if not significant:
        return last, facts
    best = max(significant, key=lambda k: float(gain[k]))
    facts.update(
        select_chosen_frames=snapshots.frames[order[best]],
        select_gain=float(gain[best]),
        select_z=float(score[best]),
    )
    return order[best], facts
