"""The price of learning on one stream (``irdrc.online.ledger`` through ``learn_on_stream``): each
period scored exactly with the behaviour policy in force, beside the realised counts."""

from __future__ import annotations

import math
import random
import time

import pytest
import torch

from irdrc.core.exact import build_model, episodic_metrics, stationary_metrics
from irdrc.core.params import Params
from irdrc.online.loop import StreamLearner, learn_on_stream

PAPER = Params()


class Fixed(StreamLearner):
    """A learner that never learns: ε-greedy around a fixed table."""

    name = "fixed"

    def __init__(self, table: torch.Tensor, eps: float = 0.0, seed: int = 0) -> None:
        self.table, self.eps, self.rng = table.long(), eps, random.Random(seed)
        self.actions = self.table.tolist()

    def act(self, state: int) -> int:
        if self.eps and self.rng.random() < self.eps:
            return self.rng.randrange(2)
        return self.actions[state]

    def greedy(self) -> torch.Tensor:
        return self.table

    def behaviour(self) -> torch.Tensor:
        probs = torch.nn.functional.one_hot(self.table, 2).double()
        return (1 - self.eps) * probs + self.eps / 2


def test_always_radar_pays_its_hand_computed_price(paper_scorer):
    """Always radar for 5 episodes: regret (g* − g_radar)·2000 exactly, no missed event (a perfect
    radar), the floor the optimum's missed events per step × 2000."""
    model = paper_scorer.model
    radar = torch.ones(model.num_states, dtype=torch.int64)
    rec = learn_on_stream(Fixed(radar), PAPER, paper_scorer, episodes=5)
    row = rec.history[-1]
    g_star = stationary_metrics(model, paper_scorer.optimal.policy).avg_reward
    g_radar = stationary_metrics(model, "always_radar").avg_reward
    assert row["regret"] == pytest.approx((g_star - g_radar) * 2000, rel=1e-12)
    assert row["behaviour_ratio"] == pytest.approx(g_radar / g_star, rel=1e-12)
    assert row["expected_missed"] == 0.0 and row["realised_missed"] == 0.0
    mu = paper_scorer.model.stationary(
        torch.nn.functional.one_hot(paper_scorer.optimal.policy, 2).double()
    )
    comm = paper_scorer.optimal.policy == 0
    floor = float((mu * model.event * comm).sum()) * 2000  # the optimum misses what comm meets
    assert floor > 0 and row["floor_missed"] == pytest.approx(floor, rel=1e-9)
    assert [r["episodes"] for r in rec.history] == list(range(6))


def test_the_ledger_scores_the_behaviour_policy_not_the_greedy_one(paper_scorer):
    """ε = 0.5 around the optimum: the regret is the mixture's, (g* − g(π_ε))·steps. Scoring the
    greedy policy instead (the mutation) would give 0, which the hand value tells apart."""
    model = paper_scorer.model
    g_star = paper_scorer.optimal_metrics.avg_reward
    mix = 0.5 * torch.nn.functional.one_hot(paper_scorer.optimal.policy, 2).double() + 0.25
    hand = (g_star - stationary_metrics(model, mix).avg_reward) * 1200

    def regret(mutate: bool) -> float:
        learner = Fixed(paper_scorer.optimal.policy, eps=0.5)
        if mutate:
            learner.behaviour = learner.greedy
        return learn_on_stream(learner, PAPER, paper_scorer, episodes=3).history[-1]["regret"]

    assert regret(False) == pytest.approx(hand, rel=1e-12)
    assert hand > 100 and not math.isclose(regret(True), hand, rel_tol=1e-3)


class Switching(Fixed):
    """Radar for the first 100 steps of every episode, then the optimum: it announces the change."""

    def __init__(self, optimum: torch.Tensor) -> None:
        super().__init__(torch.ones_like(optimum))
        self.optimum = optimum

    def begin_episode(self, episode: int) -> None:
        self.table = torch.ones_like(self.optimum)
        self.actions = self.table.tolist()

    def switches(self, episode: int, horizon: int) -> tuple[int, ...]:
        return (100,)

    def switch(self, steps: int) -> None:
        self.table = self.optimum.clone()
        self.actions = self.table.tolist()


class Ready(Switching):
    """The same change, made when a plan comes ready: ``observe`` says so after the 100th step,
    without announcing it."""

    def switches(self, episode: int, horizon: int) -> tuple[int, ...]:
        return ()

    def observe(self, state, action, step) -> bool | None:
        self.seen = getattr(self, "seen", 0) + 1
        if self.seen % 400 == 100:
            self.switch(self.seen)
            return True
        return None


