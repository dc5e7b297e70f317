"""One vehicle on the road (``irdrc.online``): the price of learning, the loop, its learners."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import random

import pytest
import torch

from irdrc.agents.base import Hooks
from irdrc.core.exact import build_model, episodic_metrics, exact_scorer, stationary_metrics
from irdrc.core.params import Params
from irdrc.online import configs
from irdrc.online.learners import make_learner
from irdrc.online.loop import StreamLearner, learn_on_stream
from irdrc.online.safe import ConstrainedScorer, SafeLearner

PAPER = Params()


@pytest.fixture(scope="module")
def scorer():
    return exact_scorer(PAPER)


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


def test_always_radar_pays_its_hand_computed_price(scorer):
    """Always radar for 5 episodes: regret (g* − g_radar)·2000 exactly, no missed event (a perfect
    radar), the floor the optimum's missed events per step × 2000."""
    model = scorer.model
    radar = torch.ones(model.num_states, dtype=torch.int64)
    rec = learn_on_stream(Fixed(radar), PAPER, scorer, episodes=5)
    row = rec.history[-1]
    g_star = stationary_metrics(model, scorer.optimal.policy).avg_reward
    g_radar = stationary_metrics(model, "always_radar").avg_reward
    assert row["regret"] == pytest.approx((g_star - g_radar) * 2000, rel=1e-12)
    assert row["behaviour_ratio"] == pytest.approx(g_radar / g_star, rel=1e-12)
    assert row["expected_missed"] == 0.0 and row["realised_missed"] == 0.0
    events = float((model.event * 1.0).sum())  # placeholder to keep the names apart below
    mu = scorer.model.stationary(torch.nn.functional.one_hot(scorer.optimal.policy, 2).double())
    comm = scorer.optimal.policy == 0
    floor = float((mu * model.event * comm).sum()) * 2000  # the optimum misses what comm meets
    assert events > 0 and row["floor_missed"] == pytest.approx(floor, rel=1e-9)
    assert [r["episodes"] for r in rec.history] == list(range(6))


def test_the_ledger_scores_the_behaviour_policy_not_the_greedy_one(scorer):
    """ε = 0.5 around the optimum: the regret is the mixture's, (g* − g(π_ε))·steps. Scoring the
    greedy policy instead (the mutation) would give 0, which the hand value tells apart."""
    model = scorer.model
    g_star = scorer.optimal_metrics.avg_reward
    mix = 0.5 * torch.nn.functional.one_hot(scorer.optimal.policy, 2).double() + 0.25
    hand = (g_star - stationary_metrics(model, mix).avg_reward) * 1200

    def regret(mutate: bool) -> float:
        learner = Fixed(scorer.optimal.policy, eps=0.5)
        if mutate:
            learner.behaviour = learner.greedy
        return learn_on_stream(learner, PAPER, scorer, episodes=3).history[-1]["regret"]

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


def test_the_ledger_scores_each_announced_period_with_its_policy(scorer):
    """Radar for 100 steps then the optimum for 300, in each of 3 episodes: the regret is
    3·100·(g* − g_radar), the optimum's periods costing nothing. Scoring each episode with its
    start's policy (the mutation: switches ignored by the ledger) would give 3·400·(g* − g_radar)."""
    g_star = scorer.optimal_metrics.avg_reward
    g_radar = stationary_metrics(scorer.model, "always_radar").avg_reward
    rec = learn_on_stream(Switching(scorer.optimal.policy), PAPER, scorer, episodes=3)
    row = rec.history[-1]
    assert row["regret"] == pytest.approx(300 * (g_star - g_radar), rel=1e-12)
    assert row["behaviour_ratio"] == pytest.approx(1.0, rel=1e-12)
    assert sum(e["reward"] for e in rec.episode_rewards) == pytest.approx(row["realised_reward"])


