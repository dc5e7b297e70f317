"""Policies, evaluation aggregation, and vectorised tabular Q-learning."""

from __future__ import annotations

import math
from dataclasses import asdict, replace

import pytest
import torch
from conftest import load

from irdrc import DFRCEnv, Params
from irdrc.agents.base import PROGRESS_FIELDS
from irdrc.agents.configs import QLearningConfig
from irdrc.agents.qlearning import DEFAULT, PAPER, train
from irdrc.core import policies
from irdrc.core.evaluate import evaluate, ratio_ci
from irdrc.core.exact import Scorer as ExactScorer
from irdrc.core.exact import build_model


def test_round_robin_alternates_from_each_reset():
    env = DFRCEnv(Params.from_overrides({"env.horizon": 5}), batch_size=[3], seed=0)
    td = env.rollout(10, policies.round_robin(), break_when_any_done=False)
    assert td["action"][0].tolist() == [0, 1, 0, 1, 0, 0, 1, 0, 1, 0]
    td = env.rollout(4, policies.round_robin(first=1), break_when_any_done=False)
    assert td["action"][0].tolist() == [1, 0, 1, 0]


def test_table_and_constant_policies():
    env = DFRCEnv(Params(), batch_size=[64], seed=0)
    table = torch.randint(0, 2, (352,), generator=torch.Generator().manual_seed(1))
    td = env.rollout(20, policies.table_policy(table))
    assert torch.equal(td["action"], table[td["state"]])
    assert not bool(env.rollout(5, policies.always_comm())["action"].any())
    assert bool(env.rollout(5, policies.always_radar())["action"].all())
    with pytest.raises(ValueError):
        policies.table_policy(torch.full((352,), 2))


def test_random_policy_rate():
    env = DFRCEnv(Params(), batch_size=[4000], seed=0)
    a = env.rollout(10, policies.uniform_random(p_radar=0.3, seed=1))["action"].double()
    # 40 000 Bernoulli(0.3) draws: sd of the mean is 0.0023; 5 sd = 0.0115
    assert abs(a.mean().item() - 0.3) < 0.0115


def test_ratio_ci_is_ratio_of_sums():
    # per-episode (missed, events): a ratio of sums, not a mean of ratios (episode 3 has no event)
    missed = torch.tensor([1.0, 3.0, 0.0, 2.0])
    events = torch.tensor([2.0, 4.0, 0.0, 2.0])
    r, ci = ratio_ci(missed, events)
    assert r == pytest.approx(6 / 8)
    assert ci > 0
    assert math.isnan(ratio_ci(missed, torch.zeros(4))[0])


def test_evaluate_counts_and_ci_coverage():
    env = DFRCEnv(Params.from_overrides({"env.horizon": 50}), batch_size=[100], seed=3)
    ev = evaluate(policies.round_robin(), env, episodes=250)
    assert ev.episodes == 300 and ev.steps == 300 * 50  # rounded up to whole batches
    assert ev.metrics.radar_fraction == 0.5 and ev.ci95["radar_fraction"] == 0
    assert ev.metrics.episode_reward == pytest.approx(50 * ev.metrics.avg_reward)


def test_config_validation():
    with pytest.raises(ValueError, match=r"algo\.gamma"):
        QLearningConfig(gamma=1.0)
    with pytest.raises(ValueError, match=r"algo\.alpha_schedule"):
        QLearningConfig(alpha_schedule="linear")
    with pytest.raises(ValueError, match=r"algo\.bogus"):
        QLearningConfig.from_dict({"bogus": 1})
    assert PAPER.epsilon(0) == PAPER.epsilon(2000) == 0.1
    cfg = QLearningConfig(epsilon_start=1.0, epsilon_end=0.0, epsilon_decay_episodes=10)
    assert cfg.epsilon(5) == pytest.approx(0.5) and cfg.epsilon(10) == 0.0


@pytest.mark.parametrize(("name", "profile"), [("qlearning", DEFAULT), ("qlearning_paper", PAPER)])
def test_yaml_profiles_match_code(name, profile):
    """The composed profile (Hydra defaults included) is the code's."""
    got = load("qlearning", f"algo={name}").algo
    assert got == profile and got.name == profile.name, asdict(profile)


