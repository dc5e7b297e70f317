"""Shared helpers: hand-set transitions on the stateless env."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from irdrc import DFRCEnv, Params

torch.set_num_threads(1)


def one_step(params: Params, states, actions, seed: int = 0) -> TensorDict:
    """Step a fresh env once from hand-set ``states`` with ``actions``; returns the "next" td."""
    states = torch.as_tensor(states, dtype=torch.int64)
    actions = torch.as_tensor(actions, dtype=torch.int64).expand_as(states)
    n = states.numel()
    env = DFRCEnv(params, batch_size=[n], seed=seed)
    td = TensorDict(
        {"state": states, "action": actions, "step_count": torch.zeros(n, 1, dtype=torch.int64)},
        batch_size=[n],
    )
    return env.step(td)["next"]


@pytest.fixture
def step_from():
    return one_step