def test_posterior_sampling_draws_again_whenever_its_data_doubles():
    """Within the first episode after 1, 2, 4, …, 256 steps; afterwards at the doublings that fall
    inside an episode (512 = 400 + 112, 1024 = 800 + 224, 2048 = 2000 + 48)."""
    learner = make_learner("posterior", configs.learner_config("posterior", {}), PAPER, 0)
    assert learner.switches(0, 400) == (1, 2, 4, 8, 16, 32, 64, 128, 256)
    assert [learner.switches(e, 400) for e in (1, 2, 3, 5)] == [(112,), (224,), (), (48,)]


def test_a_gain_never_shown_is_planned_as_the_largest_reward_seen():
    """Radar steps only: no comm reward has shown, so each level's is planned as the largest
    |reward| seen (a detection's r4·(b + 1) or a miss); planned as 0 (the mutation), a learner
    that stopped its coin early would never try comm where it pays."""
    from irdrc.core.stream import VehicleStream
    from irdrc.online.form import FormCounts

    counts, stream = FormCounts(PAPER, 1.0), VehicleStream(PAPER, 0)
    s = stream.reset()
    for _ in range(400):
        out = stream.step(1)
        counts.observe(s, 1, out)
        s = out.state
    est = counts.estimate()
    assert counts.top_reward > 0 and counts.comm_reward == [None, None]
    assert est.comm_reward.tolist() == [counts.top_reward] * 2
    assert est.miss_penalty == 0.0 and est.packets.min() > 0


def test_switches_that_do_not_rise_within_the_episode_are_refused(scorer):
    learner = Switching(scorer.optimal.policy)
    learner.switches = lambda episode, horizon: (100, 50)
    with pytest.raises(ValueError, match="must rise within"):
        learn_on_stream(learner, PAPER, scorer, episodes=1)


def test_realised_counts_match_the_exact_episodic_expectation(scorer):
    """Over 300 episodes of the optimal policy, the realised reward and missed events are within
    5 standard errors (from the episodes' own spread) of the exact episodic expectation (episodes
    from a uniform reset: what the stream's episodes are)."""
    model = build_model(PAPER)
    policy = scorer.optimal.policy
    K, T = 300, PAPER.env.horizon
    rec = learn_on_stream(Fixed(policy), PAPER, scorer, episodes=K, seed=3, eval_every_frames=T * K)
    per = torch.tensor([e["reward"] for e in rec.episode_rewards], dtype=torch.float64)
    ep = episodic_metrics(model, policy)
    row = rec.history[-1]
    se = float(per.std()) * math.sqrt(K)
    assert abs(row["realised_reward"] - ep.avg_reward * K * T) < 5 * se
    assert row["realised_reward"] == pytest.approx(float(per.sum()), rel=1e-12)
    # the optimum's own regret is exactly 0; its realised regret is g*·steps − the rewards, whose
    # expectation is the resets' transient (an episode from a uniform state earns another amount)
    g_star = scorer.optimal_metrics.avg_reward
    assert row["regret"] == pytest.approx(0.0, abs=1e-6)
    assert row["realised_regret"] == pytest.approx(g_star * K * T - row["realised_reward"])
    assert abs(row["realised_regret"] - (g_star - ep.avg_reward) * K * T) < 5 * se


def tiny(name: str) -> object:
    base = {"episodes": 6}
    if name.startswith("dqn"):
        base.update(warmup_steps=100, batch_size=64, update_every=8, hidden=(16, 16))
    if name == "safe":
        base.update(target_miss=0.1)
    return configs.learner_config(name, base)


def numbers(rows: list[dict]) -> list[dict]:
    """A run's evaluations without their wall times: what two equal runs share number for number."""
    return [{k: v for k, v in r.items() if k != "wall_seconds"} for r in rows]


