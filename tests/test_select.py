"""Choosing DQN's final policy by its own measured returns (``algo.select_every_frames``):
``chain_rewards`` (common random numbers), ``Snapshots``, ``choose_final`` and the training loop."""

from __future__ import annotations

import math

import pytest
import torch

from irdrc import Params
from irdrc.agents.dqn import DQNConfig, train
from irdrc.agents.lagrangian import LagrangianConfig
from irdrc.agents.select import Snapshots, choose_final
from irdrc.core.evaluate import chain_rewards
from irdrc.core.model import build_model
from irdrc.core.solve import ExactScorer, stationary_metrics


@pytest.fixture(scope="module")
def paper():
    params = Params()
    return params, ExactScorer(build_model(params))


def _tables(scorer: ExactScorer) -> dict[str, torch.Tensor]:
    optimal = scorer.optimal.policy.reshape(-1).long()
    return {"optimal": optimal, "radar": torch.ones_like(optimal)}


def test_chain_rewards_match_the_exact_average_reward(paper):
    """Each row's chain means average to the exact stationary reward. The chains are independent
    (own start state, own random stream position), so their spread gives the standard error; four
    of them leave a false failure at ~6e-5."""
    params, scorer = paper
    tables = _tables(scorer)
    rows = chain_rewards(
        params, torch.stack(list(tables.values())), envs=256, steps=2000, burn_in=500, seed=3
    )
    assert rows.shape == (2, 256)
    for row, table in zip(rows, tables.values(), strict=True):
        exact = stationary_metrics(scorer.model, table).avg_reward
        se = float(row.std()) / math.sqrt(row.numel())
        assert abs(float(row.mean()) - exact) < 4 * se, (float(row.mean()), exact, se)


def test_chain_rewards_use_common_random_numbers(paper):
    """The same table twice gives identical chains (the random stream does not depend on the
    actions taken); another seed gives other chains."""
    params, scorer = paper
    optimal = _tables(scorer)["optimal"]
    same = chain_rewards(params, torch.stack([optimal, optimal]), envs=8, steps=300, seed=1)
    assert torch.equal(same[0], same[1])
    other_seed = chain_rewards(params, optimal[None], envs=8, steps=300, seed=2)
    assert not torch.equal(same[0], other_seed[0])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"envs": 1}, "envs >= 2"), ({"steps": 0}, "steps >= 1"), ({"burn_in": -1}, "burn_in")],
)
def test_chain_rewards_reject_bad_sizes(paper, kwargs, match):
    params, scorer = paper
    with pytest.raises(ValueError, match=match):
        chain_rewards(params, _tables(scorer)["optimal"][None], **kwargs)


def test_chain_rewards_reject_bad_tables(paper):
    params, _ = paper
    with pytest.raises(ValueError, match=r"\[K, 352\]"):
        chain_rewards(params, torch.zeros(3, 10, dtype=torch.long))
    with pytest.raises(ValueError, match="actions 0"):
        chain_rewards(params, torch.full((1, 352), 2))


def test_snapshots_are_due_every_period_from_after_on():
    snaps = Snapshots(every=1000, after=2500)
    due = [now for now in range(32, 6017, 32) if snaps.due(now - 32, now)]
    assert due == [3008, 4000, 5024, 6016]  # first batch end past each multiple ≥ 2 500
    assert not Snapshots(every=0, after=0).due(0, 10**6)


def test_snapshots_round_trip_through_their_state():
    snaps = Snapshots(every=10, after=0)
    snaps.take(10, torch.tensor([0, 1, 1]), torch.zeros(3, 2))
    copy = Snapshots(every=10, after=0)
    copy.load(snaps.state())
    assert copy.frames == [10] and torch.equal(copy.tables[0], snaps.tables[0])
    copy.pop()
    assert copy.frames == [] and copy.tables == [] and copy.values == []


def _snapshots(*tables: torch.Tensor) -> Snapshots:
    snaps = Snapshots(every=1000, after=0)
    for i, t in enumerate(tables):
        snaps.take(1000 * (i + 1), t, torch.zeros(t.numel(), 2))
    return snaps


MEASURE = {"envs": 64, "steps": 1000, "burn_in": 200, "z": 2.58, "seed": 0}


