"""The factored exact operator (irdrc.core.exact.factored) against the dense model, and at scale."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from conftest import assert_factored_equals_dense, metrics_at, scenario

from irdrc.core.exact import build_factored, build_model, stationary_metrics, value_iteration
from irdrc.core.exact.dense import DENSE_MAX_STATES
from irdrc.core.params import Params
from tests.test_constrained_recipe import ROOT


def random_params(seed: int, wide: bool = False) -> Params:
    """A small model with every v1 feature drawn at random (chains, event probabilities, event
    model, radar reaction, arrivals, link capacities, queue). ``wide``: over the whole range a user
    may type (chains that never or always stay, events up to certainty, up to 8 arrivals a step,
    links of up to 60 packets, queues of up to 40), not only around the paper's values."""
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
    if wide:
        ov |= {
            "env.queue_capacity": int(torch.randint(1, 41, (1,), generator=g)),
            "env.arrival_rate": u(0.05, 8.0),
            "env.packets_good": int(torch.randint(0, 61, (1,), generator=g)),
            "env.packets_bad": int(torch.randint(0, 61, (1,), generator=g)),
            **{f"env.stay_good.{f}": u(0.0, 1.0) for f in factors},
            **{f"env.stay_bad.{f}": u(0.0, 1.0) for f in factors},
            **{f"env.p0.{e}": u(0.0, 0.3) for e in events},
            **{f"env.p1.{e}": u(0.0, 1.0) for e in events},
        }
    return Params.from_overrides(ov)


@pytest.mark.parametrize("seed", range(6))
def test_factored_equals_dense_on_random_models(seed):
    assert_factored_equals_dense(random_params(seed), seed)


@pytest.mark.parametrize("seed", range(6))
def test_factored_equals_dense_on_models_drawn_over_every_allowed_value(seed):
    assert_factored_equals_dense(random_params(seed, wide=True), seed)


@pytest.mark.parametrize("queue", [10, 60])
def test_a_link_that_carries_more_than_the_arrivals_can_bring(queue):
    """ν beyond the arrivals' reach in one step (λ = 1: 19 counts carry all but 1e-16 of the
    mass), as a learner's optimistic plan has it for a channel level it never saw full; with a
    deep queue the power steps run on a prefix of the queue lengths (its mass near empty). Both
    once failed in ``push_rows`` (a shape error, or an empty index)."""
    params = Params.from_overrides(
        {"env.queue_capacity": queue, "env.packets_good": queue + 10, "env.packets_bad": 25}
    )
    assert int(build_factored(params).pmf.shape[-1]) < 25  # the case in question
    assert_factored_equals_dense(params, queue)


@pytest.mark.parametrize(("lam", "D", "nu"), [(1.7, 300, 600), (4.0, 700, 699), (0.5, 5, 300)])
def test_queue_expectations_are_the_direct_sums_for_links_wider_than_a_block(lam, D, nu):
    """Packets sent E[min(d + A, ν)] and dropped E[(d + A − ν − D)^+], A ~ Poisson(λ), for links
    of hundreds of packets (a learner's optimistic plan sets ν to the whole queue), the sum over
    capacities taken several ``SHORT_BLOCK``s at a time, against the sums written out."""
    from irdrc.core.exact.factored import SHORT_BLOCK, _poisson, _queue_expectations

    assert nu > SHORT_BLOCK
    sent, dropped = _queue_expectations(lam, D, nu, nu)
    a = torch.arange(D + nu + 200, dtype=torch.float64)
    p = _poisson(lam, len(a))
    d = torch.arange(D + 1, dtype=torch.float64)[:, None]
    direct_sent = (torch.minimum(d + a, torch.tensor(float(nu))) * p).sum(1)
    direct_dropped = ((d + a - nu - D).clamp(min=0) * p).sum(1)
    assert torch.allclose(sent, direct_sent, rtol=0, atol=1e-12)
    assert torch.allclose(dropped, direct_dropped, rtol=0, atol=1e-12)