@pytest.mark.parametrize("name", ["dqn", "dqn_paper", "posterior", "qlearning", "safe"])
def test_a_resumed_run_is_the_uninterrupted_run(scorer, name):
    """Checkpointed after 3 of 6 episodes (through torch.save / weights_only load, as a checkpoint
    file is), a resumed run's evaluations are the uninterrupted run's, number for number."""
    cfg = tiny(name)
    grader = ConstrainedScorer(scorer, 0.1) if name == "safe" else None
    saved = {}

    def keep(state):
        buf = io.BytesIO()
        torch.save(state, buf)
        buf.seek(0)
        saved["state"] = torch.load(buf, weights_only=True)

    hooks = Hooks(on_checkpoint=keep, checkpoint_every_frames=1200)
    whole = learn_on_stream(
        make_learner(name, cfg, PAPER, 5),
        PAPER,
        scorer,
        episodes=6,
        seed=5,
        hooks=hooks,
        greedy_scorer=grader,
    )
    assert saved["state"]["episode"] == 3
    resumed = learn_on_stream(
        make_learner(name, cfg, PAPER, 5),
        PAPER,
        scorer,
        episodes=6,
        seed=5,
        resume=saved["state"],
        greedy_scorer=grader,
    )

    assert json.dumps(numbers(resumed.history)) == json.dumps(numbers(whole.history))
    assert resumed.episode_rewards == whole.episode_rewards


@pytest.mark.parametrize("name", ["dqn", "dqn_paper", "posterior", "qlearning", "safe"])
def test_a_longer_run_begins_as_the_shorter_one(scorer, name):
    """Every schedule counts episodes, not the run (DQN's learning rate anneals over
    ``lr_decay_episodes``, 4 here): the first 3 episodes of a 6-episode run are a 3-episode run's,
    number for number (with DQN's rate annealed over the run, they differ from its first update)."""

    def history(episodes: int) -> list[dict]:
        cfg = dataclasses.replace(tiny(name), episodes=episodes)
        if name == "dqn":
            cfg = dataclasses.replace(cfg, lr_decay_episodes=4)
        grader = ConstrainedScorer(scorer, 0.1) if name == "safe" else None
        rec = learn_on_stream(
            make_learner(name, cfg, PAPER, 5),
            PAPER,
            scorer,
            episodes=episodes,
            seed=5,
            greedy_scorer=grader,
        )
        return numbers(rec.history)

    short, long = history(3), history(6)
    assert json.dumps(long[: len(short)]) == json.dumps(short)


@pytest.mark.parametrize("full", [True, False], ids=["every_state", "sample_states"])
@pytest.mark.parametrize("double", [True, False])
def test_the_one_stream_dqn_loss_is_the_td_mean_square_of_its_sample(double, full):
    """``StreamDQN.td_loss`` sums per (state, action) before the backward pass; its value and its
    gradient are the plain mean over the sample of (Q(s, a) − y)², y = r − r̄ + γ·Q_target(s′, a′),
    a′ the online network's choice (double DQN) or the target's own (``algo.double_dqn=false``),
    whether one pass covers every state or (above ``FULL_PASS_STATES``) the sample's states only.
    The sample repeats pairs, as replay samples do."""
    from irdrc.online.dqn import StreamDQN

    cfg = configs.learner_config("dqn", {"double_dqn": double})
    learner = StreamDQN(cfg, PAPER, seed=3)
    learner.full = full
    with torch.no_grad():  # a target that differs from the online network
        for p in learner.target.parameters():
            p.add_(0.3 * torch.randn_like(p))
    learner.center.value = 0.37
    g = torch.Generator().manual_seed(0)
    S = PAPER.env.num_states
    few = torch.randperm(S, generator=g)[:40]  # 40 states spread over S
    sample = torch.stack(
        [
            few[torch.randint(0, 40, (500,), generator=g)].double(),  # repeated pairs
            torch.randint(0, 2, (500,), generator=g).double(),
            torch.randn(500, generator=g, dtype=torch.float64) * 10,
            torch.randint(0, S, (500,), generator=g).double(),
        ],
        1,
    )
    loss = learner.td_loss(sample)
    grads = torch.autograd.grad(loss, list(learner.qnet.parameters()))

    s, a, s2 = sample[:, 0].long(), sample[:, 1].long(), sample[:, 3].long()
    q = learner.qnet(learner.obs)
    with torch.no_grad():
        q_target = learner.target(learner.obs)
        pick = (q if double else q_target)[s2].argmax(-1, keepdim=True)
        y = sample[:, 2].float() - 0.37 + cfg.gamma * q_target[s2].gather(1, pick).squeeze(1)
    plain = ((q[s, a] - y) ** 2).mean()
    expected = torch.autograd.grad(plain, list(learner.qnet.parameters()))
    # float32 sums of 500 squares of order 100: agreement to a few parts in 10^5
    assert float(loss.detach()) == pytest.approx(float(plain.detach()), rel=1e-4)
    for got, want in zip(grads, expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-3, atol=1e-5)


