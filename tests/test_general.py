"""The general model (MODEL.md § B.1–B.3): multi-level factors with their own matrices, the radar
reaction on levels, bursty (Markov-modulated Poisson) arrivals, imperfect radar (P_d, P_fa, r5).

The simulator is checked against the dense exact model by Pearson χ² on next-state counts and by
binomial / normal bounds at 5 standard deviations on events, misses, false alarms, packets and
rewards (see ``conftest.assert_chi2`` and ``test_env_stats``: a correct simulator fails one such
comparison with probability below ~1e-6, and the seeds are fixed). The dense model is checked
against the factored operator to 1e-9 and against hand-computed rewards.
"""

from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_chi2, assert_factored_equals_dense, one_step

from irdrc import Params
from irdrc.core.exact import build_factored, build_model, stationary_metrics
from irdrc.core.gym import DFRCGymEnv
from irdrc.core.states import decode_state, state_index

SPEED3 = {
    "levels": ["low", "medium", "high"],
    "transition": [[0.7, 0.3, 0.0], [0.2, 0.6, 0.2], [0.1, 0.3, 0.6]],
    "event": [0.01, 0.1, 0.3],
}
OBJECT3 = {
    "levels": ["none", "one", "many"],
    "transition": [[0.6, 0.3, 0.1], [0.3, 0.5, 0.2], [0.2, 0.3, 0.5]],
    "event": [0.02, 0.15, 0.4],
}
CHANNEL3 = {
    "levels": ["good", "fair", "bad"],
    "transition": [[0.8, 0.15, 0.05], [0.3, 0.5, 0.2], [0.1, 0.3, 0.6]],
    "packets": [4, 3, 1],
    "comm_reward": [2.0, 1.5, 0.5],
}
BURSTY = {"rates": [0.5, 3.0], "transition": [[0.9, 0.1], [0.3, 0.7]]}

FEATURES = {
    "levels": {"env.factors": {"speed": SPEED3, "channel": CHANNEL3}},
    "reaction": {"env.factors": {"object": OBJECT3, "speed": SPEED3}, "env.reaction_clear": 0.7},
    "bursty": {"env.bursty": BURSTY, "env.arrival_rate": None},
    "imperfect_radar": {"env.detection_prob": 0.8, "env.false_alarm_prob": 0.1, "reward.r5": 7.0},
    "everything": {
        "env.factors": {"speed": SPEED3, "object": OBJECT3, "channel": CHANNEL3},
        "env.bursty": BURSTY,
        "env.arrival_rate": None,
        "env.detection_prob": 0.8,
        "env.false_alarm_prob": 0.1,
        "reward.r5": 7.0,
        "env.event_model": "sum",
        "env.reaction_clear": 0.6,
    },
}


def params_of(feature: str, queue: int = 3) -> Params:
    return Params.from_overrides({**FEATURES[feature], "env.queue_capacity": queue})


def test_v1_spelled_as_factors_is_v1():
    """The general path on v1's own numbers gives v1's model (to float64 rounding)."""
    v1 = Params()
    T = [[0.9, 0.1], [0.9, 0.1]]
    spelled = Params.from_overrides(
        {
            "env.factors": {
                "channel": {"transition": T, "packets": [4, 2], "comm_reward": [2.0, 1.0]},
                "road": {"transition": T, "event": [0.005, 0.05]},
                "weather": {"transition": T, "event": [0.005, 0.046]},
                "speed": {"transition": T, "event": [0.005, 0.1]},
                "object": {"transition": T, "event": [0.005, 0.05]},
            }
        }
    )
    assert not spelled.env.is_v1 and spelled.env.factor_levels == v1.env.factor_levels
    a, b = build_model(v1), build_model(spelled)
    for key in ("P", "R", "event", "sent", "dropped", "capacity", "missed", "false_alarms"):
        assert torch.allclose(getattr(a, key), getattr(b, key), rtol=0, atol=1e-15), key


def test_state_index_is_mixed_radix():
    p = params_of("everything")
    levels = p.env.factor_levels
    assert levels == (3, 2, 2, 3, 3, 2)
    s = torch.arange(p.env.num_states)
    cols = decode_state(s, levels)
    assert cols.shape == (p.env.num_states, 7)
    assert torch.equal(state_index(*cols.unbind(-1), levels=levels), s)
    assert (
        state_index(2, 1, 0, 1, 2, 1, 1, levels=levels)
        == (((((2 * 3 + 1) * 2 + 0) * 2 + 1) * 3 + 2) * 3 + 1) * 2 + 1
    )
    # v1's index is unchanged by the general formula
    assert state_index(3, 1, 0, 1, 0, 1, 0, levels=(2, 2, 2, 2, 2, 1)) == state_index(
        3, 1, 0, 1, 0, 1
    )