def test_deep_queue_is_solved_without_the_dense_matrix():
    """S = 100 000 (D = 3 124) in the paper's dynamics: the reward ignores the queue, so the
    optimal average reward is the D = 10 one; solved in seconds (the dense matrix would be 160 GB)."""
    deep = build_factored(Params.from_overrides({"env.queue_capacity": 3124}))
    assert deep.num_states == 100_000
    sol = value_iteration(deep, tol=1e-6)
    small = stationary_metrics(build_model(Params()), value_iteration(build_model(Params())).policy)
    got = stationary_metrics(deep, sol.policy)
    assert got.avg_reward == pytest.approx(small.avg_reward, abs=1e-9)
    with pytest.raises(ValueError, match="factored"):
        build_model(Params.from_overrides({"env.queue_capacity": DENSE_MAX_STATES // 32}))


@pytest.mark.e2e
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
    assert "S = 10 080 states, factored value iteration" in res.stdout
    assert "C×" in res.stdout or "R×" in res.stdout or "radar" in res.stdout
    import json

    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["solver"] == "factored" and s["num_states"] == 10080
    assert 0 < s["metrics"]["throughput"] <= 1.125 + 1e-9  # the mean of the bursty arrivals
    # the paper's baseline beside the others, as on the dense path: radar every other step, and
    # every packet that arrives (1.125 a step) sent or dropped
    rr = s["table"]["round_robin (stationary)"]
    assert rr["radar_fraction"] == pytest.approx(0.5)
    assert rr["throughput"] + rr["drop_rate"] == pytest.approx(1.125)


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
    import irdrc.core.sizes as sizes
    from irdrc.core.exact import DenseModel, FactoredModel, exact_scorer

    params = random_params(3)
    dense = exact_scorer(params)
    assert isinstance(dense.model, DenseModel)
    monkeypatch.setattr(sizes, "DENSE_LIMIT_BYTES", 16 * params.env.num_states**2 - 1)
    fac = exact_scorer(params)
    assert isinstance(fac.model, FactoredModel)
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
    import irdrc.core.exact.stationary as fmod

    params = scenario("env=large", "env.queue_capacity=5")
    dense, fac = build_model(params), build_factored(params)
    policy = value_iteration(dense).policy
    want = stationary_metrics(dense, policy)
    monkeypatch.setattr(fmod, "AUTO_POWER_STEPS", 5)
    for method in ("auto", "iad", "power"):
        mu, steps = fmod.stationary_distribution_factored(fac, policy, method=method)
        got = metrics_at(fac, policy, mu)
        assert got.avg_reward == pytest.approx(want.avg_reward, abs=1e-9), method
        assert got.mean_queue == pytest.approx(want.mean_queue, abs=1e-8), method
        if method == "auto":
            assert steps > 5  # the power steps did not converge alone


def test_auto_hands_over_as_soon_as_the_power_steps_show_they_are_slow():
    """``auto`` on a slow chain (large at D = 69, S = 10 080) stops the power steps once their change
    decays too slowly to converge in ``AUTO_POWER_STEPS`` (300 of them made 397 steps in all; now
    under 200) and ends where aggregation alone does; on a fast chain (the paper's) it is the power
    iteration, bit for bit."""
    import irdrc.core.exact.stationary as fmod

    fac = build_factored(scenario("env=large", "env.queue_capacity=69"))
    policy = value_iteration(fac).policy
    mu, steps = fmod.stationary_distribution_factored(fac, policy)
    iad, _ = fmod.stationary_distribution_factored(fac, policy, method="iad")
    assert steps < 200
    assert float((mu - iad).abs().sum()) < 1e-11
    paper = build_factored(scenario("env=paper", "env.queue_capacity=99"))
    policy = value_iteration(paper).policy
    auto, steps = fmod.stationary_distribution_factored(paper, policy)
    power, power_steps = fmod.stationary_distribution_factored(paper, policy, method="power")
    assert steps == power_steps < fmod.AUTO_POWER_STEPS and torch.equal(auto, power)


def test_extrapolation_lands_on_the_limit_of_a_geometric_sequence():
    """Iterates whose error shrinks by one factor r a round, x_k = x* + r^k·e (e sums to 0), are
    extrapolated to x* itself; where the differences do not shrink (r ≥ 1) or flip sign (r ≤ 0)
    the last iterate is kept."""
    from irdrc.core.exact.stationary import _extrapolate

    g = torch.Generator().manual_seed(0)
    limit = torch.rand(7, 3, generator=g, dtype=torch.float64)
    limit /= limit.sum()
    e = torch.randn(7, 3, generator=g, dtype=torch.float64)
    e = (e - e.mean()) * 0.01
    for r in (0.5, 0.85, 0.99):
        xs = [limit + r**k * e for k in range(3)]
        assert torch.allclose(_extrapolate(*xs), limit, rtol=0, atol=1e-12), r
    for r in (-0.5, 1.0, 1.2):
        xs = [limit + r**k * e for k in range(3)]
        assert torch.equal(_extrapolate(*xs), xs[2]), r


def test_aggregation_rounds_are_extrapolated():
    """Random choices on large's dynamics (D = 5, S = 864): the aggregation rounds' error decays at
    the sticky factors' mixing rate, 169 rounds to 1e-13 round by round; extrapolating every few
    rounds ends in under 100, at the dense model's metrics."""
    import irdrc.core.exact.stationary as fmod

    params = scenario("env=large", "env.queue_capacity=5")
    dense, fac = build_model(params), build_factored(params)
    policy = torch.full((dense.num_states, 2), 0.5, dtype=torch.float64)
    want = stationary_metrics(dense, policy)
    mu, rounds = fmod.stationary_distribution_factored(fac, policy, method="iad")
    got = metrics_at(fac, policy, mu)
    assert rounds < 100
    assert got.avg_reward == pytest.approx(want.avg_reward, abs=1e-9)
    assert got.mean_queue == pytest.approx(want.mean_queue, abs=1e-8)


@pytest.fixture
def stepped_rows(monkeypatch) -> list[int]:
    """The queue lengths each chain step of the factored model covers, in order."""
    from irdrc.core.exact.factored import FactoredModel

    rows: list[int] = []
    step_rows = FactoredModel.step_rows

    def counted(self, X, probs):
        rows.append(X.shape[0])
        return step_rows(self, X, probs)

    monkeypatch.setattr(FactoredModel, "step_rows", counted)
    return rows


def test_a_periodic_policy_on_a_deep_queue_settles_in_a_few_rounds(monkeypatch, stepped_rows):
    """Round robin on the paper's dynamics with a 200-packet queue (S = 6 432): the queue stays
    short, so aggregating over whole periods converges in a couple of rounds where stepping whole
    periods from uniform took 390 steps, each over only the queue lengths that hold mass; both give
    the same metrics (to the power iteration's tolerance, 1e-13 in L1)."""
    from irdrc.core.exact.factored import FactoredModel
    from irdrc.core.exact.mdp import ExactMDP

    fac = build_factored(scenario("env=paper", "env.queue_capacity=200"))
    got = stationary_metrics(fac, "round_robin").as_dict()
    assert len(stepped_rows) <= 10 and max(stepped_rows) < 201
    monkeypatch.setattr(FactoredModel, "cycle", ExactMDP.cycle)
    want = stationary_metrics(fac, "round_robin").as_dict()
    for k in want:
        assert got[k] == pytest.approx(want[k], rel=1e-9, abs=1e-11), k


def test_a_periodic_policy_goes_on_by_whole_periods_where_aggregation_stops(monkeypatch):
    """Round robin on large's dynamics (D = 5): with the aggregation rounds cut to one, the power
    iteration over whole periods finishes from where they stopped, at the dense model's metrics."""
    import irdrc.core.exact.stationary as fmod

    params = scenario("env=large", "env.queue_capacity=5")
    want = stationary_metrics(build_model(params), "round_robin")
    monkeypatch.setattr(fmod, "IAD_MAX_ITER", 1)
    got = stationary_metrics(build_factored(params), "round_robin")
    assert got.avg_reward == pytest.approx(want.avg_reward, abs=1e-9)
    assert got.mean_queue == pytest.approx(want.mean_queue, abs=1e-8)


def test_a_queue_that_stays_full_is_stepped_only_near_the_top(stepped_rows):
    """Radar always on the paper's dynamics with a 60-packet queue (S = 1 952): the queue fills
    and stays full, so every power step (``power``, and ``auto``, which converges by them here)
    covers only the queue lengths within a few steps' departures of D, not all 61; those and the
    aggregation rounds (``iad``, over d = 0 … D) give the dense model's metrics."""
    import irdrc.core.exact.stationary as fmod

    params = scenario("env=paper", "env.queue_capacity=60")
    dense, fac = build_model(params), build_factored(params)
    policy = torch.ones(dense.num_states, dtype=torch.int64)
    want = stationary_metrics(dense, policy)
    for method in ("auto", "iad", "power"):
        stepped_rows.clear()
        mu, _ = fmod.stationary_distribution_factored(fac, policy, method=method)
        got = metrics_at(fac, policy, mu)
        if method != "iad":  # 2 × (4 packets sent + 1) + 1
            assert stepped_rows and max(stepped_rows) <= 11, (method, max(stepped_rows))
        assert got.mean_queue == pytest.approx(60.0, abs=1e-9)
        assert got.avg_reward == pytest.approx(want.avg_reward, abs=1e-9), method


def test_aggregation_where_the_queue_never_empties():
    """Radar always on large's dynamics: the queue fills and stays full, so short queues are
    transient. The aggregated solve fixes the scale at the queue length holding the most mass (a
    recurrent one, not d = 0) and gives the dense model's metrics."""
    import irdrc.core.exact.stationary as fmod

    params = scenario("env=large", "env.queue_capacity=5")
    dense, fac = build_model(params), build_factored(params)
    policy = torch.ones(dense.num_states, dtype=torch.int64)
    want = stationary_metrics(dense, policy)
    mu, _ = fmod.stationary_distribution_factored(fac, policy, method="iad")
    got = metrics_at(fac, policy, mu)
    assert want.mean_queue == pytest.approx(5.0, abs=1e-9)  # full for good
    assert got.mean_queue == pytest.approx(want.mean_queue, abs=1e-9)
    assert got.avg_reward == pytest.approx(want.avg_reward, abs=1e-9)


def test_growth_exponent_of_the_scale_table():
    """``growth_exponents``: times that grow as S^1.5 fit k = 1.5; the last pair's k is its own."""
    from irdrc.bench.scale import growth_exponents

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
    # two rows of one state space (two requested sizes that build it) are one size: one size
    # alone fits nothing (it divided by zero), and a repeat does not move the fit
    assert growth_exponents([rows[0], rows[0]]) == []
    again = growth_exponents([*rows[:3], rows[1]])[0]
    assert again["k_fit"] == pytest.approx(1.5) and again["sizes"] == [1_000, 10_000, 100_000]


def test_banded_stationary_is_exact_across_hundreds_of_orders_of_magnitude():
    """``banded_stationary`` (GTH on the aggregated queue): a random banded chain's stationary
    distribution as the dense solve gives it; a queue that climbs (up 0.9, down 0.1: π_d ∝ 9^d,
    700 orders of magnitude over 740 states) without overflow, to the closed form; and a chain whose
    lower states cannot be reached from the top (their mass is 0)."""
    import numpy as np

    from irdrc.core.exact.banded import banded_stationary

    rng = np.random.default_rng(0)
    n = 60
    P = np.zeros((n, n))
    for i in range(n):
        for o in range(-3, 6):
            P[i, min(max(i + o, 0), n - 1)] += rng.random()
    P /= P.sum(1, keepdims=True)
    src, dst = np.nonzero(P)
    pi = banded_stationary(src, dst, P[src, dst], n)
    A = np.vstack([P.T - np.eye(n), np.ones(n)])
    ref = np.linalg.lstsq(A, np.r_[np.zeros(n), 1.0], rcond=None)[0]
    assert np.abs(pi - ref).max() < 1e-12
    n = 740
    src = np.r_[np.arange(n), np.arange(n)]
    dst = np.r_[np.minimum(np.arange(n) + 1, n - 1), np.maximum(np.arange(n) - 1, 0)]
    vals = np.r_[np.full(n, 0.9), np.full(n, 0.1)]
    pi = banded_stationary(src, dst, vals, n)
    assert np.isfinite(pi).all() and pi[-1] == pytest.approx(8 / 9, rel=1e-12)
    assert pi[-2] == pytest.approx(pi[-1] / 9, rel=1e-12)  # detailed balance: 0.9·π_d = 0.1·π_d+1
    assert pi[0] == 0.0  # 9^-739 of the top: below the smallest double, as it should be
    # only up: from the top nothing below is reached again, so everything ends there
    src = np.arange(n)
    dst = np.minimum(np.arange(n) + 1, n - 1)
    pi = banded_stationary(src, dst, np.ones(n), n)
    assert pi[-1] == 1.0 and pi[:-1].sum() == 0.0
