"""recipes/study.py (irdrc.recipes.study): every (scenario, learner, seed) scored exactly, the
scoring time kept apart from training, bad studies refused before work."""

from __future__ import annotations

import csv
import json

import pytest
import torch
from conftest import run_recipe, scenario

from irdrc.core.exact import Scorer as ExactScorer
from irdrc.core.exact import build_model
from irdrc.recipes.study import Config, TimedScorer

SMALL = [
    "scenarios=[paper]",
    "seeds=[0,1]",
    "evals={default:2}",
    "overrides={dqn:['algo.num_envs=8','algo.frames_per_batch=32','algo.total_frames=640','algo.batch_size=32'],"
    "dqn_plain:['algo.num_envs=8','algo.frames_per_batch=32','algo.total_frames=640','algo.batch_size=32'],"
    "qlearning:['algo.episodes=2']}",
]
"""A study of a few seconds: the three learners, two seeds, the paper scenario, tiny budgets."""


def test_study_rows_and_table(tmp_path):
    assert run_recipe("study", tmp_path, *SMALL) == 0
    rows = list(csv.DictReader((tmp_path / "study.csv").open()))
    assert [(r["learner"], r["seed"]) for r in rows] == [
        ("dqn", "0"),
        ("dqn", "1"),
        ("dqn_plain", "0"),
        ("dqn_plain", "1"),
        ("qlearning", "0"),
        ("qlearning", "1"),
    ]
    # Q-learning's seeds are learners of one batched run; DQN runs once per seed
    assert {r["run_seed"] for r in rows if r["learner"] == "qlearning"} == {"0"}
    assert [r["learners_in_run"] for r in rows] == ["1", "1", "1", "1", "2", "2"]
    # plain DQN is DQN's run without the reward table and the centering: other numbers
    dqn = [r["final_ratio"] for r in rows if r["learner"] == "dqn"]
    assert dqn != [r["final_ratio"] for r in rows if r["learner"] == "dqn_plain"]
    for r in rows:
        assert r["budget_env_steps"] == ("800" if r["learner"] == "qlearning" else "640")
        assert int(r["evaluations"]) == 3  # at 0, half-way, end
        assert float(r["train_seconds"]) >= 0 and float(r["scoring_seconds"]) >= 0
        assert float(r["best_ratio"]) >= float(r["final_ratio"])
        for pct in (95, 99):
            if r[f"env_steps_to_{pct}"]:
                assert float(r[f"train_seconds_to_{pct}"]) <= float(r["train_seconds"]) + 1e-9
    # the final ratio is the exact ratio of the final greedy policy: Q-learning's budget of 2
    # episodes cannot have left the all-comm start for every state, so it is below the optimum
    assert all(float(r["final_ratio"]) < 0.999 for r in rows if r["learner"] == "qlearning")
    table = (tmp_path / "study.md").read_text().splitlines()
    assert len(table) == 2 + 3 + 2 and table[2].startswith("| paper (352) | dqn | 640 |")
    assert table[3].startswith("| paper (352) | dqn_plain | 640 |")
    assert table[-1].startswith("Measured on ")  # where and when, once under the table
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["scenarios"]["paper"]["solver"] == "DenseModel"


def test_timed_scorer_counts_every_call():
    scorer = ExactScorer(build_model(scenario()))
    timed = TimedScorer(scorer)
    table = scorer.optimal.policy
    assert timed.metrics(table).avg_reward == scorer.optimal_metrics.avg_reward
    timed.metrics(torch.ones_like(table))
    assert len(timed.after) == 2 and timed.after[0] <= timed.after[1] == timed.seconds


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"learners": ["ppo"]}, "learners"),
        ({"learners": []}, "learners"),
        ({"seeds": []}, "non-empty"),
        ({"scenarios": ["paper", "nowhere"]}, "nowhere"),
        ({"evals": {"default": 0}}, "evals"),
        ({"evals": {"default": 2, "larg": 3}}, "evals.larg"),
        ({"overrides": {"sac": []}}, "overrides.sac"),
    ],
)
def test_bad_studies_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        Config(**kw)


@pytest.mark.parametrize("learner", ["dqn", "qlearning"])
def test_the_learners_take_a_model_beyond_the_dense_limit(learner):
    """The study's ``large`` scenario (S = 100 800) has no dense model; its learners score on the
    factored one, so their configs must load there (they refused it, naming the dense tensor's
    151 GiB, and ``python recipes/study.py`` stopped at ``large``)."""
    from conftest import load

    from irdrc.core.sizes import fits_dense

    cfg = load(learner, "env=large")
    assert cfg.params.env.num_states == 100_800 and not fits_dense(cfg.params)
