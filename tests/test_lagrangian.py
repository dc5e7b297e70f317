"""The Lagrangian DQN (irdrc.agents.lagrangian): its loss, the greedy path over μ, the final
policy's measured search, the long-run measurement it relies on, its config, and learning."""

from __future__ import annotations

import itertools
import json
import math

import pytest
import torch
from conftest import load
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate

from irdrc.agents import lagrangian as L
from irdrc.agents import policy_search
from irdrc.agents.base import Hooks
from irdrc.agents.configs import LagrangianConfig, OffPolicyConfig
from irdrc.agents.offpolicy import RewardCenter
from irdrc.agents.policy_search import (
    SearchConfig,
    greedy_path,
    path_index,
    pooled,
    rate_order,
)
from irdrc.core.cmdp import solve_cmdp
from irdrc.core.env import DFRCEnv
from irdrc.core.evaluate import STATE_ACTION_SUMS, long_run
from irdrc.core.exact import build_model, stationary_metrics, stationary_occupancy
from irdrc.core.params import Params


@pytest.fixture(scope="module")
def paper():
    return build_model(Params())


def test_yaml_profile_equals_the_dataclass_defaults():
    """The composed profile (DQN's YAML and the differences stated over it) is the code's."""
    got = load("constrained", "learner=dqn_lagrangian").algo
    assert got == LagrangianConfig() and got.name == "dqn_lagrangian"
    assert LagrangianConfig().dqn.total_frames == 80_000


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("mu_lr", -1.0),
        ("mu_max", 0.0),
        ("mu_init", 0.0),
        ("search_span", 0.5),
        ("measure_envs", 1),
        ("measure_max_blocks", 0),
        ("bogus", 1),
        ("average_tau", 0.01),  # a DQN option the Lagrangian loop does not implement
        ("confirm", "maybe"),
    ],
)
def test_bad_settings_named(key, value):
    with pytest.raises(ValueError, match=key):
        LagrangianConfig.from_sections({key: value})


def test_bad_target_and_objective_named():
    with pytest.raises(ValueError, match="target_miss"):
        LagrangianConfig(target_miss=1.5)
    with pytest.raises(ValueError, match="objective"):
        LagrangianConfig(objective="packets")


def test_greedy_path_is_greedy_at_every_multiplier():
    """Every table of the path is the argmax of Q_J − μ·Q_C on its interval of μ, and neighbours
    differ in exactly one state."""
    gen = torch.Generator().manual_seed(0)
    q = torch.randn(40, 2, 2, generator=gen, dtype=torch.float64)
    breaks, tables = greedy_path(q)
    assert len(tables) == len(breaks) + 1
    assert breaks == sorted(breaks) and all(b > 0 for b in breaks)
    for a, b in itertools.pairwise(tables):
        assert int((a != b).sum()) == 1
    edges = [0.0, *breaks, breaks[-1] * 2 + 1]
    for k, table in enumerate(tables):
        mu = 0.5 * (edges[k] + edges[k + 1])
        greedy = ((q[:, 0] - mu * q[:, 1]).argmax(-1) == 1).long()
        assert torch.equal(table, greedy), k
        assert path_index(breaks, mu) == k