def test_a_clearly_better_earlier_table_replaces_a_trapped_last_one(paper):
    """The last table radars everywhere (0.42 of the optimum); the optimum taken earlier wins by
    dozens of standard errors."""
    params, scorer = paper
    t = _tables(scorer)
    index, facts = choose_final(params, _snapshots(t["radar"], t["optimal"], t["radar"]), **MEASURE)
    assert index == 1
    assert facts["select_chosen_frames"] == 2000 and facts["select_z"] > 10
    assert facts["select_candidates"] == 2  # the two radar snapshots are one candidate
    assert facts["select_env_steps"] == 2 * 64 * 1200


def test_the_last_table_stays_unless_something_is_significantly_better(paper):
    params, scorer = paper
    t = _tables(scorer)
    index, facts = choose_final(params, _snapshots(t["radar"], t["optimal"]), **MEASURE)
    assert index == 1 and facts["select_gain"] == 0.0  # worse earlier tables never replace it
    # The same clear win as above, asked to exceed an absurd margin: the last table stays.
    index, _ = choose_final(
        params, _snapshots(t["optimal"], t["radar"]), **{**MEASURE, "z": 1000.0}
    )
    assert index == 1


def test_one_distinct_table_costs_no_measurement(paper):
    params, scorer = paper
    t = _tables(scorer)
    index, facts = choose_final(params, _snapshots(t["optimal"], t["optimal"]), **MEASURE)
    assert index == 1 and facts["select_env_steps"] == 0 and facts["select_candidates"] == 1


SHORT = {
    "num_envs": 8,
    "frames_per_batch": 32,
    "total_frames": 1_024,
    "init_random_frames": 256,
    "buffer_size": 1_024,
    "batch_size": 64,
    "select_every_frames": 128,
    "select_after_frames": 256,
    "select_envs": 8,
    "select_steps": 50,
    "select_burn_in": 10,
}


def test_training_with_selection_counts_its_steps_and_keeps_a_snapshot(paper):
    params, scorer = paper
    run = train(params, DQNConfig(**SHORT), seed=0, eval_every_frames=512)
    info = run.info
    assert run.training_env_steps == 1_024
    assert run.env_steps == 1_024 + info["select_env_steps"] == 1_024 + run.measurement_env_steps
    assert info["select_env_steps"] == info["select_candidates"] * 8 * 60 * (
        info["select_candidates"] > 1
    )
    snaps = run.state["snapshots"]
    assert snaps["frames"] == [256, 384, 512, 640, 768, 896]  # the last table is not stored
    candidates = [*snaps["tables"], None]
    chosen = info["select_chosen_frames"]
    if chosen < 1_024:
        assert torch.equal(run.greedy[0], candidates[snaps["frames"].index(chosen)])
    assert info["selected_ratio"] == pytest.approx(scorer.ratio(run.greedy[0]))
    assert run.history[-1]["env_steps"] == 1_024  # the last network's exact score stays


def test_selection_off_by_default_and_resumed_runs_keep_their_snapshots(paper):
    params, _ = paper
    plain = train(params, DQNConfig(**{**SHORT, "select_every_frames": 0}), seed=0)
    assert "select_candidates" not in plain.info and "snapshots" not in plain.state
    assert DQNConfig().select_every_frames == 0
    first = train(params, DQNConfig(**{**SHORT, "total_frames": 640}), seed=0)
    assert first.state["snapshots"]["frames"] == [256, 384, 512]
    resumed = train(params, DQNConfig(**SHORT), seed=0, resume=first.state)
    assert resumed.state["snapshots"]["frames"][:3] == [256, 384, 512]
    assert resumed.state["snapshots"]["frames"][-1] == 896


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"select_every_frames": -1}, "select_every_frames"),
        ({"select_envs": 1}, "select_envs"),
        ({"select_steps": 0}, "select_steps"),
        ({"select_z": -1.0}, "select_z"),
        ({"select_every_frames": 100, "select_after_frames": 600_000}, "select_after_frames"),
    ],
)
def test_bad_selection_settings_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DQNConfig(**kwargs)


def test_the_lagrangian_learner_refuses_selection():
    with pytest.raises(ValueError, match="select_every_frames"):
        LagrangianConfig.from_dict({"select_every_frames": 1000})
