"""Shared helpers: hand-set transitions on the stateless env."""

from __future__ import annotations

import math

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


def assert_chi2(counts: torch.Tensor, expected: torch.Tensor) -> None:
    """Pearson χ² of observed transition ``counts`` [rows, S] against ``expected`` counts.

    Cells with expected count ≥ 5 are compared one by one, each row's remaining cells lumped into one
    (kept when its expectation is ≥ 5 too). Under the model the statistic has mean dof and sd
    √(2·dof); 5 sd above the mean is the bound. Cells the model calls impossible must stay empty.
    """
    big = expected >= 5
    stat = float((((counts - expected) ** 2 / expected.clamp(min=1e-300)) * big).sum())
    dof = int(big.sum()) - counts.shape[0]
    rest_e = (expected * ~big).sum(1)
    rest_o = (counts * ~big).sum(1)
    keep = rest_e >= 5
    stat += float(((rest_o - rest_e) ** 2 / rest_e.clamp(min=1e-300))[keep].sum())
    dof += int(keep.sum())
    assert stat < dof + 5 * math.sqrt(2 * dof), (stat, dof)
    assert float(counts[expected == 0].sum()) == 0.0
