"""Fleet policies as joint policies of the exact fleet model: tables the vehicles apply to their own
states, each vehicle's single-vehicle optimum, and MODEL.md § C's baselines."""

from __future__ import annotations

from typing import cast

import torch

from irdrc.core.exact import value_iteration
from irdrc.fleet.model import FleetModel


def joint_from_single(model: FleetModel, actions: torch.Tensor) -> torch.Tensor:
    """[S_fleet] joint actions where every vehicle applies the single-vehicle table ``actions``
    ([S] over the single model's states) to its own state and the shared road and weather."""
    table = torch.as_tensor(actions).long()[model.index]  # [RW, X]
    joint = torch.zeros(model.shape(), dtype=torch.int64)
    for i in range(model.N):
        joint = joint + (model._expand(table, i) << i)
    return joint.reshape(-1)


def joint_policy(model: FleetModel, table: torch.Tensor) -> torch.Tensor:
    """[S_fleet] joint actions of a decentralised policy: a table [S] over the single-vehicle
    states every vehicle applies to its own state, one per vehicle [N·S] (vehicle-major), or
    already a joint action per joint state [S_fleet]."""
    S, table = model.single.num_states, torch.as_tensor(table).long().reshape(-1)
    if table.numel() == S:  # one table every vehicle applies
        return joint_from_single(model, table)
    if table.numel() == model.num_states:  # a joint action per joint state
        return table
    if table.numel() != model.N * S:
        raise ValueError(
            f"a fleet policy has {S}, {model.N * S} or {model.num_states} entries, not "
            f"{table.numel()}"
        )
    per = table.reshape(model.N, S)  # vehicle i's own table (agent_index)
    bits = ((joint_from_single(model, per[i]) >> i & 1) << i for i in range(model.N))
    return cast(torch.Tensor, sum(bits))


def single_optima(model: FleetModel, gamma: float = 0.99) -> torch.Tensor:
    """[N, S] each vehicle's own single-vehicle optimum (value iteration on its model alone)."""
    done: dict[int, torch.Tensor] = {}
    for t in model.kernels:
        if id(t) not in done:
            done[id(t)] = value_iteration(t.single, gamma=gamma).policy
    return torch.stack([done[id(t)] for t in model.kernels])


def baselines(model: FleetModel, single_optimum: torch.Tensor) -> dict[str, object]:
    """MODEL.md § C's baselines as joint policies: every vehicle applying the single-vehicle
    optimum ``single_optimum`` ([S], or its own [N, S]: ``single_optima``) to its own state; round-robin in phase (all comm, then all radar)
    and in anti-phase (odd and even vehicles alternate the other way round); a sensing rotation
    (vehicle t mod N in radar at step t, the others in comm). Periodic ones are lists of per-phase
    joint actions."""
    S, N = model.num_states, model.N
    every = 2**N - 1

    def const(a: int) -> torch.Tensor:
        return torch.full((S,), a, dtype=torch.int64)

    odd = sum(1 << i for i in range(1, N, 2))  # vehicles 2, 4, … (bits 1, 3, …)
    return {
        "N copies of the single optimum": joint_policy(model, single_optimum.reshape(-1)),
        "round-robin in phase": [const(0), const(every)],
        "round-robin in anti-phase": [const(odd), const(every ^ odd)],
        "sensing rotation": [const(1 << t) for t in range(N)],
    }
