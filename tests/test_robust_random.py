"""The default DQN on scenarios nobody tuned it for (``irdrc.bench.random_scenarios``): the
slow tier trains it on a handful of contested random draws and holds each final greedy policy to
0.99 of the exact optimum."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from irdrc.agents.configs import DQNConfig
from irdrc.agents.configs.value import DEFAULT_NETWORK
from irdrc.bench.random_scenarios import contested_draws, draw_overrides
from irdrc.core.exact import Scorer, build_model
from irdrc.core.params import Params

FIRST_HELD_OUT = 1000
"""Draws from here up were first seen by a benchmark, not by a choice of default; the first three
contested ones (this file's) were never screened for one."""
SAMPLED_REWARDS = dataclasses.replace(
    DQNConfig(),
    num_envs=1000,
    frames_per_batch=2000,
    total_frames=500_000,
    batch_size=1000,
    updates_per_batch=4,
    reward_means=False,
    network=DEFAULT_NETWORK,
)
"""DQN on the sampled rewards (no reward table), 64-64, on 1 000 rows for 500 000 env steps: a
run short and noisy enough that how the rewards are centred decides where it ends."""
CENTERING = 1261
"""A draw where centering on the collected rewards alone ends at 0.7824
(seed 5; r3 = 60.7 against r1 = 1.23 and r4 = 0.373; radar where the optimum sends): exploring rows
that send in the dangerous states pull the collected rewards' average r̄ to −0.29 where the optimum
earns 0.19, the values the network fits sit ~48 above the optimum's, and the rarely sampled sends
lag behind their climb (docs/DQN.md); following the values keeps them near zero."""


def final_ratio(index: int, cfg: DQNConfig, seed: int = 5, *, rewards: bool = True) -> float:
    """The final greedy policy's exact ratio on draw ``index``; ``rewards=False`` trains on the
    draw with the paper's reward weights (the mutation) and still scores it on the draw's. One
    thread, whatever the caller's: a run's numbers depend on the thread count (draw 3888, seed 5
    ends at 0.8144 with one and 0.9943 with two), and the docs' screens ran with one."""
    from irdrc.agents.dqn import train

    overrides = draw_overrides(index)
    params = Params.from_overrides(overrides)
    scorer = Scorer(build_model(params))
    if not rewards:
        overrides = {k: v for k, v in overrides.items() if not k.startswith("reward.")}
    learn = Params.from_overrides(overrides)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rec = train(
            learn,
            cfg,
            seed=seed,
            scorer=scorer if rewards else None,
            eval_every_frames=cfg.total_frames,
        )
    finally:
        torch.set_num_threads(threads)
    return scorer.ratio(rec.greedy[0])


@pytest.mark.slow
def test_the_default_dqn_holds_on_random_contested_scenarios():
    """The first three contested draws from ``FIRST_HELD_OUT`` (none of them looked at when
    choosing the default), seed 5: every final greedy policy ≥ 0.99 of its
    exact optimum. (The benchmark lists the draws from ``REPORTING`` up where it falls short:
    docs/BENCHMARKS.md.)"""
    draws = [d.index for d in contested_draws(FIRST_HELD_OUT, 3)]
    ratios = {i: final_ratio(i, DQNConfig()) for i in draws}
    assert all(r >= 0.99 for r in ratios.values()), ratios


@pytest.mark.slow
def test_a_learner_blind_to_the_scenarios_rewards_fails_there():
    """The mutation the test above guards against: DQN trained on draw 1007's dynamics with the
    paper's reward weights (r3 = 50 where the draw's is 0.186) is scored on the draw's own rewards
    and ends below the bar the test above holds the default to (0.9069 today)."""
    assert final_ratio(1007, DQNConfig(), rewards=False) < 0.99


@pytest.mark.slow
def test_centering_on_the_values_holds_where_centering_on_the_rewards_falls_short():
    """On the sampled rewards (``SAMPLED_REWARDS``), ``algo.center_on=values`` (r̄ moved by (1 − γ)
    times the network's value level after every batch) ends at the optimum on draw 1261; with r̄
    the collected rewards' average alone (``center_on=rewards``) it chooses radar where the
    optimum sends. The default holds there (with either centering: the reward table over 8 000 rows
    holds on 1261 with r̄ on the rewards too)."""
    assert final_ratio(CENTERING, DQNConfig()) >= 0.99
    assert final_ratio(CENTERING, SAMPLED_REWARDS) >= 0.99
    assert final_ratio(CENTERING, dataclasses.replace(SAMPLED_REWARDS, center_on="rewards")) < 0.99