def test_above_full_pass_states_the_one_stream_dqn_acts_on_the_network_as_a_table_would():
    """Above ``FULL_PASS_STATES`` (a 200-packet queue: 6 432 states) an update passes only its
    sample's states, and between two full tables the vehicle's greedy action is its own state's
    pass: the same action as the whole table of the same network, in every state; its checkpoint
    holds no full pass."""
    from irdrc.online.dqn import FULL_PASS_STATES, StreamDQN

    params = Params.from_overrides({"env.queue_capacity": 200})
    assert params.env.num_states > FULL_PASS_STATES
    learner = StreamDQN(configs.learner_config("dqn", {"episodes": 2}), params, seed=0)
    assert not learner.full
    rec = learn_on_stream(learner, params, exact_scorer(params), episodes=2, seed=0)
    assert learner.updates > 0 and len(rec.history) == 3
    learner.eps, learner.table = 0.0, None
    acted = [learner.act(s) for s in range(0, params.env.num_states, 7)]
    assert learner.table is None  # acting made no table
    table = learner.values(online=True).argmax(-1)[::7].tolist()
    assert acted == table
    whole = learner.values(online=True).argmax(-1).tolist()
    assert learner.behaviour().argmax(-1).tolist() == whole  # what the ledger scores
    # no update makes a full pass here, so the checkpoint keeps none (it would only go stale)
    assert learner.state_dict()["last_values"] is None


def dqn_first_99(seed: int, stop_after: int, **algo) -> int | None:
    """The episode at which the default one-stream DQN's greedy policy first reaches 0.99 of the
    optimum on the paper scenario, its run of the default 300 episodes stopped after
    ``stop_after``; None if it did not."""
    scorer = exact_scorer(PAPER)
    cfg = configs.learner_config("dqn", algo)
    done = []
    hooks = Hooks(
        on_batch=lambda info: done.append(info["episodes"]),
        should_stop=lambda: bool(done) and done[-1] >= stop_after,
    )
    rec = learn_on_stream(
        make_learner("dqn", cfg, PAPER, seed),
        PAPER,
        scorer,
        episodes=cfg.episodes,
        seed=seed,
        hooks=hooks,
    )
    return next((r["episodes"] for r in rec.history if r["optimality_ratio"] >= 0.99), None)


@pytest.mark.slow
def test_the_one_stream_dqn_reaches_the_optimum_in_tens_of_episodes():
    """Seeds 12, 14 and 15 (3, 9 and 9 episodes to 0.99 when measured, as in the benchmark's
    200-episode runs): each ≥ 0.99 of the optimum within 40 episodes. The same run with a learning
    rate of 1e-7 (a DQN that cannot move off its initial network) does not reach it: the bar is
    not met by the initial policy."""
    assert all(dqn_first_99(seed, 40) is not None for seed in (12, 14, 15))
    assert dqn_first_99(12, 40, lr=1e-7, lr_end=1e-7) is None