@pytest.mark.parametrize("learner", [Switching, Ready], ids=["announced", "reported"])
def test_the_ledger_scores_each_period_with_its_policy(paper_scorer, learner):
    """Radar for 100 steps then the optimum for 300, in each of 3 episodes, the change announced
    (``switches``) or reported as it happens (``observe`` returns True): the regret is
    3·100·(g* − g_radar), the optimum's periods costing nothing. Scoring each episode with its
    start's policy (the mutations: switches ignored by the ledger, or ``observe``'s return not
    read by the loop) would give 3·400·(g* − g_radar)."""
    g_star = paper_scorer.optimal_metrics.avg_reward
    g_radar = stationary_metrics(paper_scorer.model, "always_radar").avg_reward
    rec = learn_on_stream(learner(paper_scorer.optimal.policy), PAPER, paper_scorer, episodes=3)
    row = rec.history[-1]
    assert row["regret"] == pytest.approx(300 * (g_star - g_radar), rel=1e-12)
    assert row["behaviour_ratio"] == pytest.approx(1.0, rel=1e-12)
    assert sum(e["reward"] for e in rec.episode_rewards) == pytest.approx(row["realised_reward"])


def test_switches_that_do_not_rise_within_the_episode_are_refused(paper_scorer):
    learner = Switching(paper_scorer.optimal.policy)
    learner.switches = lambda episode, horizon: (100, 50)
    with pytest.raises(ValueError, match="must rise within"):
        learn_on_stream(learner, PAPER, paper_scorer, episodes=1)


def test_realised_counts_match_the_exact_episodic_expectation(paper_scorer):
    """Over 300 episodes of the optimal policy, the realised reward and missed events are within
    5 standard errors (from the episodes' own spread) of the exact episodic expectation (episodes
    from a uniform reset: what the stream's episodes are)."""
    model = build_model(PAPER)
    policy = paper_scorer.optimal.policy
    K, T = 300, PAPER.env.horizon
    rec = learn_on_stream(
        Fixed(policy), PAPER, paper_scorer, episodes=K, seed=3, eval_every_frames=T * K
    )
    per = torch.tensor([e["reward"] for e in rec.episode_rewards], dtype=torch.float64)
    ep = episodic_metrics(model, policy)
    row = rec.history[-1]
    se = float(per.std()) * math.sqrt(K)
    assert abs(row["realised_reward"] - ep.avg_reward * K * T) < 5 * se
    assert row["realised_reward"] == pytest.approx(float(per.sum()), rel=1e-12)
    # the optimum's own regret is exactly 0; its realised regret is g*·steps − the rewards, whose
    # expectation is the resets' transient (an episode from a uniform state earns another amount)
    g_star = paper_scorer.optimal_metrics.avg_reward
    assert row["regret"] == pytest.approx(0.0, abs=1e-6)
    assert row["realised_regret"] == pytest.approx(g_star * K * T - row["realised_reward"])
    assert abs(row["realised_regret"] - (g_star - ep.avg_reward) * K * T) < 5 * se


class Slow(Fixed):
    """``Fixed`` with the learner's work slowed where a decision waits on it (an ``observe``, the
    work between two episodes) and where it does not (the tables the exact scoring reads)."""

    def __init__(self, table: torch.Tensor) -> None:
        super().__init__(table)
        self.seen = 0

    def observe(self, state: int, action: int, step) -> None:
        self.seen += 1
        if self.seen == 10:
            time.sleep(0.02)

    def end_episode(self, episode: int) -> dict[str, float]:
        time.sleep(0.01 if episode == 0 else 0.0)
        return {}

    def begin_episode(self, episode: int) -> None:
        time.sleep(0.04 if episode == 1 else 0.0)

    def behaviour(self) -> torch.Tensor:
        time.sleep(0.1)
        return super().behaviour()

    def greedy(self) -> torch.Tensor:
        time.sleep(0.1)
        return super().greedy()


def test_each_decision_is_timed_as_the_vehicle_waits_for_it(paper_scorer):
    """The 10th step's ``observe`` (20 ms) delays one decision; the work between episodes 0 and 1
    (10 + 40 ms) delays the first of episode 1: 50 ms, the slowest. The ``behaviour`` and
    ``greedy`` tables the exact scoring reads (100 ms each) delay none: counted, the slowest would
    be 150 ms (the bound below leaves 95 ms for a busy machine). A resumed run keeps the count."""
    radar = torch.ones(PAPER.env.num_states, dtype=torch.int64)
    rec = learn_on_stream(Slow(radar), PAPER, paper_scorer, episodes=2)
    assert 0.05 <= rec.info["seconds_slowest_decision"] < 0.145
    assert rec.info["decisions_over_1ms"] >= 2
    on = learn_on_stream(Fixed(radar), PAPER, paper_scorer, episodes=3, resume=rec.state)
    assert on.info["seconds_slowest_decision"] >= 0.05
    assert on.info["decisions_over_1ms"] >= rec.info["decisions_over_1ms"]