def _batch(obs, action, nobs, sent, missed, event):
    n = len(action)
    return TensorDict(
        {
            "observation": obs,
            "action": torch.tensor(action),
            "next": {
                "observation": nobs,
                "sent": torch.tensor(sent),
                "missed": torch.tensor(missed),
                "event": torch.tensor(event),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        batch_size=[n],
    )


def test_loss_is_double_dqn_on_both_heads():
    """The TD targets by hand: next action greedy on Q_J − μ·Q_C of the online network, valued by
    the target network's heads; the cost signal is missed − m*·event."""
    torch.manual_seed(0)
    heads = L.TwoHeads(torch.nn.Linear(3, 4))
    mu = torch.tensor(2.0)
    loss = L.LagrangianDQNLoss(heads, mu, gamma=0.9, objective_key="sent", target_miss=0.1)
    SoftUpdate(loss, tau=0.01)  # the learner's target updater (the loss warns without one)
    with torch.no_grad():  # make the target network differ from the online one
        for p in loss.target_value_network_params.values(True, True):
            p.add_(0.3)
    obs, nobs = torch.randn(5, 3), torch.randn(5, 3)
    td = _batch(obs, [0, 1, 0, 1, 1], nobs, [2, 0, 1, 0, 3], [1, 0, 0, 0, 0], [1, 1, 0, 0, 1])
    out = loss(td)
    q, qn = heads(obs), heads(nobs)
    with loss.target_value_network_params.to_module(loss.value_network):
        qt = loss.value_network(nobs)
    best = (qn[:, 0] - 2.0 * qn[:, 1]).argmax(-1)
    r = torch.tensor([[2.0, 0.9], [0.0, -0.1], [1.0, 0.0], [0.0, 0.0], [3.0, -0.1]])
    target = r + 0.9 * qt[torch.arange(5), :, best]
    taken = q[torch.arange(5), :, td["action"]]
    want = (taken - target).pow(2).sum(-1).mean()
    assert float(out["loss"].detach()) == pytest.approx(float(want.detach()), rel=1e-5)
    assert td["td_error"].shape == (5,)
    # algo.double_dqn=false: the next action is greedy in the target network itself
    loss.double_dqn = False
    with torch.no_grad():  # a target network that ranks the actions the other way round
        for p in loss.target_value_network_params.values(True, True):
            p.mul_(-1.0)
    with loss.target_value_network_params.to_module(loss.value_network):
        qt = loss.value_network(nobs)
    best_t = (qt[:, 0] - 2.0 * qt[:, 1]).argmax(-1)
    assert not torch.equal(best, best_t)  # the case tells the two apart
    target_t = r + 0.9 * qt[torch.arange(5), :, best_t]
    want_t = (taken - target_t).pow(2).sum(-1).mean()
    assert float(loss(td)["loss"].detach()) == pytest.approx(float(want_t.detach()), rel=1e-5)


def test_long_run_matches_the_exact_stationary_metrics(paper):
    """The LP's randomised optimum at 0.05 lingers in the full-queue state; chains that are never
    reset measure its stationary rates. 128 chains × 3 000 steps after 1 000 of burn-in: the
    half-widths are ≈ 0.005 for miss detection and ≈ 0.04 for throughput; 4 half-widths (≈ 8σ)
    make a false failure negligible, while episodes of 400 steps from a uniform reset (what
    ``evaluate`` measures) are off by more than that for this policy."""
    sol = solve_cmdp(paper, 0.05)
    ev = long_run(Params(), sol.p_radar, envs=128, steps=3000, burn_in=1000, seed=1)
    for key in ("miss_detection", "throughput", "radar_fraction"):
        got, want, hw = ev.metrics.as_dict()[key], sol.metrics.as_dict()[key], ev.ci95[key]
        assert abs(got - want) <= 4 * hw, (key, got, want, hw)
    assert ev.steps == 128 * 4000
    with pytest.raises(ValueError, match="p_radar"):
        long_run(Params(), torch.full((10,), 0.5))


@pytest.mark.e2e
def test_final_policy_lands_on_the_target_by_measurement(paper):
    """Heads whose path sends radar first where events are likeliest and the queue is shortest
    (Q_J gain 1, Q_C gain P(event)·(11 − d)): the measured search must end in a policy that
    randomises in at most one state and whose *exact* miss detection is within 0.01 of the target.
    With 64 chains × 1 500 steps the measurement's half-widths are ≈ 0.006 at 0.1 (three seeds
    were within 0.005 when this was written); a search on the wrong side of the target, or a
    mixture that ignores its measurements, lands 0.02 – 0.1 away."""
    event = paper.event.to(torch.float64)
    d = torch.arange(paper.num_states) >> 5
    q = torch.zeros(paper.num_states, 2, 2, dtype=torch.float64)
    q[:, 0, 0] = 1.0
    q[:, 1, 0] = event * (11 - d) + 1e-6 * torch.arange(paper.num_states)  # distinct breakpoints
    cfg = LagrangianConfig(
        target_miss=0.1,
        search=SearchConfig(measure_envs=64, measure_steps=1500, measure_burn_in=300, mix_steps=6),
    )
    breaks, _ = greedy_path(q)
    policy, facts = L.final_policy(q, Params(), breaks[len(breaks) // 2], cfg, seed=0)
    exact = stationary_metrics(paper, policy)
    assert abs(exact.miss_detection - 0.1) <= 0.01, (exact.miss_detection, facts)
    assert int((policy > 1e-9).all(-1).sum()) <= 1
    assert facts["switch_state"] is not None and 0 < facts["p_switch"] < 1
    assert facts["measure_env_steps"] >= facts["measurements"] * 64 * 1800


def _path_heads(paper) -> torch.Tensor:
    """Heads whose path sends radar first where events are likeliest and the queue is shortest."""
    event = paper.event.to(torch.float64)
    d = torch.arange(paper.num_states) >> 5
    q = torch.zeros(paper.num_states, 2, 2, dtype=torch.float64)
    q[:, 0, 0] = 1.0
    q[:, 1, 0] = event * (11 - d) + 1e-6 * torch.arange(paper.num_states)  # distinct breakpoints
    return q


def _exact_long_run(paper, low_seed: int | None = None, low: float = 1.0):
    """A stand-in for ``long_run`` that measures exactly: per-(state, action) sums
    (``by_state``) from the policy's exact occupancy over 10⁶ steps, so that the search's pooled
    rates are the model's; on the stream seeded ``low_seed`` every missed event is counted
    ``low`` times (a stream whose numbers read miss detection low by that factor)."""
    import types

    def fake(params, p_radar, *, seed, by_state=False, **kw):
        probs = torch.stack([1 - p_radar, p_radar], -1)
        occ = stationary_occupancy(paper, probs).T * 1e6  # [S, 2] steps per state and action
        sums = {
            "steps": occ,
            "visits": occ,
            "sent": occ * paper.sent.T,
            "capacity": occ * paper.capacity.T,
            "reward": occ * paper.R.T,
            "event": occ * paper.event[:, None],
            "missed": occ * paper.missed.T * (low if seed == low_seed else 1.0),
        }
        return types.SimpleNamespace(steps=1000, by_state=sums)

    return fake


def _misordered_heads(paper) -> tuple[torch.Tensor, list[int]]:
    """Heads that order the path by event probability (riskier states radar first) except six
    risky states at queue length 8, which they hold to comm longest, and those states."""
    event = paper.event.to(torch.float64)
    q = torch.zeros(paper.num_states, 2, 2, dtype=torch.float64)
    q[:, 0, 0] = 1.0
    q[:, 1, 0] = event + 1e-6 * torch.arange(paper.num_states)
    bad = [s for s in range(paper.num_states) if s >> 5 == 8 and float(event[s]) > 0.05][:6]
    q[bad, 1, 0] = 1e-4
    return q, bad


def test_ranking_recovers_what_misordered_heads_lose(paper, monkeypatch):
    """Six risky states the heads keep in comm longest (``_misordered_heads``) spoil the path near
    a 5 % target: with them in comm, a table that sends anywhere lets the queue fall to 8, where
    they miss, so the path's neighbours promise 0.155 packets per step at the target (0.38 of the
    LP's 0.413, computed when this was written). Measured exactly (``_exact_long_run``), the
    ranked family, whose order comes from the measured data per missed event in comm, finds the
    LP's pair (promise 0.4132) and ends within 0.3 % of the LP; 0.95 leaves room for the
    randomisation's search."""
    monkeypatch.setattr(policy_search, "long_run", _exact_long_run(paper))
    q, bad = _misordered_heads(paper)
    cfg = LagrangianConfig(target_miss=0.05)
    breaks, _ = greedy_path(q)
    policy, facts = L.final_policy(q, Params(), breaks[len(breaks) // 2], cfg, seed=0)
    exact = stationary_metrics(paper, policy)
    lp = solve_cmdp(paper, 0.05).metrics.throughput
    assert exact.miss_detection <= 0.05 + 1e-9
    assert facts["ranked"] is True and facts["path_promise"] <= 0.5 * lp, facts
    json.dumps(facts, allow_nan=False)  # the summary's JSON takes them
    assert exact.throughput >= 0.95 * lp, (exact.throughput / lp, facts)
    assert bool((policy[bad, 1] == 1).all())  # the misordered states watch the road


def test_ranking_loses_to_a_path_that_promises_more(paper, monkeypatch):
    """Where the path's pair promises more at the target than the ranked family's, the path's is
    kept and the final policy is the path's mixture (to rounding: measured exactly, the pooled
    rates do not depend on which tables were measured); for the average-reward objective (radar
    earns reward too, so comm's data per missed event is not the trade) the ranking is not tried."""
    monkeypatch.setattr(policy_search, "long_run", _exact_long_run(paper))
    q = _path_heads(paper)
    breaks, _ = greedy_path(q)
    mu = breaks[len(breaks) // 2]
    cfg = LagrangianConfig(target_miss=0.1)
    search = policy_search.FinalPolicySearch(q, Params(), mu, 0.1, "sent", cfg.search, 0)
    lo, hi, fresh, _ = search.path_search()
    want, _, _ = search.mix((lo, hi), fresh)
    # A ranked family that can only offer radar-always: its promise is 0.
    monkeypatch.setattr(policy_search, "rate_order", lambda pool, key: [])
    policy, facts = L.final_policy(q, Params(), mu, cfg, 0)
    assert facts["ranked"] is False and facts["rank_promise"] == 0.0, facts
    assert torch.allclose(policy[:, 1], want, atol=1e-9, rtol=0)
    cfg = LagrangianConfig(target_miss=0.1, objective="avg_reward")
    assert L.final_policy(q, Params(), mu, cfg, 0)[1]["ranked"] is None


def test_where_the_target_binds_the_lp_communicates_in_the_top_of_the_rate_ranking(paper):
    """The premise of the ranked family (docs/CONSTRAINED.md): at p^v_1 = 0.1 and a 5 % target the
    LP communicates (at all) in exactly the states ranked first by the model's data per missed
    event in comm — the all-favourable states with 4 to 10 packets queued, tied among themselves."""
    sol = solve_cmdp(paper, 0.05)
    comm = set((sol.p_radar < 1).nonzero().flatten().tolist())
    ratio = paper.sent[0].double() / paper.missed[0].double()
    top = set(torch.argsort(ratio, descending=True)[: len(comm)].tolist())
    assert comm == top and len(comm) == 7
    assert {s >> 5 for s in comm} == set(range(4, 11))  # the queue length d is the top bits


def test_rate_order_shrinks_seldom_seen_states_towards_the_average():
    """Data per comm step over missed events per comm step, the latter shrunk towards the average
    over every state seen in comm (``RATE_PRIOR_STEPS`` = 500 comm steps of weight); states never
    seen in comm are not ranked. Worked by hand: average missed per comm step = 40/20 000 = 0.002,
    so the prior adds 1 missed event in 500 steps; state 0: 4 / (21/10 500) = 2 000; state 2:
    1 / (11/5 500) = 500; state 3 (seen 100 times, no miss): 2 / (1/600) = 1 200, where without
    the shrinkage its rate of 0 would rank it above every other state; state 4: 2 / (11/5 400)
    ≈ 982. With 3 misses in its 100 steps state 3 falls to 2 / (4.075/600) ≈ 294, the lowest."""
    n = torch.tensor([10_000.0, 0.0, 5_000.0, 100.0, 4_900.0])
    comm = {
        "steps": n,
        "sent": torch.tensor([4.0, 0.0, 1.0, 2.0, 2.0]) * n,
        "missed": torch.tensor([20.0, 0.0, 10.0, 0.0, 10.0]),
    }
    pool = {k: torch.stack([v, torch.full((5,), 100.0)], -1) for k, v in comm.items()}
    assert policy_search.RATE_PRIOR_STEPS == 500.0
    assert rate_order(pool, "sent") == [2, 4, 3, 0]
    pool["missed"][3, 0] = 3.0
    assert rate_order(pool, "sent") == [3, 2, 4, 0]
    assert rate_order({k: torch.zeros(5, 2) for k in pool}, "sent") == []


def test_mix_lands_within_the_tolerance_of_the_target(paper, monkeypatch):
    """The randomisation's regula falsi, on exact measurements, ends at or below the target and
    within ``MIX_TOLERANCE`` of it, in fewer measurements than ``mix_steps`` allows (a bisection on
    the log-odds takes all of them)."""
    monkeypatch.setattr(policy_search, "long_run", _exact_long_run(paper))
    q = _path_heads(paper)
    breaks, _ = greedy_path(q)
    cfg = LagrangianConfig(target_miss=0.1).search
    search = policy_search.FinalPolicySearch(
        q, Params(), breaks[len(breaks) // 2], 0.1, "sent", cfg, 0
    )
    lo, hi, fresh, _ = search.path_search()
    before = len(search.visits)
    p, state, mixed = search.mix((lo, hi), fresh)
    exact = stationary_metrics(paper, torch.stack([1 - p, p], -1)).miss_detection
    assert mixed and 0 < float(p[state]) < 1
    assert 0.1 * (1 - policy_search.MIX_TOLERANCE) - 1e-9 <= exact <= 0.1 + 1e-9, exact
    assert len(search.visits) - before < cfg.mix_steps


def test_a_search_that_sees_no_event_keeps_the_safest_table(paper, monkeypatch):
    """Measurements too short to see an event (miss detection NaN) show no table meeting the
    target: from a multiplier past the path's last break the search keeps the safest table and its
    final policy is that table, never a NaN mixture (it once indexed past the path's breaks)."""
    q = _path_heads(paper)
    breaks, tables = greedy_path(q)
    cfg = LagrangianConfig(target_miss=0.05).search
    search = policy_search.FinalPolicySearch(q, Params(), breaks[-1] * 10, 0.05, "sent", cfg, 0)
    monkeypatch.setattr(search, "rates", lambda p_radar, fresh=False: (math.nan, 0.0))
    lo, hi, _, mu = search.path_search()
    assert lo is None and mu is None and torch.equal(hi, tables[-1].double())
    p, state, mixed = search.mix((tables[-2].double(), tables[-1].double()), False)
    assert torch.equal(p, tables[-1].double()) and not mixed and state is not None


def test_long_run_sums_per_state_and_action(paper):
    """``by_state`` leaves the random numbers, and so the metrics, as they were, and its sums
    agree with the model: the last block's visits are the radar fraction's steps, every step run
    is counted, and in the two most visited comm states data per comm step and events per comm
    step are within 4 binomial standard errors (≈ 8σ over the per-step spread; chains are not
    independent samples, so a loose bound) of the model's."""
    sol = solve_cmdp(paper, 0.05)
    kw = dict(envs=64, steps=1000, burn_in=500, seed=3)
    plain = long_run(Params(), sol.p_radar, **kw)
    ev = long_run(Params(), sol.p_radar, by_state=True, **kw)
    for key in ("miss_detection", "throughput", "radar_fraction", "mean_queue"):
        assert getattr(plain.metrics, key) == getattr(ev.metrics, key), key
    assert plain.by_state is None
    b = ev.by_state
    assert set(b) == {*STATE_ACTION_SUMS, "visits"}
    assert all(v.shape == (paper.num_states, 2) for v in b.values())
    assert float(b["steps"].sum()) == ev.steps == 64 * 1500
    assert float(b["visits"][:, 1].sum()) == pytest.approx(ev.metrics.radar_fraction * 64_000)
    assert float(b["visits"].sum()) == 64_000
    comm = {k: v[:, 0] for k, v in b.items()}
    for s in comm["steps"].topk(2).indices.tolist():
        n = float(comm["steps"][s])
        assert n > 500
        assert float(comm["sent"][s]) / n == pytest.approx(float(paper.sent[0, s]), abs=0.05)
        e = float(paper.event[s])
        assert abs(float(comm["event"][s]) / n - e) <= 4 * math.sqrt(e * (1 - e) / n) + 1e-9
        assert float(comm["missed"][s]) == float(comm["event"][s])  # comm misses every event


def test_pooled_rates_weigh_visits_by_every_measurement():
    """``pooled``: a policy's miss detection and objective are its visits weighted by the rates
    per state and action of the whole pool, not by its own few events."""
    visits = torch.tensor([[10.0, 0.0], [0.0, 30.0]])  # state 0 comm, state 1 radar
    pool = {
        "steps": torch.tensor([[1000.0, 1000.0], [1000.0, 1000.0]]),
        "event": torch.tensor([[100.0, 100.0], [300.0, 300.0]]),  # P(event): 0.1, 0.3
        "missed": torch.tensor([[100.0, 0.0], [300.0, 30.0]]),  # radar misses 10 % in state 1
        "sent": torch.tensor([[2000.0, 0.0], [1000.0, 0.0]]),
    }
    miss, sent = pooled(visits, pool, "sent")
    # missed: 10·0.1 + 30·0.03 = 1.9; events: 10·0.1 + 30·0.3 = 10; data: 10·2 / 40 steps
    assert miss == pytest.approx(0.19)
    assert sent == pytest.approx(0.5)


@pytest.mark.parametrize("confirm", [True, False])
def test_confirmation_undoes_a_search_measured_low(paper, monkeypatch, confirm):
    """A measurement whose random numbers happen to read miss detection 1/6 low for every policy
    (the search's stream; the confirmation's reads exactly) stands in for the winner's curse: the
    search keeps tables whose measured miss fell below the target. Measurements are exact but for
    that factor, so the outcome is exact: without the confirmation the final policy misses
    ≈ 0.1 · 6/5 = target + 0.02 (as the search measured it, 1/6 low); with it, the fresh
    measurements climb the path to neighbours on either side of the target and the mixture lands
    on it."""
    monkeypatch.setattr(
        policy_search, "long_run", _exact_long_run(paper, low_seed=0 + 7919, low=5 / 6)
    )
    q = _path_heads(paper)
    cfg = LagrangianConfig(target_miss=0.1, search=SearchConfig(mix_steps=12, confirm=confirm))
    breaks, _ = greedy_path(q)
    policy, facts = L.final_policy(q, Params(), breaks[len(breaks) // 2], cfg, seed=0)
    exact = stationary_metrics(paper, policy).miss_detection
    assert facts["confirmed"] is confirm
    if confirm:
        # 12 bisection steps on the log-odds leave the weight within ≈ 0.002 of the crossing
        assert 0.1 - 0.003 <= exact <= 0.1, (exact, facts)
    else:
        assert 0.1 + 0.017 <= exact <= 0.1 + 0.02, (exact, facts)
    assert facts["measured_final_miss"] <= 0.1


def test_dual_step_is_relative_and_bounded():
    cfg = LagrangianConfig(target_miss=0.05, mu_lr=1.0, mu_min=1e-3, mu_max=1e3)
    assert L.dual_step(10.0, 0.05, 1000, cfg) == pytest.approx(10.0)
    assert L.dual_step(10.0, 1.0, 1000, cfg) == pytest.approx(10.0 * math.e)  # error clipped at 1
    assert L.dual_step(10.0, 0.0, 500, cfg) == pytest.approx(10.0 * math.exp(-0.5))
    assert L.dual_step(100.0, 0.075, 1000, cfg) == pytest.approx(100.0 * math.exp(0.5))
    assert L.dual_step(999.0, 1.0, 10_000, cfg) == 1e3
    assert L.dual_step(2e-3, 0.0, 10_000, cfg) == 1e-3


def test_short_run_reports_mu_measured_miss_and_a_probability_policy():
    cfg = LagrangianConfig(
        dqn=OffPolicyConfig(
            num_envs=8,
            frames_per_batch=32,
            total_frames=1024,
            init_random_frames=256,
            batch_size=1000,
            updates_per_batch=4,
            reward_means=False,
            name="dqn_lagrangian",
        ),
        search=SearchConfig(measure_envs=8, measure_steps=50, measure_burn_in=10, mix_steps=2),
    )
    seen = []
    rec = L.train(Params(), cfg, seed=0, eval_every_frames=512, hooks=Hooks(on_batch=seen.append))
    assert {"mu", "measured_miss", "loss"} <= set(seen[-1])
    assert rec.policy.shape == (1, 352, 2)
    assert torch.allclose(rec.policy.sum(-1), torch.ones(1, 352, dtype=torch.float64))
    assert rec.env_steps == rec.training_env_steps + rec.measurement_env_steps
    assert (
        rec.measurement_env_steps == rec.info["measure_env_steps"]
        and rec.training_env_steps == 1024
    )
    assert len(rec.info["mu_trace"]) == 1024 // 32
    assert math.isfinite(rec.info["mu"]) and rec.info["mu"] >= 0
    with pytest.raises(ValueError, match="resume"):
        L.train(Params(), cfg, resume={})


@pytest.mark.slow
def test_meets_a_loose_target():
    """p^v_1 = 1, target 0.15: the LP sends everything (throughput 1.0) with miss 0.15. The
    learner must end with exact miss ≤ 0.16 and throughput ≥ 0.95 of the LP's (the benchmark's
    criteria), on two seeds."""
    params = Params.from_overrides({"env.p1.speed": 1.0})
    model = build_model(params)
    lp = solve_cmdp(model, 0.15)
    for seed in (0, 1):
        rec = L.train(params, LagrangianConfig(target_miss=0.15), seed=seed)
        m = stationary_metrics(model, rec.policy[0])
        assert m.miss_detection <= 0.16, (seed, m.miss_detection)
        assert m.throughput >= 0.95 * lp.value, (seed, m.throughput)


@pytest.mark.slow
def test_meets_the_binding_target_on_unseen_seeds():
    """p^v_1 = 0.1, target 0.05, where the LP communicates only in the all-favourable long-queue
    states (0.413 packets per step): on two seeds beyond both benchmarks' (0–19), the learner must
    meet the benchmark's criteria (exact miss ≤ 0.06, throughput ≥ 0.95 of the LP's) within 20 M env
    steps. Without the ranked family (the heads' path alone) seed 21 ends at 0.81 of the LP's
    throughput (measured when this was written)."""
    params = Params()
    model = build_model(params)
    lp = solve_cmdp(model, 0.05)
    for seed in (20, 21):
        rec = L.train(params, LagrangianConfig(target_miss=0.05), seed=seed)
        m = stationary_metrics(model, rec.policy[0])
        assert m.miss_detection <= 0.06, (seed, m.miss_detection, rec.info)
        assert m.throughput >= 0.95 * lp.value, (seed, m.throughput / lp.value, rec.info)
        assert rec.env_steps <= 20_000_000, (seed, rec.env_steps)


def test_objective_centering_shifts_the_objective_signal_only():
    params = Params()
    env = DFRCEnv(params, batch_size=[1])
    heads, _, _ = L.make_network(env, LagrangianConfig())
    loss = L.LagrangianDQNLoss(
        heads, torch.tensor(1.0), gamma=0.99, objective_key="sent", target_miss=0.05
    )
    SoftUpdate(loss, tau=0.01)
    td = TensorDict(
        {
            ("next", "sent"): torch.tensor([[3.0], [0.0]]),
            ("next", "missed"): torch.tensor([[False], [True]]),
            ("next", "event"): torch.tensor([[False], [True]]),
        },
        batch_size=[2],
    )
    plain = loss.signals(td)
    # the shared loop centres the objective's key in every sample (``TrainingLoop.center_key``)
    center = RewardCenter(0.01, value=0.75)
    centred = loss.signals(center.center(td.clone(), ("next", "sent")))
    assert torch.allclose(centred[:, 0], plain[:, 0] - 0.75)
    assert torch.equal(centred[:, 1], plain[:, 1])  # the cost signal is untouched


def test_centering_runs_and_tracks_the_objective_mean(monkeypatch):
    seen = []
    original = RewardCenter.update

    def spy(self, reward):
        original(self, reward)
        seen.append(self.value)

    monkeypatch.setattr(RewardCenter, "update", spy)
    dqn = OffPolicyConfig(
        num_envs=8,
        frames_per_batch=32,
        total_frames=256,
        init_random_frames=64,
        buffer_size=256,
        batch_size=32,
        updates_per_batch=4,
        reward_means=False,
        reward_centering=0.01,
        name="dqn_lagrangian",
    )
    cfg = LagrangianConfig(
        dqn=dqn, search=SearchConfig(measure_envs=4, measure_steps=20, measure_burn_in=0)
    )
    L.train(Params(), cfg, seed=0, eval_every_frames=128)
    assert len(seen) == 256 // 32 and all(0.0 <= v <= 4.0 for v in seen)  # packets sent per step