def test_posterior_sampling_reaches_the_optimum_in_a_few_episodes(scorer):
    """Told the model's form, it is ≥ 0.99 of the optimum within 10 episodes on the paper scenario
    (2 on this seed when measured) and its regret levels off: episodes 11–20 cost less than a fifth
    of the first ten (nothing at all on this seed when measured)."""
    cfg = configs.learner_config("posterior", {"episodes": 20})
    rec = learn_on_stream(make_learner("posterior", cfg, PAPER, 0), PAPER, scorer, episodes=20)
    ratios = [r["optimality_ratio"] for r in rec.history]
    assert max(ratios[1:11]) >= 0.99
    regret = [r["regret"] for r in rec.history]
    assert regret[20] - regret[10] < (regret[10] - regret[0]) / 5


def comm_everywhere(learner: SafeLearner) -> None:
    """A plan that sends in every state (the budget alone keeps the misses down)."""
    learner._solve = lambda: torch.tensor([[1.0, 0.0]]).repeat(learner.num_states, 1)


def test_the_miss_budget_keeps_cumulative_miss_detection_under_the_target(scorer):
    """With a plan that sends everywhere, the budget alone holds the cumulative miss detection at
    or under m* = 0.1 at every evaluation; with the budget lifted (the mutation) it breaks."""
    cfg = configs.learner_config("safe", {"episodes": 5, "target_miss": 0.1})
    grader = ConstrainedScorer(scorer, 0.1)

    def worst(mutate: bool) -> float:
        learner = make_learner("safe", cfg, PAPER, 0)
        comm_everywhere(learner)
        if mutate:
            learner._may_send = lambda: True
        rec = learn_on_stream(learner, PAPER, scorer, episodes=5, greedy_scorer=grader)
        cum = [r["cumulative_miss_detection"] for r in rec.history[1:]]
        return max(c for c in cum if not math.isnan(c))

    assert worst(False) <= 0.1
    assert worst(True) > 0.5


def test_the_safe_learner_starts_in_radar_and_learns_to_send(scorer):
    """Its first episode is radar everywhere (no slack yet); within 10 episodes of the paper
    scenario at m* = 0.1 its plan sends more than half the LP's packets, with every evaluation's
    cumulative miss detection ≤ 0.1."""
    cfg = configs.learner_config("safe", {"episodes": 10, "target_miss": 0.1})
    grader = ConstrainedScorer(scorer, 0.1)
    rec = learn_on_stream(
        make_learner("safe", cfg, PAPER, 1), PAPER, scorer, episodes=10, greedy_scorer=grader
    )
    first = rec.history[1]
    assert first["realised_sent"] == 0 and first["realised_missed"] == 0
    assert all(r["cumulative_miss_detection"] <= 0.1 for r in rec.history[1:])
    assert rec.history[-1]["lp_ratio"] > 0.5


def test_the_safe_learner_plans_again_whenever_its_data_doubles(scorer):
    """Before episodes 0, 1, 2, 4 and 8 of 10: five LPs, and the plan is unchanged between them."""
    cfg = configs.learner_config("safe", {"episodes": 10, "target_miss": 0.1})
    learner = make_learner("safe", cfg, PAPER, 1)
    solved = []
    solve = learner._solve
    learner._solve = lambda: solved.append(learner.counts.steps) or solve()
    learn_on_stream(learner, PAPER, scorer, episodes=10)
    assert solved == [0, 400, 800, 1600, 3200] and learner.updates == 5


def test_the_safe_learner_plans_on_a_mixed_noisy_or_chain(scorer):
    """Its plan after 33 episodes at m* = 0.05 (seed 1) sends 0.899 of the LP's packets when
    measured; planning on the posterior mean of the sampler's cold start (the mutation: no sweeps
    before a plan) overstates the events and sends 0.828."""
    cfg = configs.learner_config("safe", {"episodes": 33, "target_miss": 0.05})
    grader = ConstrainedScorer(scorer, 0.05)

    def ratio(mutate: bool) -> float:
        learner = make_learner("safe", cfg, PAPER, 1)
        if mutate:
            learner.counts.advance = lambda rng, sweeps: None
        rec = learn_on_stream(learner, PAPER, scorer, episodes=33, greedy_scorer=grader)
        return rec.history[-1]["lp_ratio"]

    assert ratio(False) > 0.86 > ratio(True)