@pytest.mark.parametrize("feature", list(FEATURES))
def test_simulated_transitions_match_the_exact_model(feature):
    """χ² of next states, and 5-σ bounds on events, misses, false alarms, packets and reward,
    from a spread of states under both actions."""
    p = params_of(feature)
    m = build_model(p)
    S, n = m.num_states, 12_000
    gen = torch.Generator().manual_seed(0)
    starts = torch.randperm(S, generator=gen)[:6]
    rows = torch.stack([starts, starts]).T.reshape(-1)  # (state, action) pairs
    acts = torch.tensor([0, 1]).repeat(len(starts))
    nxt = one_step(p, rows.repeat_interleave(n), acts.repeat_interleave(n), seed=1)
    counts = torch.zeros(len(rows), S, dtype=torch.float64)
    counts.scatter_add_(
        1, nxt["state"].view(len(rows), n), torch.ones(len(rows), n, dtype=torch.float64)
    )
    expected = torch.stack([m.P[a, s] for s, a in zip(rows, acts, strict=True)]) * n
    assert_chi2(counts, expected)
    for key, table in (
        ("event", m.event[None].expand(2, -1)),
        ("missed", m.missed),
        ("false_alarm", m.false_alarms),
    ):
        freq = nxt[key].double().view(len(rows), n).mean(1)
        prob = torch.stack([table[a, s] for s, a in zip(rows, acts, strict=True)])
        sigma = torch.sqrt(prob * (1 - prob) / n)
        assert bool(((freq - prob).abs() <= 5 * sigma + 1e-12).all()), (key, freq, prob)
    for key, table in (("reward", m.R), ("sent", m.sent), ("capacity", m.capacity)):
        x = nxt[key].double().view(len(rows), n)
        mean = torch.stack([table[a, s] for s, a in zip(rows, acts, strict=True)])
        se = x.std(1) / math.sqrt(n)
        assert bool(((x.mean(1) - mean).abs() <= 5 * se + 1e-9).all()), (key, x.mean(1), mean)


def test_bursty_arrivals_follow_the_phase():
    """Arrivals are Poisson with the rate of the step's phase (mean and variance per phase)."""
    p = params_of("bursty", queue=60)
    levels = p.env.factor_levels
    n = 40_000
    for phase, rate in enumerate(BURSTY["rates"]):
        s = state_index(0, 0, 0, 0, 0, 0, phase, levels=levels)
        nxt = one_step(p, torch.full((n,), s), 1, seed=2 + phase)  # radar: nothing leaves
        assert bool((nxt["phase"] == phase).all())
        a = decode_state(nxt["state"], levels)[:, 0].double()  # d′ = A (queue 60 never fills)
        # Poisson: mean = variance = rate; 5 standard errors of the mean
        assert abs(float(a.mean()) - rate) <= 5 * math.sqrt(rate / n)
        assert abs(float(a.var()) - rate) <= 0.1 * rate
    td = one_step(p, torch.zeros(4, dtype=torch.int64), 0)
    assert td["observation"].shape == (4, 7)


def test_imperfect_radar_rewards_by_hand():
    """R for radar with P_d = 0.8, P_fa = 0.1, r5 = 7 in one state, computed by hand."""
    p = Params.from_overrides(
        {
            "env.detection_prob": 0.8,
            "env.false_alarm_prob": 0.1,
            "reward.r5": 7.0,
            "env.queue_capacity": 2,
            "env.p1": {"road": 0.2, "weather": 0.3, "speed": 0.4, "object": 0.1},
        }
    )
    m = build_model(p)
    s = state_index(1, 0, 1, 1, 0, 0)  # road and weather bad: b = 2
    e = 1 - (1 - 0.2) * (1 - 0.3) * (1 - 0.005) * (1 - 0.005)
    want_radar = e * (0.8 * 5 * 3 - 0.2 * 50) - (1 - e) * 0.1 * 7
    want_comm = (1 - e) * 2 - e * 50
    assert math.isclose(float(m.R[1, s]), want_radar, rel_tol=1e-12)
    assert math.isclose(float(m.R[0, s]), want_comm, rel_tol=1e-12)
    assert math.isclose(float(m.missed[1, s]), 0.2 * e, rel_tol=1e-12)
    assert math.isclose(float(m.false_alarms[1, s]), 0.1 * (1 - e), rel_tol=1e-12)
    # always radar: false alarms / radar steps without an event = P_fa exactly
    met = stationary_metrics(m, torch.ones(m.num_states, dtype=torch.int64))
    assert math.isclose(met.false_alarm_rate, 0.1, rel_tol=1e-9)
    assert math.isclose(met.miss_detection, 0.2, rel_tol=1e-9)


