"""The learners on one stream (``irdrc.online``): posterior sampling, DQN, Q-learning; resume and
longer runs, number for number."""

from __future__ import annotations

import dataclasses
import io
import json
from typing import Any

import pytest
import torch

from irdrc.agents.base import Hooks
from irdrc.core.exact import exact_scorer
from irdrc.core.params import Params
from irdrc.online import configs
from irdrc.online.learners import make_learner
from irdrc.online.loop import learn_on_stream
from irdrc.online.safe import ConstrainedScorer

PAPER = Params()


def test_a_learner_is_made_from_its_profile_a_mapping_or_refused_by_name():
    """``make_learner`` takes the learner's profile type, keys over its profile, or None; an
    unknown name lists the learners, and another learner's config is named (it failed deep in the
    learner with an AttributeError)."""
    assert make_learner("qlearning", None, PAPER).cfg == configs.QLEARNING
    assert make_learner("qlearning", {"episodes": 7}, PAPER).cfg.episodes == 7
    with pytest.raises(ValueError, match=r"learner='posteror' must be one of dqn, dqn_paper"):
        make_learner("posteror", configs.POSTERIOR, PAPER)
    with pytest.raises(ValueError, match=r"learner=dqn takes a StreamDQNConfig .* not a Posterior"):
        make_learner("dqn", configs.POSTERIOR, PAPER)
    with pytest.raises(ValueError, match=r"algo\.lrr \(did you mean algo\.lr\?\)"):
        make_learner("dqn", {"lrr": 1e-3}, PAPER)


def test_posterior_sampling_draws_again_whenever_its_data_doubles():
    """Within the first episode after 1, 2, 4, …, 256 steps; afterwards at the doublings that fall
    inside an episode (512 = 400 + 112, 1024 = 800 + 224, 2048 = 2000 + 48)."""
    learner = make_learner("posterior", configs.learner_config("posterior", {}), PAPER, 0)
    assert learner.switches(0, 400) == (1, 2, 4, 8, 16, 32, 64, 128, 256)
    assert [learner.switches(e, 400) for e in (1, 2, 3, 5)] == [(112,), (224,), (), (48,)]


def test_a_plan_made_beside_the_acting_is_the_plan_waited_for_once_its_sweeps_are_done():
    """The same stream and draws to two posterior samplers, one that waits for each plan and one
    that makes it one sweep per step: the second acts on its coin until its first plan is ready,
    ``observe`` reports that step alone, and the plan is the first one's, in force after as many
    steps as its value iteration took sweeps. Its second plan, started from the first's values,
    is again the first learner's. Restored from a checkpoint, between two plans or while one is
    being made, it goes on as the original."""
    from irdrc.core.exact import value_iteration
    from irdrc.core.stream import VehicleStream

    persistent = Params.from_overrides({"env.stay_good.channel": 0.95, "env.stay_bad.channel": 0.9})
    wait = make_learner("posterior", configs.learner_config("posterior", {}), persistent, 3)
    cfg = configs.learner_config("posterior_anytime", {})
    beside = make_learner("posterior", cfg, persistent, 3)
    stream, sweeps = VehicleStream(persistent, 0), []
    solve = wait._solve

    def counted(est: Any) -> torch.Tensor:
        """The waiting learner's plan, the sweeps its value iteration took noted."""
        sweeps.append(value_iteration(wait.counts.model(est), gamma=0.99, tol=1e-6).iterations)
        return solve(est)

    wait._solve = counted
    s = stream.reset()

    def run(steps: int, *more: Any) -> list[bool]:
        """Radar steps shown to every learner; when each learner ``beside`` said a plan was ready."""
        nonlocal s
        said = []
        for _ in range(steps):
            out = stream.step(1)
            wait.observe(s, 1, out)
            said.append(bool(beside.observe(s, 1, out)))
            assert all(bool(other.observe(s, 1, out)) == said[-1] for other in more)
            s = out.state
        return said

    run(50)
    wait.switch(50), beside.switch(50)
    assert beside.plan is None and beside.behaviour().eq(0.5).all()
    said = run(sweeps[0] + 5)
    assert said.index(True) == sweeps[0] - 1 and said.count(True) == 1
    assert beside.plan == wait.plan and beside.lags == [sweeps[0]] and sweeps[0] > 5

    def restored() -> Any:
        """A learner from ``beside``'s checkpoint (through torch.save, as a checkpoint file is)."""
        buf = io.BytesIO()
        torch.save(beside.state_dict(), buf)
        buf.seek(0)
        learner = make_learner("posterior", cfg, persistent, 3)
        learner.load_state_dict(torch.load(buf, weights_only=True))
        return learner

    between = restored()  # no plan being made: the next starts from the last plan's values
    wait.switch(100), beside.switch(100), between.switch(100)
    making = restored()  # a plan being made
    first = beside.plan
    said = run(sweeps[1] + 5, between, making)
    assert said.count(True) == 1 and beside.plan == wait.plan != first
    for other in (between, making):
        assert other.plan == beside.plan and other.info() == beside.info()
    assert beside.info()["planning"]["plans_made_beside_acting"] == 2
    assert beside.lags[1] < sweeps[1]  # it started from the first plan's values


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