def test_the_safe_learner_states_its_confidence_in_the_plan(scorer):
    """``plan_confidence`` draws models from the posterior of the counts: after 32 episodes at
    m* = 0.1 (seed 1) the true long-run miss detection of the plan lies within 4 of its posterior
    sds of the draws' mean (4 sds leave room for a posterior somewhat narrower than the truth's
    spread), the spread is narrower than after 4 episodes (8× the data), and the learner's own
    sampler is left as it was. A plan that sends everywhere misses every event (probability 0 of
    meeting the target); radar everywhere, with P_d = 1, misses almost none (probability 1)."""
    cfg = configs.learner_config("safe", {"episodes": 32, "target_miss": 0.1})
    grader = ConstrainedScorer(scorer, 0.1)

    def learned(episodes: int) -> SafeLearner:
        learner = make_learner("safe", cfg, PAPER, 1)
        learn_on_stream(learner, PAPER, scorer, episodes=episodes)
        return learner

    late, early = learned(32), learned(4)
    fire = [f.copy() for f in late.counts.fire]
    conf = late.plan_confidence()
    assert all((a == b).all() for a, b in zip(fire, late.counts.fire, strict=True))
    true = grader.metrics(late.plan).miss_detection
    assert conf["miss_sd"] > 0 and abs(true - conf["miss_mean"]) <= 4 * conf["miss_sd"]
    assert conf["miss_sd"] < early.plan_confidence()["miss_sd"]
    assert conf == late.plan_confidence()  # drawn on a generator fixed by the data
    late.plan = torch.tensor([[1.0, 0.0]]).repeat(late.num_states, 1)
    assert late.plan_confidence(draws=5)["p_within_target"] == 0.0
    late.plan = torch.tensor([[0.0, 1.0]]).repeat(late.num_states, 1)
    radar = late.plan_confidence(draws=5)
    assert radar["p_within_target"] == 1.0 and radar["miss_mean"] < 0.01  # P_d drawn near 1
    with pytest.raises(ValueError, match="draws=1"):
        late.plan_confidence(draws=1)


def test_learner_keys_are_checked_against_the_chosen_learner():
    with pytest.raises(ValueError, match=r"algo.batch_sze \(did you mean algo.batch_size\?\)"):
        configs.learner_config("dqn", {"batch_sze": 3})
    with pytest.raises(ValueError, match=r"algo\.target_miss"):
        configs.learner_config("posterior", {"target_miss": 0.1})
    with pytest.raises(ValueError, match="learner='rainbow' must be one of"):
        configs.learner_config("rainbow", {})
    with pytest.raises(ValueError, match="learner=ppo is not a learner on one vehicle's stream"):
        configs.learner_config("ppo", {})
    with pytest.raises(ValueError, match=r"algo.hidden\[0\]"):
        configs.learner_config("dqn", {"hidden": [0]})
    assert dataclasses.replace(configs.DQN, episodes=5).epsilon(0) == configs.DQN.eps_start


