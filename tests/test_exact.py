"""The exact model and solvers, and the simulator checked against them."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import EDGES, assert_chi2

from irdrc import DFRCEnv, Params, state_index
from irdrc.core import policies
from irdrc.core.evaluate import evaluate
from irdrc.core.exact import (
    DenseModel,
    ValueIteration,
    as_schedule,
    build_model,
    episodic_metrics,
    policy_evaluation,
    stationary_distribution,
    stationary_metrics,
    value_iteration,
)
from irdrc.core.metrics import METRIC_NAMES

SCENARIOS = {
    "paper": {},
    "sum_no_reaction": {"env.event_model": "sum", "env.radar_reaction": False, "env.p1.speed": 0.6},
    "busy_queue": {"env.arrival_rate": 2.5, "env.queue_capacity": 4, "env.packets_bad": 1},
    "edges": EDGES,
}


@pytest.fixture(scope="module")
def paper():
    return build_model(Params())


def tiny_model(P, R) -> DenseModel:
    z = torch.zeros(P.shape[-1], dtype=torch.float64)
    radar = torch.tensor([0.0, 1.0], dtype=torch.float64)
    return DenseModel(Params(), P, R, z, 0 * R, 0 * R, 0 * R, 0 * R, 0 * R, z, radar)


def test_value_iteration_on_hand_solved_mdp():
    # State 0: stay (+1) or move to 1 (+0); state 1: stay (+2) or move to 0 (+0). γ = 0.9.
    # V(1) = 2/(1 − 0.9) = 20; in state 0, staying is worth 10, moving 0.9·20 = 18 → move.
    P = torch.tensor([[[1.0, 0.0], [0.0, 1.0]], [[0.0, 1.0], [1.0, 0.0]]], dtype=torch.float64)
    R = torch.tensor([[1.0, 2.0], [0.0, 0.0]], dtype=torch.float64)
    sol = value_iteration(tiny_model(P, R), gamma=0.9)
    assert sol.policy.tolist() == [1, 0]
    assert torch.allclose(sol.values, torch.tensor([18.0, 20.0], dtype=torch.float64), atol=1e-9)
    with pytest.raises(RuntimeError, match="did not reach tol"):
        value_iteration(tiny_model(P, R), gamma=0.9, max_iter=3)
    with pytest.raises(ValueError, match="gamma"):
        value_iteration(tiny_model(P, R), gamma=1.0)


def test_value_iteration_a_few_sweeps_at_a_time_is_the_same_solve():
    """Three sweeps at a time from zeros: the same iterates, so the same solution, bit for bit, as
    ``value_iteration``; started from V* it stops after a sweep or two; a start of another size is
    refused. (A persistent channel: a solve of about a hundred sweeps, where the paper's takes 3.)"""
    model = build_model(
        Params.from_overrides({"env.stay_good.channel": 0.95, "env.stay_bad.channel": 0.9})
    )
    whole = value_iteration(model, tol=1e-6)
    vi, solution, calls = ValueIteration(model, tol=1e-6), None, 0
    while solution is None:
        solution, calls = vi.sweep(3), calls + 1
        assert vi.iterations <= 3 * calls
    assert solution.iterations == whole.iterations > 10
    assert calls == math.ceil(whole.iterations / 3)
    assert torch.equal(solution.values, whole.values) and torch.equal(solution.policy, whole.policy)
    warm = ValueIteration(model, tol=1e-6, values=whole.values).sweep(10)
    assert warm is not None and warm.iterations <= 2
    assert torch.equal(warm.policy, whole.policy)
    with pytest.raises(ValueError, match="states"):
        ValueIteration(model, values=torch.zeros(3))


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_rows_sum_to_one(name):
    m = build_model(Params.from_overrides(SCENARIOS[name]))
    assert torch.allclose(m.P.sum(-1), torch.ones_like(m.P[..., 0]), atol=1e-12)
    assert bool((m.P >= 0).all())


def test_optimal_beats_every_baseline_exactly(paper):
    sol = value_iteration(paper)
    best = stationary_metrics(paper, sol.policy).avg_reward
    for name in ("round_robin", "always_comm", "always_radar", "random"):
        assert best > stationary_metrics(paper, name).avg_reward + 0.1
        # and in discounted value from every state, for stationary baselines
        if name != "round_robin":
            assert bool((sol.values >= policy_evaluation(paper, name) - 1e-9).all())


def test_stationary_distribution_and_schedules(paper):
    mu = stationary_distribution(paper.P[0])
    assert torch.allclose(mu @ paper.P[0], mu, atol=1e-12) and abs(float(mu.sum()) - 1) < 1e-12
    assert len(as_schedule("round_robin", 352)) == 2
    with pytest.raises(ValueError, match="shape"):
        as_schedule(torch.zeros(5, dtype=torch.long), 352)
    # a table as a Python list (``tolist()``: S actions or S rows of probabilities) is one table,
    # not a schedule of S one-number tables ("policy table has shape ()")
    radar = torch.ones(352, dtype=torch.long)
    assert len(as_schedule(radar.tolist(), 352)) == 1
    probs = torch.nn.functional.one_hot(radar, 2).double()
    assert torch.equal(as_schedule(probs.tolist(), 352)[0], probs)
    assert len(as_schedule([torch.zeros_like(radar).tolist(), radar.tolist()], 352)) == 2
    # a list of the wrong length, or rows of the wrong width, is refused by its own shape
    for wrong, shape in (([0] * 10, r"\(10,\)"), ([[0.5, 0.25, 0.25]] * 352, r"\(352, 3\)")):
        with pytest.raises(ValueError, match=rf"policy table has shape {shape}; expected \[352\]"):
            as_schedule(wrong, 352)
    # with the default chains each factor is bad w.p. 0.1 every step: P(c = 1) = 0.1 under
    # always-comm (no radar reaction), exactly
    c1 = mu.view(11, 2, 16)[:, 1].sum()
    assert abs(float(c1) - 0.1) < 1e-12


def test_episodic_differs_from_stationary(paper):
    # resets start from a uniform queue (mean 5): the episodic mean queue is visibly higher
    stat = stationary_metrics(paper, "always_comm")
    epi = episodic_metrics(paper, "always_comm")
    assert epi.mean_queue > stat.mean_queue + 0.02
    assert episodic_metrics(paper, "always_comm", horizon=100_000).mean_queue == pytest.approx(
        stat.mean_queue, abs=1e-3
    )


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_simulator_matches_model_chi2(name):
    """One step from every (state, action), K times each: χ² on next states, 5σ on rewards."""
    params = Params.from_overrides(SCENARIOS[name])
    m = build_model(params)
    S, K = m.num_states, 1500
    states = torch.arange(S).repeat(2).repeat_interleave(K)
    actions = torch.arange(2).repeat_interleave(S).repeat_interleave(K)
    env = DFRCEnv(params, batch_size=[states.numel()], seed=7)
    from tensordict import TensorDict

    td = TensorDict(
        {
            "state": states,
            "action": actions,
            "step_count": torch.zeros(states.numel(), 1, dtype=torch.long),
        },
        batch_size=[states.numel()],
    )
    nxt = env.step(td)["next"]
    rows = actions * S + states
    counts = torch.zeros(2 * S, S, dtype=torch.float64)
    counts.index_put_(
        (rows, nxt["state"]), torch.ones(rows.numel(), dtype=torch.float64), accumulate=True
    )
    expected = m.P.reshape(2 * S, S) * K
    assert_chi2(counts, expected)
    # mean reward, sent, dropped, capacity per (action, state) within 5 standard errors
    for key, exact in (
        ("reward", m.R),
        ("sent", m.sent),
        ("dropped", m.dropped),
        ("capacity", m.capacity),
    ):
        x = nxt[key].double().reshape(-1)
        sums = torch.zeros(2 * S, dtype=torch.float64).index_add_(0, rows, x)
        sq = torch.zeros(2 * S, dtype=torch.float64).index_add_(0, rows, x * x)
        mean = sums / K
        se = torch.sqrt((sq / K - mean**2).clamp(min=0) / (K - 1))
        mu = exact.reshape(-1)
        if key != "reward":
            # Rare counts (drops with μ ~ 1e-6) give all-zero samples and a sample se of 0. For an
            # integer X ≥ 0, E[X²] ≥ E[X], so Var X ≥ μ − μ²: a floor on the true se.
            se = torch.maximum(se, torch.sqrt((mu - mu**2).clamp(min=0) / K))
        # the 1e-6 admits float32 rounding of rewards where every sample agreed
        bad = (mean - mu).abs() > 5 * se + 1e-6
        assert not bool(bad.any()), (key, mean[bad].tolist(), mu[bad].tolist())


@pytest.mark.parametrize("which", ["optimal", "round_robin"])
def test_sampled_episodes_match_exact_episodic(paper, which):
    if which == "optimal":
        policy = value_iteration(paper).policy
        module, exact = policies.table_policy(policy), episodic_metrics(paper, policy)
    else:
        module, exact = policies.round_robin(), episodic_metrics(paper, "round_robin")
    env = DFRCEnv(Params(), batch_size=[2048], seed=11)
    ev = evaluate(module, env)
    for name in METRIC_NAMES:
        got, want, ci = getattr(ev.metrics, name), getattr(exact, name), ev.ci95[name]
        if ci == 0 or math.isnan(ci):
            assert got == pytest.approx(want, abs=1e-9), name
        else:
            # ci95 is 1.96 standard errors; 5 standard errors is the bound
            assert abs(got - want) <= 5 / 1.96 * ci, (name, got, want, ci)


# Parameters whose float32 rounding is visible (float32 keeps ~7 significant digits).
F64_SCENARIOS = {
    "noisy_or": {
        "env.queue_capacity": 3,
        "env.arrival_rate": 1.2345678901,
        "env.packets_good": 3,
        "env.packets_bad": 1,
        "env.p0": {
            "road": 0.0123456789,
            "weather": 0.0234567891,
            "speed": 0.123456789,
            "object": 0.0345678912,
        },
        "env.p1": {
            "road": 0.123456789,
            "weather": 0.234567891,
            "speed": 0.345678912,
            "object": 0.456789123,
        },
        "env.stay_good": {
            "channel": 0.912345678,
            "road": 0.823456789,
            "weather": 0.734567891,
            "speed": 0.645678912,
            "object": 0.956789123,
        },
        "env.stay_bad": {
            "channel": 0.112345678,
            "road": 0.223456789,
            "weather": 0.334567891,
            "speed": 0.445678912,
            "object": 0.556789123,
        },
        "env.reaction_clear": 0.876543219,
        "reward": {"r1": 2.123456789, "r2": 1.123456789, "r3": 37.123456789, "r4": 5.123456789},
    },
}
F64_SCENARIOS["sum"] = {**F64_SCENARIOS["noisy_or"], "env.event_model": "sum"}


def _reference_float64(params: Params):
    """MODEL.md in plain Python floats (float64), written without torch: P, R, event, sent, dropped."""
    env, rw = params.env, params.reward
    D, lam = env.queue_capacity, env.arrival_rate
    g, h = env.stay_good.as_tuple(), env.stay_bad.as_tuple()
    p0, p1 = env.p0.as_tuple(), env.p1.as_tuple()
    S = (D + 1) * 32
    # Poisson pmf up to a count whose mass beyond is < 1e-30 (far below the 1e-12 asked).
    pmf, k = [], 0
    while True:
        pmf.append(math.exp(k * math.log(lam) - lam - math.lgamma(k + 1)))
        if k > D + 10 and pmf[-1] < 1e-32:
            break
        k += 1

    def factor_next(x, stay_good, stay_bad):
        return [stay_good, 1 - stay_good] if x == 0 else [1 - stay_bad, stay_bad]

    P = [[[0.0] * S for _ in range(S)] for _ in range(2)]
    R = [[0.0] * S for _ in range(2)]
    sent = [[0.0] * S for _ in range(2)]
    dropped = [[0.0] * S for _ in range(2)]
    event = [0.0] * S
    for s in range(S):
        d, f = divmod(s, 32)
        bits = [(f >> b) & 1 for b in (4, 3, 2, 1, 0)]  # c r w v m
        c, ev_bits = bits[0], bits[1:]
        ps = [(p1 if x else p0)[i] for i, x in enumerate(ev_bits)]
        if env.event_model == "noisy_or":
            e = 1.0 - math.prod(1.0 - q for q in ps)
        else:
            e = min(1.0, sum(ps))
        event[s] = e
        b = sum(ev_bits)
        R[0][s] = (1 - e) * (rw.r1 if c == 0 else rw.r2) - e * rw.r3
        R[1][s] = e * rw.r4 * (b + 1)
        for a in (0, 1):
            nu = 0 if a == 1 else (env.packets_good if c == 0 else env.packets_bad)
            q_next = [0.0] * (D + 1)
            for k, pk in enumerate(pmf):
                rest = max(0, d + k - nu)
                dn = min(D, rest)
                q_next[dn] += pk
                sent[a][s] += pk * min(d + k, nu)
                dropped[a][s] += pk * (rest - dn)
            per = [factor_next(x, g[i], h[i]) for i, x in enumerate(bits)]
            if a == 1 and env.radar_reaction and bits[4] == 1:
                per[3] = [1.0, 0.0]
                per[4] = [env.reaction_clear, 1 - env.reaction_clear]
            for f2 in range(32):
                b2 = [(f2 >> bb) & 1 for bb in (4, 3, 2, 1, 0)]
                pf = math.prod(per[i][b2[i]] for i in range(5))
                for dn in range(D + 1):
                    P[a][s][dn * 32 + f2] = q_next[dn] * pf
    return P, R, event, sent, dropped


@pytest.mark.parametrize("name", list(F64_SCENARIOS))
def test_exact_model_is_float64_from_the_parameters_on(name):
    """P, R, event, sent and dropped equal a plain-Python float64 computation to 1e-12.

    Float32 anywhere on the way would show: it keeps ~7 significant digits, so an event probability
    of ~0.5 would be off by ~1e-8 and a reward of ~37 by ~1e-6.
    """
    params = Params.from_overrides(F64_SCENARIOS[name])
    m = build_model(params)
    P, R, event, sent, dropped = _reference_float64(params)
    for got, want in (
        (m.P, P),
        (m.R, R),
        (m.event, event),
        (m.sent, sent),
        (m.dropped, dropped),
    ):
        assert got.dtype == torch.float64
        want = torch.tensor(want, dtype=torch.float64)
        err = float((got - want).abs().max() / want.abs().max().clamp(min=1.0))
        assert err < 1e-12, err


def test_closest_decisions_are_the_smallest_margins_and_their_cost_is_exact():
    """The table the solve recipe prints: rows in order of the smallest margin |Q*(comm) −
    Q*(radar)| over queue lengths; each row's ratio is the optimum with the other mode taken at
    that factor combination (every d), evaluated here independently; the samples that tell the
    modes apart are (1.96·(σ_comm + σ_radar)/margin)² at the combination's closest queue length,
    and the episodes are those samples over the optimum's visits per episode."""
    from irdrc.core.exact import (
        one_step_spread,
        stationary_metrics,
        stationary_occupancy,
        value_iteration,
    )
    from irdrc.runs.tables import closest_decisions

    params = Params.from_overrides({"env.p1.speed": 1.0})
    model = build_model(params)
    sol = value_iteration(model, gamma=0.99, tol=1e-9)
    lines = closest_decisions(model, sol, 0.99, count=4).splitlines()
    assert lines[0].startswith("c r w v m") and len(lines) == 5
    nf = model.num_states // (params.env.queue_capacity + 1)
    margins = (sol.q[0] - sol.q[1]).abs().view(-1, nf)
    margin = margins.min(0).values
    best = stationary_metrics(model, sol.policy).avg_reward
    spread = one_step_spread(model, sol.values, 0.99).view(2, -1, nf)
    visits = params.env.horizon * stationary_occupancy(model, sol.policy).sum(0).view(-1, nf).sum(0)
    for rank, line in enumerate(lines[1:]):
        f = int(torch.argsort(margin)[rank])
        bits = line[:9]
        assert [int(b) for b in bits.split()] == [(f >> k) & 1 for k in (4, 3, 2, 1, 0)]
        cells = line[9:].split()
        assert float(cells[2]) == pytest.approx(float(margin[f]), abs=1e-4)
        flipped = sol.policy.view(-1, nf).clone()
        flipped[:, f] = 1 - flipped[:, f]
        ratio = stationary_metrics(model, flipped.reshape(-1)).avg_reward / best
        assert float(cells[6]) == pytest.approx(ratio, abs=1e-4)
        assert ratio < 1.0  # the optimum's own mode is the better one there
        d = int(margins[:, f].argmin())
        sc, sr = float(spread[0, d, f]), float(spread[1, d, f])
        assert [float(cells[7].rstrip(",")), float(cells[8])] == pytest.approx([sc, sr], abs=0.01)
        need = (1.96 * (sc + sr) / float(margin[f])) ** 2
        # the last two columns, right-aligned in 14 and 8 characters, thousands split by spaces
        samples = float(line[-24:-10].replace(" ", ""))
        assert samples == pytest.approx(need, abs=0.5)
        episodes = float(line[-8:].replace(" ", ""))
        assert episodes == pytest.approx(need / float(visits[f]), abs=0.5)


@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"env.detection_prob": 0.9, "env.false_alarm_prob": 0.05, "reward.r5": 10},
        {"env.p1.speed": 1.0, "reward.r4": 50},
    ],
    ids=["paper", "imperfect_radar", "speed1_r4_50"],
)
def test_one_step_spread_is_the_simulators(overrides):
    """``one_step_spread`` against the simulator: from a calm state, a risky one and one with an
    object nearby (the radar reaction), each action 200 000 steps of ``Dynamics``, the sample
    standard deviation of r + γ·V*(s′). Tolerance: the rarest outcome here (an event, p ≈ 0.02)
    gives the one-step value a kurtosis of about 1/p ≈ 50, so the sample sd's relative standard
    error is about ½·√(50/200 000) ≈ 0.8 %; 4 % is five of them. Without Var[V*(s′)] the calm
    state's radar spread is 12 % lower, and without the false alarms' r5² the imperfect radar's
    calm spread is several times lower, so either mistake fails."""
    from irdrc.core.dynamics import Dynamics
    from irdrc.core.exact import one_step_spread, value_iteration

    params = Params.from_overrides(overrides)
    model = build_model(params)
    sol = value_iteration(model, gamma=0.99, tol=1e-9)
    spread = one_step_spread(model, sol.values, 0.99)
    dyn = Dynamics(params)
    gen = torch.Generator().manual_seed(0)
    n = 200_000
    calm, risky, nearby = state_index(2, 0, 0, 0, 0, 0), state_index(5, 1, 1, 0, 1, 0), 1
    for s in (calm, risky, nearby):
        for a in (0, 1):
            out = dyn.step(torch.full((n,), s), torch.full((n,), a), gen)
            y = out.reward.double() + 0.99 * sol.values[out.state]
            assert float(y.std()) == pytest.approx(float(spread[a, s]), rel=0.04), (s, a)


def test_one_step_spread_is_for_a_scenarios_binary_model():
    from irdrc.core.exact import one_step_spread

    model = build_model(Params(), shares=(0.0, 0.5, 1.0))
    with pytest.raises(ValueError, match="binary model"):
        one_step_spread(model, torch.zeros(model.num_states), 0.99)


def test_tables_print_values_below_the_solves_accuracy_as_such():
    """A long-run value under the exact solves' accuracy (1e-12) is not shown as float noise:
    `solve.py env=large env.packets_good=800` printed a random policy's drop rate as 2.10e-314."""
    from irdrc.core.metrics import format_table

    row = {"drop_rate": 2.1e-314, "mean_queue": -3e-17, "throughput": 0.0, "avg_reward": 1.19e-10}
    cells = format_table({"p": row}, names=tuple(row)).splitlines()[-1].split()
    assert cells == ["p", "<1e-12", "<1e-12", "0", "1.19e-10"]