def test_multilevel_detection_reward_and_comm_reward_by_hand():
    p = params_of("levels")
    m = build_model(p)
    levels = p.env.factor_levels
    s = state_index(2, 2, 1, 0, 2, 0, levels=levels)  # bad channel, slippery road, high speed
    e = 1 - (1 - 0.05) * (1 - 0.005) * (1 - 0.3) * (1 - 0.005)
    assert math.isclose(float(m.event[s]), e, rel_tol=1e-12)
    assert math.isclose(float(m.R[1, s]), e * 5 * (1 + 1 + 2), rel_tol=1e-12)  # b = 1 + 2
    assert math.isclose(float(m.R[0, s]), (1 - e) * 0.5 - e * 50, rel_tol=1e-12)
    assert float(m.capacity[0, s]) == 1.0


def test_gym_single_env_matches_the_exact_model():
    """The gymnasium env (its own per-step code) on the general model: χ² of next states."""
    p = params_of("everything", queue=2)
    m = build_model(p)
    env = DFRCGymEnv(p)
    starts = [5, 301, 600]
    n = 4_000
    counts = torch.zeros(2 * len(starts), m.num_states, dtype=torch.float64)
    env.reset(seed=0)
    for i, (s, a) in enumerate((s, a) for s in starts for a in (0, 1)):
        for _ in range(n):
            env.reset(options={"state": s})
            _, _, _, _, info = env.step(a)
            counts[i, info["state"]] += 1
    expected = torch.stack([m.P[a, s] for s in starts for a in (0, 1)]) * n
    assert_chi2(counts, expected)


def _random_params(seed: int) -> Params:
    g = torch.Generator().manual_seed(seed)

    def stochastic(n: int) -> list[list[float]]:
        x = torch.rand(n, n, generator=g, dtype=torch.float64) + 0.05
        x = x / x.sum(1, keepdim=True)
        x[:, -1] = 1 - x[:, :-1].sum(1)
        return x.tolist()

    def probs(n: int) -> list[float]:
        return (torch.rand(n, generator=g, dtype=torch.float64) * 0.3).tolist()

    lv = [2 + int(x) for x in torch.randint(0, 2, (5,), generator=g)]
    factors = {
        "channel": {
            "transition": stochastic(lv[0]),
            "packets": torch.randint(0, 5, (lv[0],), generator=g).tolist(),
            "comm_reward": (torch.rand(lv[0], generator=g) * 3).tolist(),
        }
    }
    for name, n in zip(("road", "weather", "speed", "object"), lv[1:], strict=True):
        factors[name] = {"transition": stochastic(n), "event": probs(n)}
    return Params.from_overrides(
        {
            "env.factors": factors,
            "env.bursty": {"rates": [0.3, 2.5], "transition": stochastic(2)},
            "env.arrival_rate": None,
            "env.queue_capacity": 4,
            "env.detection_prob": 0.85,
            "env.false_alarm_prob": 0.07,
            "reward.r5": 3.0,
            "env.event_model": ("noisy_or", "sum")[seed % 2],
            "env.reaction_clear": 0.5,
        }
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_factored_equals_dense_with_every_feature_on(seed):
    p = _random_params(seed)
    assert p.env.false_alarm_prob > 0 and p.env.bursty is not None
    assert_factored_equals_dense(p, seed)


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (
            {"env.factors": {"speed": {"transition": [[0.5, 0.6], [0.5, 0.5]], "event": [0, 0]}}},
            "sum",
        ),
        ({"env.factors": {"speed": {"transition": [[1.0, 0.0], [0.5, 0.5]]}}}, r"speed\.event"),
        ({"env.factors": {"speed": {**SPEED3, "event": [0.1, 0.2]}}}, "3 values"),
        ({"env.factors": {"speed": {**SPEED3, "levels": ["a", "b"]}}}, "levels"),
        ({"env.factors": {"speed": {**SPEED3, "packets": [1, 2, 3]}}}, "only the channel"),
        ({"env.factors": {"channel": {**CHANNEL3, "event": [0, 0, 0]}}}, "drives no event"),
        ({"env.factors": {"speeed": SPEED3}}, "did you mean"),
        ({"env.factors": {"speed": {**SPEED3, "matrix": 1}}}, "unknown key"),
        (
            {"env.factors": {"speed": SPEED3}, "env.p1": {"speed": 0.5}},
            r"env\.p1\.speed=0\.5 is not used",
        ),
        ({"env.factors": {"channel": CHANNEL3}, "reward.r1": 3.0}, r"reward\.r1=3\.0 is not used"),
        ({"env.bursty": BURSTY}, "arrival_rate=null"),
        ({"env.arrival_rate": None}, "needs env.bursty"),
        (
            {"env.bursty": {"rates": [1.0, 2.0]}, "env.arrival_rate": None},
            "both rates and transition",
        ),
        ({"env.bursty": {**BURSTY, "rates": [1.0, -2.0]}, "env.arrival_rate": None}, "rates"),
        ({"env.detection_prob": 1.5}, "detection_prob"),
        ({"env.false_alarm_prob": -0.1}, "false_alarm_prob"),
        ({"reward.r5": -1}, r"reward\.r5"),
    ],
)
def test_bad_general_configs_are_rejected(overrides, match):
    with pytest.raises(ValueError, match=match):
        Params.from_overrides(overrides)