def test_the_recipe_writes_the_ledger_everywhere(tmp_path, capsys):
    """``recipes/online.py`` in-process, 3 episodes of its default learner (posterior sampling):
    exit 0; the ledger in metrics.csv (a row per episode), summary.json and the printout; a
    checkpoint to resume from."""
    import csv

    from irdrc.online import recipe
    from irdrc.runs import app

    args = ["algo.episodes=3", f"hydra.run.dir={tmp_path}", "logger=none"]
    assert app.execute(recipe, [*args, "progress=false"]) == 0
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [int(r["episodes"]) for r in rows] == [0, 1, 2, 3]
    assert {"regret", "expected_missed", "floor_missed", "realised_missed"} <= set(rows[0])
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["learner"] == "posterior" and summary["episodes"] == 3
    assert summary["ledger"]["regret"] == pytest.approx(float(rows[-1]["regret"]))
    assert (tmp_path / "checkpoint.pt").is_file() and (tmp_path / "learning_curve.png").is_file()
    out = capsys.readouterr().out
    assert "the price of learning over 3 episodes" in out and "where the optimum misses" in out
    # nothing left to train at 3 episodes; a longer run goes on from the checkpoint
    resume = [f"resume={tmp_path / 'checkpoint.pt'}", "logger=none", "progress=false"]
    assert app.execute(recipe, resume) == 2
    assert "nothing left to train" in capsys.readouterr().err
    # … unless its files are gone (a crash while they were written): then it writes them again
    (tmp_path / "summary.json").unlink()
    assert app.execute(recipe, resume) == 0
    again = json.loads((tmp_path / "summary.json").read_text())
    assert again["episodes"] == 3 and again["ledger"] == summary["ledger"]
    assert app.execute(recipe, [*resume, "algo.episodes=5"]) == 0
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [int(r["episodes"]) for r in rows] == [0, 1, 2, 3, 4, 5]


@pytest.mark.parametrize(
    ("first", "stay", "words"),
    [
        (None, None, "never ≥ 0.99"),
        (1, None, "first ≥ 0.99 after 1 episode (the last evaluation)"),
        (4, 0.5, "first ≥ 0.99 after 4 episodes, ≥ 0.99 at 50% of the evaluations since"),
    ],
)
def test_the_printed_ledger_says_when_the_greedy_policy_first_reached_099(
    capsys, first, stay, words
):
    """The console's convergence clause, in words that agree with the count."""
    from types import SimpleNamespace

    from irdrc.online.recipe import print_ledger

    keys = ("regret", "realised_regret", "expected_missed", "realised_missed", "floor_missed")
    row = dict.fromkeys((*keys, "expected_sent", "realised_sent", "cumulative_miss_detection"), 1.0)
    summary = {"episodes_to_99": first, "stay_99": stay, "episodes": 6, "env_steps_per_second": 1.0}
    print_ledger(row, summary, SimpleNamespace(learner="posterior"))
    assert f"greedy policy: {words}\n" in capsys.readouterr().out


