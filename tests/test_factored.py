"""The factored exact operator (irdrc.core.factored) against the dense model, and at scale."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from conftest import assert_factored_equals_dense

from irdrc.core.factored import (
    build_factored,
    stationary_metrics_factored,
    value_iteration_factored,
)
from irdrc.core.model import DENSE_MAX_STATES, build_model
from irdrc.core.params import Params
from irdrc.core.solve import stationary_metrics, value_iteration
from irdrc.experiments.config import compose
from tests.test_constrained_recipe import ROOT


def random_params(seed: int) -> Params:
    """A small model with every v1 feature drawn at random (chains, event probabilities, event
    model, radar reaction, arrivals, link capacities, queue)."""
    g = torch.Generator().manual_seed(seed)

    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand(1, generator=g))

    factors = ("channel", "road", "weather", "speed", "object")
    events = ("road", "weather", "speed", "object")
    ov = {
        "env.queue_capacity": int(torch.randint(1, 9, (1,), generator=g)),
        "env.arrival_rate": u(0.2, 3.0),
        "env.packets_good": int(torch.randint(2, 6, (1,), generator=g)),
        "env.packets_bad": int(torch.randint(0, 2, (1,), generator=g)),
        "env.event_model": "noisy_or" if seed % 2 else "sum",
        "env.radar_reaction": bool(seed % 3),
        "env.reaction_clear": u(0.1, 0.9),
        **{f"env.stay_good.{f}": u(0.05, 0.95) for f in factors},
        **{f"env.stay_bad.{f}": u(0.05, 0.95) for f in factors},
        **{f"env.p0.{e}": u(0.0, 0.05) for e in events},
        **{f"env.p1.{e}": u(0.05, 0.2) for e in events},
        "reward.r4": u(1.0, 50.0),
    }
    return Params.from_overrides(ov)


@pytest.mark.parametrize("seed", range(6))
def test_factored_equals_dense_on_random_models(seed):
    assert_factored_equals_dense(random_params(seed), seed)


def test_deep_queue_is_solved_without_the_dense_matrix():
    """S = 100 000 (D = 3 124) in the paper's dynamics: the reward ignores the queue, so the
    optimal average reward is the D = 10 one; solved in seconds (the dense matrix would be 160 GB)."""
    deep = build_factored(Params.from_overrides({"env.queue_capacity": 3124}))
    assert deep.num_states == 100_000
    sol = value_iteration_factored(deep, tol=1e-6)
    small = stationary_metrics(build_model(Params()), value_iteration(build_model(Params())).policy)
    got = stationary_metrics_factored(deep, sol.policy)
    assert got.avg_reward == pytest.approx(small.avg_reward, abs=1e-9)
    with pytest.raises(ValueError, match="factored"):
        build_model(Params.from_overrides({"env.queue_capacity": DENSE_MAX_STATES // 32}))


def test_solve_recipe_switches_to_the_factored_operator(tmp_path):
    res = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "solve.py"),
            "env=large",
            "env.queue_capacity=69",
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert res.returncode == 0, res.stderr
    assert "S = 10080 states, factored value iteration" in res.stdout
    assert "C×" in res.stdout or "R×" in res.stdout or "radar" in res.stdout
    import json

    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["solver"] == "factored" and s["num_states"] == 10080
    assert 0 < s["metrics"]["throughput"] <= 1.125 + 1e-9  # the mean of the bursty arrivals


@pytest.mark.e2e
def test_scale_benchmark_table(tmp_path):
    res = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "bench_scale.py"),
            "scenarios=[paper]",
            "states=[1000,2000]",
            "repeats=1",
            "skip_after_seconds=0",
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert res.returncode == 0, res.stderr
    import csv

    rows = list(csv.DictReader((tmp_path / "bench_scale.csv").open()))
    assert [(r["solver"], r["num_states"]) for r in rows] == [
        ("dense", "1024"),
        ("factored", "1024"),
    ]
    assert float(rows[0]["avg_reward"]) == pytest.approx(float(rows[1]["avg_reward"]), abs=1e-9)
    assert "Not run" in (tmp_path / "bench_scale.md").read_text()  # 2 048 skipped: 0 s budget
    res = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "bench_scale.py"), "scenarios=[nowhere]"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert res.returncode == 2 and "scenarios[0]" in res.stderr


def test_factored_scorer_scores_as_the_dense_one(monkeypatch):
    """exact_scorer switches to the factored model above the dense limit (forced low here), and
    the factored scorer's optimum and its ratios of arbitrary tables are the dense scorer's."""
    import irdrc.core.model as model_mod
    from irdrc.core.factored import FactoredScorer, exact_scorer
    from irdrc.core.solve import ExactScorer

    params = random_params(3)
    dense = exact_scorer(params)
    assert type(dense) is ExactScorer
    monkeypatch.setattr(model_mod, "DENSE_MODEL_LIMIT_BYTES", 16 * params.env.num_states**2 - 1)
    fac = exact_scorer(params)
    assert isinstance(fac, FactoredScorer)
    assert torch.equal(fac.optimal.policy, dense.optimal.policy)
    assert fac.optimal_metrics.avg_reward == pytest.approx(dense.optimal_metrics.avg_reward, 1e-9)
    g = torch.Generator().manual_seed(0)
    for _ in range(3):
        table = torch.randint(0, 2, (params.env.num_states,), generator=g)
        assert fac.ratio(table) == pytest.approx(dense.ratio(table), rel=1e-9)


def test_auto_hands_a_slow_chain_to_aggregation(monkeypatch):
    """A sticky, bursty, deep-queue chain (large's dynamics, D = 5, S = 864): ``auto`` after a
    few power steps (forced to 5) finishes by aggregation-disaggregation, to the dense model's
    metrics; ``iad`` alone and ``power`` alone agree."""
    import irdrc.core.factored as fmod

    params = Params.from_config(compose("solve", ["env=large", "env.queue_capacity=5"]))
    dense, fac = build_model(params), build_factored(params)
    policy = value_iteration(dense).policy
    want = stationary_metrics(dense, policy)
    monkeypatch.setattr(fmod, "AUTO_POWER_STEPS", 5)
    for method in ("auto", "iad", "power"):
        mu, steps = fmod.stationary_distribution_factored(fac, policy, method=method)
        got = stationary_metrics_factored(fac, policy, mu=mu)
        assert got.avg_reward == pytest.approx(want.avg_reward, abs=1e-9), method
        assert got.mean_queue == pytest.approx(want.mean_queue, abs=1e-8), method
        if method == "auto":
            assert steps > 5  # the power steps did not converge alone


def test_aggregation_where_the_queue_never_empties():
    """Radar always on large's dynamics: the queue fills and stays full, so short queues are
    transient. The aggregated solve fixes the scale at the queue length holding the most mass (a
    recurrent one, not d = 0) and gives the dense model's metrics."""
    import irdrc.core.factored as fmod

    params = Params.from_config(compose("solve", ["env=large", "env.queue_capacity=5"]))
    dense, fac = build_model(params), build_factored(params)
    policy = torch.ones(dense.num_states, dtype=torch.int64)
    want = stationary_metrics(dense, policy)
    mu, _ = fmod.stationary_distribution_factored(fac, policy, method="iad")
    got = stationary_metrics_factored(fac, policy, mu=mu)
    assert want.mean_queue == pytest.approx(5.0, abs=1e-9)  # full for good
    assert got.mean_queue == pytest.approx(want.mean_queue, abs=1e-9)
    assert got.avg_reward == pytest.approx(want.avg_reward, abs=1e-9)


def test_growth_exponent_of_the_scale_table():
    """``growth_exponents``: times that grow as S^1.5 fit k = 1.5; the last pair's k is its own."""
    from irdrc.experiments.bench_scale import growth_exponents

    rows = [
        {
            "scenario": "large",
            "solver": "factored",
            "device": "cpu",
            "num_states": S,
            "median_seconds": 1e-6 * S**1.5,
        }
        for S in (1_000, 10_000, 100_000)
    ] + [
        {
            "scenario": "large",
            "solver": "factored",
            "device": "cpu",
            "num_states": 1_000_000,
            "median_seconds": 1e-6 * 100_000**1.5 * 1000,
        }
    ]
    (g,) = growth_exponents(rows)
    assert g["k_last"] == pytest.approx(3.0)
    assert 1.5 < g["k_fit"] < 3.0
    three = growth_exponents(rows[:3])[0]
    assert three["k_fit"] == pytest.approx(1.5) and three["k_last"] == pytest.approx(1.5)
