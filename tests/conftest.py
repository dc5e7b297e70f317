"""Shared helpers: hand-set transitions on the stateless env."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from irdrc import DFRCEnv, Params
from irdrc.core.factored import (
    build_factored,
    stationary_distribution_factored,
    stationary_metrics_factored,
    value_iteration_factored,
)
from irdrc.core.model import build_model
from irdrc.core.solve import stationary_metrics, value_iteration

torch.set_num_threads(1)


TINY_DQN = [
    "algo.num_envs=8",
    "algo.frames_per_batch=32",
    "algo.total_frames=640",
    "algo.init_random_frames=128",
    "algo.buffer_size=640",
    "algo.batch_size=32",
    "eval.every_frames=320",
    "progress=false",
    "logger=none",
]
"""Overrides of a DQN run of a few seconds (640 env steps), for tests that need a run's files."""


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


def assert_factored_equals_dense(params, seed: int) -> None:
    """Every operator and table to 1e-9 (observed: ≤ 1e-11), value iteration's policy and values,
    and exact stationary metrics of the optimum and of a randomised policy by both methods."""
    dense, fac = build_model(params), build_factored(params)
    S = dense.num_states
    gen = torch.Generator().manual_seed(seed)
    V = torch.randn(S, generator=gen, dtype=torch.float64)
    x = torch.rand(S, generator=gen, dtype=torch.float64)
    for a in (0, 1):
        assert torch.allclose(fac.expect(V, a), dense.P[a] @ V, rtol=0, atol=1e-9)
        assert torch.allclose(fac.push(x, a), x @ dense.P[a], rtol=0, atol=1e-9)
    for key, table in fac.tables().items():
        assert torch.allclose(table, getattr(dense, key), rtol=0, atol=1e-9), key
    opt, fopt = value_iteration(dense), value_iteration_factored(fac, tol=1e-9)
    assert torch.equal(opt.policy, fopt.policy)
    assert torch.allclose(fopt.values, opt.values, rtol=0, atol=1e-8)
    mixed = torch.rand(S, 2, generator=gen, dtype=torch.float64)
    mixed = mixed / mixed.sum(-1, keepdim=True)
    for policy in (opt.policy, mixed):
        want = stationary_metrics(dense, policy).as_dict()
        for method in ("auto", "gmres", "iad", "power"):
            mu, _ = stationary_distribution_factored(fac, policy, method=method)
            assert mu.shape == (S,) and abs(float(mu.sum()) - 1) < 1e-12
            got = stationary_metrics_factored(fac, policy, mu=mu).as_dict()
            assert set(got) == set(want)  # false_alarm_rate in both, or in neither
            for k in want:
                assert got[k] == pytest.approx(want[k], rel=1e-9, abs=1e-9), (method, k)


def assert_dqn_trains_and_resumes(**options) -> None:
    """A tiny DQN run with ``options`` (DQNConfig keys) counts its updates and evaluations,
    returns a policy and values for every state, and resumes from its checkpoint to a longer run."""
    from irdrc.agents.dqn import DQNConfig, NetworkConfig, train

    base = dict(
        num_envs=8,
        frames_per_batch=32,
        total_frames=320,
        init_random_frames=64,
        buffer_size=320,
        batch_size=16,
        updates_per_batch=2,
        network=NetworkConfig(hidden=(16,)),
    )
    cfg = DQNConfig(**base, **options)
    run = train(Params(), cfg, seed=0, eval_every_frames=160)
    # learning starts at 64 frames: (320 − 32)/32 = 9 batches × 2 updates
    assert run.updates == 18 and run.greedy.shape == (1, 352) and run.q.shape == (1, 352, 2)
    assert [e["env_steps"] for e in run.history] == [0, 160, 320]
    longer = DQNConfig(**{**base, "total_frames": 480}, **options)
    resumed = train(Params(), longer, seed=0, eval_every_frames=160, resume=run.state)
    assert resumed.env_steps == 480 and resumed.updates == 18 + 5 * 2
    assert [e["env_steps"] for e in resumed.history] == [0, 160, 320, 480]