def tiny(name: str) -> object:
    base: dict[str, object] = {"episodes": 6}
    if name.startswith("dqn"):
        base.update(warmup_steps=100, batch_size=64, update_every=8, hidden=(16, 16))
    if name.startswith("safe"):
        base.update(target_miss=0.1)
    return configs.learner_config(name, base)


def numbers(rows: list[dict]) -> list[dict]:
    """A run's evaluations without their wall times: what two equal runs share number for number."""
    return [{k: v for k, v in r.items() if k != "wall_seconds"} for r in rows]


@pytest.mark.parametrize(
    "name",
    ["dqn", "dqn_paper", "posterior", "posterior_anytime", "qlearning", "safe", "safe_anytime"],
)
def test_a_resumed_run_is_the_uninterrupted_run(paper_scorer, name):
    """Checkpointed after 3 of 6 episodes (through torch.save / weights_only load, as a checkpoint
    file is), a resumed run's evaluations are the uninterrupted run's, number for number."""
    cfg = tiny(name)
    grader = ConstrainedScorer(paper_scorer, 0.1) if name.startswith("safe") else None
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
        paper_scorer,
        episodes=6,
        seed=5,
        hooks=hooks,
        greedy_scorer=grader,
    )
    assert saved["state"]["episode"] == 3
    resumed = learn_on_stream(
        make_learner(name, cfg, PAPER, 5),
        PAPER,
        paper_scorer,
        episodes=6,
        seed=5,
        resume=saved["state"],
        greedy_scorer=grader,
    )

    assert json.dumps(numbers(resumed.history)) == json.dumps(numbers(whole.history))
    assert resumed.episode_rewards == whole.episode_rewards


@pytest.mark.parametrize(
    "name",
    ["dqn", "dqn_paper", "posterior", "posterior_anytime", "qlearning", "safe", "safe_anytime"],
)
def test_a_longer_run_begins_as_the_shorter_one(paper_scorer, name):
    """Every schedule counts episodes, not the run (DQN's learning rate anneals over
    ``lr_decay_episodes``, 4 here): the first 3 episodes of a 6-episode run are a 3-episode run's,
    number for number (with DQN's rate annealed over the run, they differ from its first update)."""

    def history(episodes: int) -> list[dict]:
        cfg = dataclasses.replace(tiny(name), episodes=episodes)
        if name == "dqn":
            cfg = dataclasses.replace(cfg, lr_decay_episodes=4)
        grader = ConstrainedScorer(paper_scorer, 0.1) if name.startswith("safe") else None
        rec = learn_on_stream(
            make_learner(name, cfg, PAPER, 5),
            PAPER,
            paper_scorer,
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
    paper_scorer = exact_scorer(PAPER)
    cfg = configs.learner_config("dqn", algo)
    done = []
    hooks = Hooks(
        on_batch=lambda info: done.append(info["episodes"]),
        should_stop=lambda: bool(done) and done[-1] >= stop_after,
    )
    rec = learn_on_stream(
        make_learner("dqn", cfg, PAPER, seed),
        PAPER,
        paper_scorer,
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


def test_posterior_sampling_reaches_the_optimum_in_a_few_episodes(paper_scorer):
    """Told the model's form, it is ≥ 0.99 of the optimum within 10 episodes on the paper scenario
    (2 on this seed when measured) and its regret levels off: episodes 11–20 cost less than a fifth
    of the first ten (nothing at all on this seed when measured)."""
    cfg = configs.learner_config("posterior", {"episodes": 20})
    rec = learn_on_stream(
        make_learner("posterior", cfg, PAPER, 0), PAPER, paper_scorer, episodes=20
    )
    ratios = [r["optimality_ratio"] for r in rec.history]
    assert max(ratios[1:11]) >= 0.99
    regret = [r["regret"] for r in rec.history]
    assert regret[20] - regret[10] < (regret[10] - regret[0]) / 5