def test_v1_configs_keep_their_keys():
    """The general keys at their defaults stay out of v1's config (run names, caches, hashes)."""
    d = Params().to_dict()
    for key in ("factors", "bursty", "detection_prob", "false_alarm_prob"):
        assert key not in d["env"]
    assert "r5" not in d["reward"]
    p = params_of("everything")
    assert Params.from_config(p.to_dict()) == p


def test_factor_levels_follow_their_own_matrices():
    """Each factor's next level against its configured matrix row, read from the config (not from
    the model's tables), and the radar reaction on levels: v′ = 0, m′ = 0 w.p. reaction_clear,
    else m′ = m."""
    p = params_of("everything")
    levels = p.env.factor_levels
    n = 30_000
    start = (1, 2, 1, 0, 2, 2, 1)  # d, c, r, w, v, m, phase
    T = p.env.factor
    rows = {
        1: CHANNEL3["transition"][2],
        2: T("road").transition[1],
        3: T("weather").transition[0],
        4: SPEED3["transition"][2],
        5: OBJECT3["transition"][2],
        6: BURSTY["transition"][1],
    }
    comm = decode_state(
        one_step(p, torch.full((n,), state_index(*start, levels=levels)), 0)["state"], levels
    )
    for col, row in rows.items():
        freq = torch.bincount(comm[:, col], minlength=len(row)).double() / n
        prob = torch.tensor(row, dtype=torch.float64)
        sigma = torch.sqrt(prob * (1 - prob) / n)
        assert bool(((freq - prob).abs() <= 5 * sigma + 1e-12).all()), (col, freq, prob)
    radar = decode_state(
        one_step(p, torch.full((n,), state_index(*start, levels=levels)), 1, seed=5)["state"],
        levels,
    )
    assert bool((radar[:, 4] == 0).all())  # v′ = 0
    m_next = torch.bincount(radar[:, 5], minlength=3).double() / n
    clear = FEATURES["everything"]["env.reaction_clear"]
    prob = torch.tensor([clear, 0.0, 1 - clear], dtype=torch.float64)
    sigma = torch.sqrt(prob * (1 - prob) / n)
    assert bool(((m_next - prob).abs() <= 5 * sigma + 1e-12).all()), m_next
    for col in (1, 2, 3, 6):  # the others follow their chains under radar too
        freq = torch.bincount(radar[:, col], minlength=len(rows[col])).double() / n
        prob = torch.tensor(rows[col], dtype=torch.float64)
        sigma = torch.sqrt(prob * (1 - prob) / n)
        assert bool(((freq - prob).abs() <= 5 * sigma + 1e-12).all()), (col, freq, prob)


ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]


