"""Policies with one interface: TensorDictModules that read the env's keys and write ``action``.

Every policy here maps a tensordict of any batch shape to an int64 ``action`` of that shape
(0 = communication, 1 = radar), so one ``evaluate()`` serves them all.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from irdrc.core.dynamics import fresh_seed


class _Constant(nn.Module):
    def __init__(self, action: int) -> None:
        super().__init__()
        self.action = int(action)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return torch.full_like(state, self.action)


class _RoundRobin(nn.Module):
    def __init__(self, first: int) -> None:
        super().__init__()
        self.first = int(first)

    def forward(self, step_count: torch.Tensor) -> torch.Tensor:
        return (step_count.squeeze(-1) + self.first) % 2


class _Random(nn.Module):
    def __init__(self, p_radar: float, seed: int | None) -> None:
        super().__init__()
        self.p_radar = float(p_radar)
        self.generator = torch.Generator()
        self.generator.manual_seed(seed if seed is not None else fresh_seed())

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        u = torch.rand(state.shape, generator=self.generator).to(state.device)
        return (u < self.p_radar).to(torch.int64)


class _Table(nn.Module):
    actions: torch.Tensor

    def __init__(self, actions: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("actions", torch.as_tensor(actions, dtype=torch.int64).clone())

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.actions[state]


class _ShareTable(nn.Module):
    rho: torch.Tensor

    def __init__(self, rho: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("rho", torch.as_tensor(rho, dtype=torch.float32).clone())

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.rho[state].unsqueeze(-1)


def share_table_policy(rho: torch.Tensor) -> TensorDictModule:
    """Policy from a radar share per state index: ``rho`` [S] in [0, 1], the action of an env
    with ``env.actions=continuous`` (MODEL.md § D)."""
    rho = torch.as_tensor(rho)
    if rho.ndim != 1 or bool(((rho < 0) | (rho > 1)).any()):
        raise ValueError("a radar-share policy is a 1-D table of shares in [0, 1], one per state")
    return TensorDictModule(_ShareTable(rho), in_keys=["state"], out_keys=["action"])


class _RandomTable(nn.Module):
    p_radar: torch.Tensor

    def __init__(self, p_radar: torch.Tensor, seed: int | None) -> None:
        super().__init__()
        self.register_buffer("p_radar", torch.as_tensor(p_radar, dtype=torch.float64).clone())
        self.generator = torch.Generator()
        self.generator.manual_seed(seed if seed is not None else fresh_seed())

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        u = torch.rand(state.shape, generator=self.generator, dtype=torch.float64)
        return (u.to(state.device) < self.p_radar[state]).to(torch.int64)


def always_comm() -> TensorDictModule:
    """Communication mode every step."""
    return TensorDictModule(_Constant(0), in_keys=["state"], out_keys=["action"])


def always_radar() -> TensorDictModule:
    """Radar mode every step."""
    return TensorDictModule(_Constant(1), in_keys=["state"], out_keys=["action"])


def round_robin(first: int = 0) -> TensorDictModule:
    """The paper's round-robin baseline: modes alternate every step.

    Args:
        first: the mode at step 0 of each episode (0 comm, 1 radar); the action at step t is
            (t + first) mod 2.
    """
    if first not in (0, 1):
        raise ValueError(f"first={first!r} must be 0 (comm) or 1 (radar)")
    return TensorDictModule(_RoundRobin(first), in_keys=["step_count"], out_keys=["action"])


def uniform_random(p_radar: float = 0.5, seed: int | None = None) -> TensorDictModule:
    """Radar with probability ``p_radar`` each step, from its own seeded generator."""
    if not 0.0 <= p_radar <= 1.0:
        raise ValueError(f"p_radar={p_radar!r} must be in [0, 1]")
    return TensorDictModule(_Random(p_radar, seed), in_keys=["state"], out_keys=["action"])


def table_policy(
    actions: torch.Tensor, seed: int | None = None, num_actions: int = 2
) -> TensorDictModule:
    """Policy from a table per state index (see ``irdrc.core.dynamics``): [S] actions in
    0 … ``num_actions`` − 1 (deterministic; G levels with ``env.actions=levels``) or [S, 2]
    probabilities of (comm, radar) (randomised, drawn from its own generator seeded by ``seed``)."""
    actions = torch.as_tensor(actions)
    if actions.ndim == 2:
        if (
            actions.shape[1] != 2
            or bool((actions < 0).any())
            or not torch.allclose(actions.sum(-1).double(), torch.ones(actions.shape[0]).double())
        ):
            raise ValueError(
                "a randomised policy must be an [S, 2] table of probabilities summing to 1 per "
                "state, S the env's number of states"
            )
        return TensorDictModule(
            _RandomTable(actions[:, 1], seed), in_keys=["state"], out_keys=["action"]
        )
    whole = not actions.is_floating_point() or bool((actions == actions.round()).all())
    if actions.ndim != 1 or not whole or bool(((actions < 0) | (actions >= num_actions)).any()):
        top = "0/1" if num_actions == 2 else f"0 … {num_actions - 1}"
        raise ValueError(f"actions must be a 1-D table of {top}, one entry per state")
    return TensorDictModule(_Table(actions), in_keys=["state"], out_keys=["action"])