def test_the_safe_recipe_states_the_plans_confidence(tmp_path, capsys):
    """``learner=safe``: summary.json carries the LP, the plan's ratio to it and its stated
    confidence, and the printout says them."""
    from irdrc.online import recipe
    from irdrc.runs import app

    args = ["learner=safe", "algo.episodes=2", f"hydra.run.dir={tmp_path}", "logger=none"]
    assert app.execute(recipe, [*args, "progress=false"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    conf = summary["plan_confidence"]
    assert set(conf) == {"miss_mean", "miss_sd", "p_within_target", "draws"}
    assert 0.0 <= conf["p_within_target"] <= 1.0 and summary["lp"]["throughput"] > 0
    out = capsys.readouterr().out
    assert f"probability {conf['p_within_target']:.2f}" in out and "the LP's packets" in out
    # read against the LP, not the unconstrained optimum it is not meant to reach
    assert "of the optimum (below 0.99)" not in out
    assert summary["lp_ratio"] < 0.95  # two episodes of data: a plan far short of the LP …
    assert "of the LP's packets (below 0.95" in out  # … and the warning says so


def test_a_safe_run_is_not_told_it_fell_from_a_plan_that_broke_its_target(tmp_path, capsys):
    """Early in a ``learner=safe`` run the greedy plan can send more than the LP by breaking the
    target; the end warning reads the best only among the plans that met it."""
    import csv

    from irdrc.online import recipe
    from irdrc.runs import app

    args = ["learner=safe", "algo.target_miss=0.1", "algo.episodes=3", "logger=none"]
    assert app.execute(recipe, [*args, f"hydra.run.dir={tmp_path}", "progress=false"]) == 0
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    final = float(rows[-1]["lp_ratio"])
    # the case this test is about: an evaluation above the final plan that broke the target
    assert any(float(r["lp_ratio"]) > final + 0.1 and float(r["meets_target"]) == 0 for r in rows)
    out = capsys.readouterr().out
    assert f"{final:.4f} of the LP's packets (below 0.95)" in out and "below its best" not in out


def test_a_safe_run_is_warned_against_the_lp():
    from irdrc.online.recipe import SAFE_END_THRESHOLD
    from irdrc.runs.report import end_warning

    def warn(rows):
        return end_warning(
            rows,
            "algo.episodes=600",
            key="lp_ratio",
            threshold=SAFE_END_THRESHOLD,
            of="the LP's",
            best_among="meets_target",
        )

    def row(ratio, steps, meets=1.0):
        return {"lp_ratio": ratio, "env_steps": steps, "meets_target": meets}

    assert warn([row(0.5, 0), row(0.96, 400)]) is None
    warning = warn([row(0.96, 400), row(0.9, 800)])
    assert warning.startswith("warning: the final greedy policy is 0.9000 of the LP's (below 0.95")
    assert "its best evaluation was 0.9600 at 400 env steps" in warning
    assert warning.endswith("try algo.episodes=600")
    # a plan sending more than the LP breaks the target: it is no best the learner fell from
    early = warn([row(0.0, 0), row(1.2, 400, meets=0.0), row(0.93, 800)])
    assert "below 0.95)" in early and "below its best" not in early
    assert "its best evaluation was 0.9300 at 800 env steps" in early
    assert warn([row(0.0, 0), row(1.2, 400, meets=0.0), row(0.97, 800)]) is None
    never = warn([row(1.2, 400, meets=0.0), row(0.9, 800, meets=0.0)])
    assert "none of its evaluations had meets_target" in never


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["algo.batch_size=64"], "unknown key(s) algo.batch_size"),
        (["learner=dqn", "algo.batch_sze=64"], "did you mean algo.batch_size?"),
        (["learner=nobody"], "learner='nobody' must be one of"),
        (
            ["learner=sac"],
            "learner=sac is not a learner on one vehicle's stream: use python recipes/sac.py",
        ),
        (["learner=vdn"], "use python recipes/fleet.py learner=vdn"),
        (["learner=dqn_lagrangian"], "use python recipes/constrained.py learner=dqn_lagrangian"),
        (["env.actions=continuous"], "env.actions=continuous"),
        (["learner=safe", "algo.target_miss=1.5"], "algo.target_miss=1.5"),
    ],
)
def test_the_recipe_refuses_before_any_work(tmp_path, capsys, args, message):
    from irdrc.online import recipe
    from irdrc.runs import app

    run_dir = tmp_path / "run"
    code = app.execute(recipe, ["learner=posterior", *args, f"hydra.run.dir={run_dir}"])
    assert code == 2 and message in capsys.readouterr().err
    assert not run_dir.exists()


def test_onlines_own_learner_example_runs_as_printed_and_prints_what_the_page_says():
    """ONLINE.md's *Your own learner on one stream*: its code, run as printed in a fresh
    interpreter, prints exactly the line the page shows (the stream and the coin are seeded)."""
    import subprocess
    import sys
    from pathlib import Path

    page = (Path(__file__).parents[1] / "docs" / "ONLINE.md").read_text()
    section = page.split("## Your own learner on one stream\n", 1)[1].split("\n## ", 1)[0]
    code = section.split("```python\n", 1)[1].split("```", 1)[0]
    shown = section.split("```text\n", 1)[1].split("```", 1)[0].strip()
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.strip() == shown
