"""The best decentralised policy that local search finds: how far own-observation policies can go.

With own observations (``env.observe=own``) each vehicle sees its own state and the shared road and
weather, not the others' queues, so the centralised optimum may be out of reach of any policy the
vehicles can execute. ``improve_tables`` measures how far: from per-vehicle tables it flips one
(vehicle, state) action at a time, keeps every flip that raises the fleet's exact long-run reward,
and sweeps until a whole sweep changes nothing — a local optimum of the decentralised policies
(deterministic, one table per vehicle). Each flip is one exact evaluation (``fleet_metrics``,
~0.2 s at N = 2 on the paper's sizes, so a sweep over 2 × 352 entries is a few minutes).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from irdrc.fleet.model import FleetModel
from irdrc.fleet.policies import joint_policy
from irdrc.fleet.scorer import fleet_metrics


@dataclass(frozen=True)
class SearchResult:
    """``tables`` [N, S] the local optimum, its fleet ``reward``, the start's ``start_reward``,
    ``flips`` kept, ``sweeps`` run, ``evaluations`` and ``seconds``."""

    tables: torch.Tensor
    reward: float
    start_reward: float
    flips: int
    sweeps: int
    evaluations: int
    seconds: float


def improve_tables(
    model: FleetModel,
    tables: torch.Tensor,
    *,
    max_sweeps: int = 10,
    progress: Callable[[int, float, int], None] | None = None,
) -> SearchResult:
    """Local search over per-vehicle tables (see the module docstring); ``tables`` is [S] (every
    vehicle the same) or [N·S]; ``progress(sweep, reward, flips)`` after each sweep."""
    S, N = model.single.num_states, model.N
    t = torch.as_tensor(tables).long().reshape(-1, S).expand(N, S).clone()
    start = time.perf_counter()

    def value(x: torch.Tensor) -> float:
        return fleet_metrics(model, joint_policy(model, x.reshape(-1)))[0].avg_reward

    best = start_reward = value(t)
    flips = evaluations = sweeps = 0
    for sweeps in range(1, max_sweeps + 1):
        changed = 0
        for i in range(N):
            for s in range(S):
                t[i, s] ^= 1
                v = value(t)
                evaluations += 1
                if v > best + 1e-12:
                    best, changed = v, changed + 1
                else:
                    t[i, s] ^= 1
        flips += changed
        if progress is not None:
            progress(sweeps, best, changed)
        if not changed:
            break
    return SearchResult(
        t, best, start_reward, flips, sweeps, evaluations, time.perf_counter() - start
    )