@pytest.mark.e2e
@pytest.mark.parametrize(
    ("args", "states"),
    [
        (["env=multilevel"], 792),
        (["env=imperfect_radar", "reward=imperfect_radar"], 352),
        (["+env.detection_prob=0.8", "+env.false_alarm_prob=0.1", "+reward.r5=3"], 352),
    ],
)
def test_solve_recipe_on_the_named_scenarios(tmp_path, args, states):
    import json
    import subprocess
    import sys

    res = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "solve.py"),
            *args,
            "eval.mc_episodes=0",
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert res.returncode == 0, res.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert f"{states} states" in res.stdout or f"of {states} states" in res.stdout
    fa = summary["metrics"].get("false_alarm_rate")
    if "multilevel" in args[0]:
        assert fa is None and "false_alarm_rate" not in res.stdout
    else:
        # radar steps without an event raise an alarm w.p. P_fa, whatever the policy
        p_fa = 0.05 if "imperfect" in args[0] else 0.1
        assert fa == pytest.approx(p_fa, rel=1e-9) and "false_alarm_rate" in res.stdout
    header = (tmp_path / "policy.csv").read_text().splitlines()[0]
    assert header == "d,c,r,w,v,m,action,p_radar"


def test_the_lp_on_sparse_factored_transitions_equals_the_dense_lp():
    """MODEL.md § B.4: the CMDP LP's flow constraints built sparse from the factors
    (``FactoredModel.sparse``) give the dense
    model's matrices (to rounding) and the same constrained optimum."""
    from irdrc.core.cmdp import solve_cmdp

    for p, sparse_enough in ((_random_params(0), False), (params_of("levels", queue=30), True)):
        dense, fac = build_model(p), build_factored(p)
        for a in (0, 1):
            sp = fac.sparse(a)
            assert sp.nnz <= int((dense.P[a] > 0).sum())  # arrivals past 1e-17 are folded in
            if sparse_enough:  # O(S · fan-out): arrivals kept × the factors' row support
                fan_out = fac.pmf.shape[-1] * int((fac.F[a] > 0).sum(1).max())
                assert sp.nnz <= dense.num_states * fan_out < dense.P[a].numel()
            assert float(abs(sp.toarray() - dense.P[a].numpy()).max()) < 1e-15
    small = Params.from_overrides({**FEATURES["imperfect_radar"], "env.queue_capacity": 4})
    sd = solve_cmdp(build_model(small), 0.25)
    sf = solve_cmdp(build_factored(small), 0.25)
    assert sf.value == pytest.approx(sd.value, rel=1e-8)
    assert sf.metrics.miss_detection <= 0.25
    assert sf.metrics.false_alarm_rate == pytest.approx(0.1, rel=1e-9)


@pytest.mark.parametrize("feature", [None, "levels", "reaction", "bursty", "everything"])
def test_nonzeros_counts_the_sparse_transitions_without_building_them(feature):
    """The LP's memory is read from its transitions' non-zeros before they are built (the
    recipes' refusal): ``nonzeros(a)`` is ``sparse(a).nnz`` exactly, dense and factored."""
    p = (
        Params.from_overrides({"env.queue_capacity": 12})
        if feature is None
        else params_of(feature, 12)
    )
    for model in (build_model(p), build_factored(p)):
        for a in range(model.num_actions):
            assert model.nonzeros(a) == model.sparse(a).nnz > 0


def test_a_factored_chain_is_written_in_place_in_little_more_than_its_own_memory(monkeypatch):
    """``FactoredModel.sparse`` writes the CSR arrays in place, ``SPARSE_CHUNK`` entries at a time:
    on ``large``'s comm chain at 24 packets (5.1 M non-zeros, 61 MB) it allocates at most 2.5× the
    matrix at its peak (1.7× here; the COO pieces it used to concatenate took 5.8×), and written a
    thousand entries at a time it is the same matrix to the bit."""
    import tracemalloc

    import numpy as np

    from irdrc import scenario
    from irdrc.core.exact import factored

    model = build_factored(scenario("large", {"env.queue_capacity": 24}))
    tracemalloc.start()
    try:
        P = model.sparse(0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2.5 * (P.data.nbytes + P.indices.nbytes + P.indptr.nbytes)
    small = build_factored(params_of("everything", 12))
    whole = [small.sparse(a) for a in range(2)]
    monkeypatch.setattr(factored, "SPARSE_CHUNK", 1000)
    for a, W in enumerate(whole):
        C = small.sparse(a)
        for name in ("data", "indices", "indptr"):
            assert np.array_equal(getattr(C, name), getattr(W, name))