def test_learners_are_independent_and_reproducible():
    p = Params()
    cfg = QLearningConfig(episodes=3)
    scorer = ExactScorer(build_model(p), cfg.gamma)
    a = train(p, cfg, num_learners=3, seed=0, scorers=scorer, eval_every_frames=400)
    b = train(p, cfg, num_learners=3, seed=0, scorers=scorer, eval_every_frames=400)
    assert torch.equal(a.q, b.q)
    assert not torch.equal(a.q[0], a.q[1])
    # 4 evaluations (0, 400, 800, 1200 env steps) of each of the 3 learners, one schema
    assert len(a.history) == 12 and [r["env_steps"] for r in a.curve(2)] == [0, 400, 800, 1200]
    assert set(a.history[0]) == set(PROGRESS_FIELDS)
    assert len(a.episode_rewards) == 9 and a.episode_rewards[-1]["episode"] == 3


def test_q_update_is_the_tabular_rule():
    # One learner, one step per episode (horizon 1), constant α: after one update from Q = 0 the
    # visited entry is α · r exactly (max over a zero next row is 0), and nothing else moved.
    p = Params.from_overrides({"env.horizon": 1})
    cfg = QLearningConfig(episodes=1, alpha=0.5, alpha_schedule="constant")
    res = train(p, cfg, num_learners=1, seed=5)
    nz = res.q.flatten().nonzero().flatten()
    assert nz.numel() <= 1
    if nz.numel():
        r = res.episode_rewards[0]["reward"]
        assert float(res.q.flatten()[nz[0]]) == pytest.approx(0.5 * r)


def test_first_reaching():
    from irdrc.agents.base import RunRecord

    rec = RunRecord(method="x", greedy=torch.zeros(1, 352, dtype=torch.long))
    rec.history = [
        {"learner": 0, "env_steps": 0, "optimality_ratio": 0.2},
        {"learner": 0, "env_steps": 400, "optimality_ratio": 0.99},
        {"learner": 1, "env_steps": 0, "optimality_ratio": 0.999},
    ]
    assert rec.first_reaching(0.95) == 400 and rec.first_reaching(0.995) is None
    assert rec.first_reaching(0.995, learner=1) == 0


@pytest.mark.slow
def test_default_profile_reaches_98_percent():
    res = train(Params(), DEFAULT, num_learners=3, seed=0)
    final = [res.curve(n)[-1]["optimality_ratio"] for n in range(3)]
    assert min(final) >= 0.98, final


@pytest.mark.e2e
def test_scenarios_trained_in_one_batch_learn_their_own_optimum():
    """Two scenarios with different optimal policies in one batch: each row learns its own.

    With r3 = r4 = 0 radar earns nothing and the optimum communicates in every state; with the
    paper's weights it communicates only in the calm states. Each optimum scores 0.64 and −0.31 of
    the other scenario's optimum, so rows fed the wrong scenario's tables fail the 0.9 asked here,
    which 100 episodes of the default profile clear on every row (0.93–1.0 measured, seeds 0–4).
    """
    scenarios = [Params(), Params.from_overrides({"reward.r3": 0, "reward.r4": 0})]
    res = train(scenarios, replace(DEFAULT, episodes=100), num_learners=2, seed=0)
    assert res.group == [0, 0, 1, 1] and res.greedy.shape == (4, 352)
    scorers = [ExactScorer(build_model(p), 0.99) for p in scenarios]
    for n in range(4):
        own = scorers[res.group[n]]
        assert own.ratio(res.greedy[n]) >= 0.9, n
        assert res.curve(n)[-1]["optimality_ratio"] == pytest.approx(own.ratio(res.greedy[n]))
    assert scorers[1].ratio(scorers[0].optimal.policy) < 0.7
    assert scorers[0].ratio(scorers[1].optimal.policy) < 0
    with pytest.raises(ValueError, match="horizon"):
        train([Params(), Params.from_overrides({"env.horizon": 10})], DEFAULT)
