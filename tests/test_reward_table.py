"""The mean reward of each (observation, action) in place of the sampled one (``algo.reward_means``):
the table, what the loss sees, where it is refused, and its means against the exact model."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import TINY_ALGO, load
from tensordict import TensorDict

from irdrc import Params
from irdrc.agents import dqn as dqn_module
from irdrc.agents.configs import DQNConfig, LagrangianConfig
from irdrc.agents.dqn import train
from irdrc.agents.offpolicy import observation_top
from irdrc.agents.reward_table import RewardTable
from irdrc.core.env import DFRCEnv
from irdrc.core.exact import build_model

TINY = TINY_ALGO


def _batch(obs: list[list[int]], actions: list[int], rewards: list[float]) -> TensorDict:
    return TensorDict(
        {
            "observation": torch.tensor(obs, dtype=torch.float32),
            "action": torch.tensor(actions),
            ("next", "reward"): torch.tensor(rewards).reshape(-1, 1),
        },
        batch_size=[len(actions)],
    )


def test_every_observation_and_action_has_its_own_entry():
    env = DFRCEnv(Params(), batch_size=[2])
    obs = env.dynamics.obs  # every state's observation
    means = RewardTable(observation_top(env), 2)
    index = torch.cat([means.index(obs, torch.full((len(obs),), a)) for a in (0, 1)])
    assert index.unique().numel() == 2 * len(obs)
    assert int(index.min()) >= 0 and int(index.max()) < means.sums.numel()


def test_a_sample_reads_the_mean_of_every_collected_step_at_its_pair():
    means = RewardTable(torch.tensor([2.0, 1.0]), 2)
    means.add(_batch([[1, 0], [1, 0], [1, 0], [2, 1]], [0, 0, 1, 0], [1.0, -49.0, 3.0, 7.0]))
    means.add(_batch([[1, 0]], [0], [0.5]))
    sample = _batch([[1, 0], [1, 0], [2, 1]], [0, 1, 0], [1.0, 1.0, 1.0])
    got = means.apply(sample)["next", "reward"].flatten().tolist()
    assert got == pytest.approx([(1.0 - 49.0 + 0.5) / 3, 3.0, 7.0])


def test_the_means_converge_to_the_exact_expected_rewards():
    """Under random actions, each (state, action) mean of 200 000 simulated steps lies within
    5·sd/√n + 15·span/n of the exact model's R[a, s] wherever it has n ≥ 200 samples (sd the
    pair's sample spread, span the range of every reward seen). The first term is the normal
    tail: five standard errors over ~700 pairs, a false alarm below 10⁻³. The second covers what
    the sample spread cannot see: a reward of probability p appears Poisson(np) times, so when
    np > 15 it is absent with probability < e⁻¹⁵ (and then counted in sd), and when np ≤ 15 its
    whole weight in the mean is at most span·p ≤ 15·span/n. Fixed seeds: the same draws each run."""
    torch.manual_seed(0)  # the rollout's random actions
    params = Params()
    env = DFRCEnv(params, batch_size=[1000], seed=3)
    means = RewardTable(observation_top(env), 2)
    squares = torch.zeros_like(means.sums)
    data = env.rollout(200, break_when_any_done=False)
    means.add(data)
    reward = data["next", "reward"].reshape(-1).double()
    span = float(reward.max() - reward.min())
    at = means.index(data["observation"], data["action"])
    squares.index_add_(0, at, reward**2)
    R = build_model(params).R  # [A, S]
    obs = env.dynamics.obs
    checked = 0
    for a in (0, 1):
        at = means.index(obs, torch.full((len(obs),), a))
        n = means.counts[at]
        mean = means.sums[at] / n.clamp(min=1)
        sd = (squares[at] / n.clamp(min=1) - mean**2).clamp(min=0).sqrt()
        ok = n >= 200
        err = (mean - R[a]).abs()[ok]
        bound = 5 * sd[ok] / n[ok].sqrt() + 15 * span / n[ok]
        assert bool((err <= bound).all()), float((err - bound).max())
        checked += int(ok.sum())
    assert checked > 100


def test_dqn_learns_from_the_table_when_on_and_not_when_off(monkeypatch):
    made: list[RewardTable] = []
    applied: list[int] = []

    class Spy(RewardTable):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

        def apply(self, sample):
            applied.append(sample.numel())
            return super().apply(sample)

    monkeypatch.setattr(dqn_module, "RewardTable", Spy)
    run = train(Params(), DQNConfig(**TINY, reward_means=True), seed=0, eval_every_frames=320)
    assert len(made) == 1 and float(made[0].counts.sum()) == TINY["total_frames"]
    assert len(applied) == run.state["updates"] and set(applied) == {TINY["batch_size"]}
    train(Params(), DQNConfig(**TINY, reward_means=False), seed=0, eval_every_frames=320)
    assert len(made) == 1  # off: no table


def test_the_key_is_checked_and_the_learners_that_cannot_use_it_refuse_it():
    assert DQNConfig().reward_means is True  # DQN with a reward table: the default
    assert load("dqn", "algo.reward_means=false").algo.reward_means is False
    assert load("dqn").algo == DQNConfig()
    assert load("dqn", "algo.reward_means=true").algo.reward_means is True
    with pytest.raises(ValueError, match=r"algo\.reward_means"):
        DQNConfig(reward_means="yes")
    with pytest.raises(ValueError, match=r"algo\.reward_means=true: the fleet"):
        load("fleet", "algo.reward_means=true")
    with pytest.raises(ValueError, match=r"algo\.reward_means=true: the Lagrangian"):
        LagrangianConfig.from_sections({"reward_means": True})


def test_a_learners_partial_algo_mapping_keeps_its_own_shape():
    """The Lagrangian and the fleet keep the shapes they were measured with, on the sampled
    rewards: a mapping that leaves those keys out fills them from the learner's own default, not
    from DQN's (which reads the mean rewards the two refuse)."""
    from irdrc.agents.configs import FleetLearnerConfig

    lag = LagrangianConfig.from_sections({"lr": 1e-3})
    assert lag.dqn.lr == 1e-3 and lag.dqn == dataclasses.replace(LagrangianConfig().dqn, lr=1e-3)
    vdn = FleetLearnerConfig.from_sections("vdn", {"tau": 0.05})
    assert (vdn.dqn.num_envs, vdn.dqn.reward_means, vdn.dqn.tau) == (1000, False, 0.05)
    assert DQNConfig.from_sections({"lr": 1e-3}).reward_means is True  # DQN's own default
