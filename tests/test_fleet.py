"""The exact fleet model (MODEL.md § C): one vehicle is today's model, access and cooperation rules
by hand, and independent vehicles add up."""

from __future__ import annotations

import pytest
import torch

from irdrc.core.exact import stationary_metrics, value_iteration
from irdrc.core.params import Params
from irdrc.fleet.model import FleetModel
from irdrc.fleet.policies import baselines, joint_from_single
from irdrc.fleet.scorer import fleet_metrics
from irdrc.fleet.spec import FleetSpec, grants


@pytest.fixture(scope="module")
def one():
    return FleetModel(FleetSpec(vehicles=1))


def test_one_vehicle_is_todays_model(one):
    """N = 1: the expected rewards are the single-vehicle model's bit for bit, value iteration
    gives the same policy, and the exact metrics agree to 1e-12."""
    single = one.single
    for a in (0, 1):
        R = one.reward(a).reshape(one.RW, one.X)
        assert torch.equal(R, single.R[a][one.index])
    sol = value_iteration(one)
    ref = value_iteration(single)
    assert torch.equal(sol.policy.reshape(one.RW, one.X), ref.policy[one.index])
    # the fleet's values are value iteration's (within tol·γ/(1 − γ)); the reference's are exact
    assert float((sol.values.reshape(one.RW, one.X) - ref.values[one.index]).abs().max()) < 1e-6
    got, per = fleet_metrics(one, sol.policy)
    want = stationary_metrics(single, ref.policy)
    for key in ("avg_reward", "throughput", "miss_detection", "radar_fraction", "drop_rate"):
        assert getattr(got, key) == pytest.approx(getattr(want, key), abs=1e-12), key
    assert per[0]["denial_rate"] == 0.0


def test_one_vehicle_with_an_imperfect_radar_is_todays_model():
    params = Params.from_overrides(
        {"env.detection_prob": 0.8, "env.false_alarm_prob": 0.1, "reward.r5": 7.0}
    )
    m = FleetModel(FleetSpec(vehicle=params, vehicles=1, share=0.7))
    for a in (0, 1):
        R = m.reward(a).reshape(m.RW, m.X)
        assert float((R - m.single.R[a][m.index]).abs().max()) < 1e-12


def test_uplink_access_by_hand():
    assert grants((0, 2), 2, "scheduled") == [(1.0, frozenset({0, 2}))]
    three = grants((0, 1, 2), 1, "scheduled")
    assert sorted(sorted(g) for _, g in three) == [[0], [1], [2]]
    assert all(p == pytest.approx(1 / 3) for p, _ in three)
    two_of_three = grants((0, 1, 2), 2, "scheduled")
    assert len(two_of_three) == 3 and all(len(g) == 2 for _, g in two_of_three)
    assert grants((0, 1, 2), 2, "collision") == [(1.0, frozenset())]
    assert grants((), 1, "collision") == [(1.0, frozenset())]


def test_cooperative_perception_and_denial_rewards_by_hand():
    """One state, computed by hand: vehicle 1 in comm, the other vehicle in radar, share 0.5,
    P_d = 1. Event probability e; granted: (1 − e)·r_comm + e·(0.5·r_comm − 0.5·r3); denied: the
    comm reward is lost, the penalty stays; in radar: e·r4·(b + 1)."""
    m = FleetModel(FleetSpec(vehicles=2, share=0.5))
    t = m.kernels[0]
    e, rc = t.event, t.r_comm
    granted = m.vehicle_terms(0, 0, others_radar=1, granted=True)
    assert torch.allclose(granted["reward"], (1 - e) * rc + e * (0.5 * rc - 0.5 * 50.0))
    assert torch.allclose(granted["missed"], 0.5 * e)
    denied = m.vehicle_terms(0, 0, others_radar=1, granted=False)
    assert torch.allclose(denied["reward"], -0.5 * 50.0 * e)
    assert float(denied["sent"].abs().max()) == 0.0 and float(denied["denied"].min()) == 1.0
    radar = m.vehicle_terms(0, 1, others_radar=0, granted=False)
    assert (
        torch.allclose(radar["reward"], e * t.detect_reward) and float(radar["missed"].max()) == 0
    )
    alone = m.vehicle_terms(0, 0, others_radar=0, granted=True)
    assert torch.allclose(alone["missed"], e)  # nobody else watches: every event missed


def test_independent_vehicles_add_up():
    """Two vehicles with two channels and no sharing do not interact (only road and weather are
    shared, and those follow their chains): N copies of the single optimum give twice its
    reward and throughput and its miss detection, and the centralised optimum is no better."""
    m = FleetModel(FleetSpec(vehicles=2, channels=2, share=0.0))
    ref = value_iteration(m.single)
    want = stationary_metrics(m.single, ref.policy)
    got, per = fleet_metrics(m, joint_from_single(m, ref.policy))
    assert got.avg_reward == pytest.approx(2 * want.avg_reward, abs=1e-10)
    assert got.throughput == pytest.approx(2 * want.throughput, abs=1e-10)
    assert got.miss_detection == pytest.approx(want.miss_detection, abs=1e-10)
    assert per[0]["avg_reward"] == pytest.approx(per[1]["avg_reward"], abs=1e-10)
    best, _ = fleet_metrics(m, value_iteration(m).policy)
    assert best.avg_reward == pytest.approx(got.avg_reward, abs=1e-7)


def test_different_independent_vehicles_add_up():
    """Vehicles that differ (env.p1.speed 0.1 and 1.0, reward.r4 5 and 50), with two channels and
    no sharing, do not interact: each vehicle's row is its own single-vehicle optimum's exact
    metrics, the fleet's reward their sum, and the centralised optimum no better than each
    vehicle's own optimum (``single_optima``)."""
    from irdrc.fleet.policies import single_optima

    a = Params.from_overrides({"env.p1.speed": 0.1})
    b = Params.from_overrides({"env.p1.speed": 1.0, "reward.r4": 50.0})
    m = FleetModel(FleetSpec(vehicles=2, channels=2, share=0.0, per_vehicle=(a, b)))
    tables = single_optima(m)
    assert not torch.equal(tables[0], tables[1])  # r4 = 50 changes the single optimum
    want = [
        stationary_metrics(t.single, value_iteration(t.single).policy).avg_reward for t in m.kernels
    ]
    got, per = fleet_metrics(m, baselines(m, tables)["N copies of the single optimum"])
    assert [r["avg_reward"] for r in per[:2]] == pytest.approx(want, abs=1e-10)
    assert got.avg_reward == pytest.approx(sum(want), abs=1e-10)
    best, _ = fleet_metrics(m, value_iteration(m).policy)
    assert best.avg_reward == pytest.approx(got.avg_reward, abs=1e-7)
    with pytest.raises(ValueError, match="per-vehicle models"):
        FleetSpec(vehicles=3, per_vehicle=(a, b))
    with pytest.raises(ValueError, match="share one road"):
        FleetModel(
            FleetSpec(per_vehicle=(a, Params.from_overrides({"env.stay_good.weather": 0.8})))
        )


def test_collisions_deny_everyone_and_the_optimum_cooperates():
    """Both always in comm on one channel: under ``collision`` nothing is sent and every request
    is denied; under ``scheduled`` one is granted each step. The centralised optimum of the paper's
    two vehicles (share 0.5, one channel) beats two copies of the single optimum."""
    coll = FleetModel(FleetSpec(vehicles=2, channels=1, access="collision"))
    both_comm = torch.zeros(coll.num_states, dtype=torch.int64)
    got, per = fleet_metrics(coll, both_comm)
    assert got.throughput == 0.0 and per[-1]["denial_rate"] == 1.0
    sched = FleetModel(FleetSpec(vehicles=2, channels=1))
    _, per = fleet_metrics(sched, both_comm)
    assert per[-1]["denial_rate"] == pytest.approx(0.5, abs=1e-12)
    opt, _ = fleet_metrics(sched, value_iteration(sched).policy)
    copies, _ = fleet_metrics(sched, joint_from_single(sched, value_iteration(sched.single).policy))
    assert opt.avg_reward > copies.avg_reward


def test_round_robin_and_rotations():
    """Periodic baselines: with one vehicle, round-robin in phase is today's round-robin (exact
    metrics to 1e-12); with two on one channel, in phase they ask together (half the requests
    denied under scheduled access), in anti-phase and in the sensing rotation never."""
    one = FleetModel(FleetSpec(vehicles=1))
    ref = value_iteration(one.single).policy
    got, _ = fleet_metrics(one, baselines(one, ref)["round-robin in phase"])
    want = stationary_metrics(one.single, "round_robin")
    for key in ("avg_reward", "throughput", "miss_detection", "radar_fraction", "mean_queue"):
        assert getattr(got, key) == pytest.approx(getattr(want, key), abs=1e-12), key
    two = FleetModel(FleetSpec(vehicles=2, channels=1))
    base = baselines(two, ref)
    denial = {k: fleet_metrics(two, base[k])[1][-1]["denial_rate"] for k in base}
    assert denial["round-robin in phase"] == pytest.approx(0.5, abs=1e-12)
    assert denial["round-robin in anti-phase"] == 0.0 and denial["sensing rotation"] == 0.0
    rot, _ = fleet_metrics(two, base["sensing rotation"])
    anti, _ = fleet_metrics(two, base["round-robin in anti-phase"])
    assert rot.avg_reward == pytest.approx(anti.avg_reward, abs=1e-10)  # the same for N = 2
    assert rot.radar_fraction == pytest.approx(0.5, abs=1e-12)


def test_bad_fleets_are_refused():
    with pytest.raises(ValueError, match=r"env\.access"):
        FleetSpec(access="aloha")
    with pytest.raises(ValueError, match=r"env\.share"):
        FleetSpec(share=1.5)
    # a mapping where a vehicle's Params belongs (was "'dict' object has no attribute 'env'")
    with pytest.raises(
        ValueError, match=r"FleetSpec\(vehicle=…\) takes a vehicle's Params, got dict"
    ):
        FleetSpec(vehicle={"env.p1.speed": 0.5})
    with pytest.raises(ValueError, match=r"per_vehicle\[1\]=…\) takes a vehicle's Params"):
        FleetSpec(vehicles=2, per_vehicle=(Params(), {"env.p1.speed": 0.5}))
    big = Params.from_overrides({"env.queue_capacity": 300})  # S = 9 632 per vehicle
    with pytest.raises(ValueError, match=r"env.queue_capacity=300: a fleet's vehicle .*≤ 255"):
        FleetModel(FleetSpec(vehicle=big))
    three = FleetModel(FleetSpec(vehicles=3))  # the simulator's tables exist at any N …
    assert not three.exact
    with pytest.raises(ValueError, match="joint states"):  # … the exact solver stops at 2·10⁶
        value_iteration(three)
    with pytest.raises(ValueError, match="joint states"):
        fleet_metrics(three, torch.zeros(1, dtype=torch.int64))


def test_the_fleet_stationary_distribution_is_one_linear_solve(monkeypatch):
    """The joint queues mix slowly: power iteration took 171 operator products to a change of
    1e-13 at the paper's sizes (599 at a queue of 31). The fleet's stationary distribution is one
    GMRES solve: far fewer products, a residual ‖μP − μ‖₁ below 1e-12, and the vehicles alike get
    the same metrics to 1e-12 (power iteration left them 1e-16 apart, enough to split a printed
    rounding)."""
    two = FleetModel(FleetSpec(vehicles=2))
    ref = value_iteration(two.single).policy
    joint = joint_from_single(two, ref)
    probs = torch.nn.functional.one_hot(joint, two.num_actions).to(torch.float64)
    calls = 0
    step = FleetModel.step

    def counted(self, x, p):
        nonlocal calls
        calls += 1
        return step(self, x, p)

    monkeypatch.setattr(FleetModel, "step", counted)
    mu = two.stationary(probs)
    assert calls < 60
    monkeypatch.undo()
    assert float((two.step(mu, probs) - mu).abs().sum()) < 1e-12
    assert float(mu.min()) >= 0.0 and float(mu.sum()) == pytest.approx(1.0, abs=1e-14)
    _, per = fleet_metrics(two, joint)
    for key in ("avg_reward", "throughput", "denial_rate", "miss_detection"):
        assert per[0][key] == pytest.approx(per[1][key], abs=1e-12), key


def test_a_periodic_chain_and_a_failed_solve_still_give_the_stationary_law(monkeypatch):
    """GMRES solves a periodic chain (power iteration would oscillate forever); where GMRES stops
    short, the lazy chain (x + xP)/2, aperiodic with the same stationary law, finishes it."""
    from irdrc.core.exact import krylov

    P = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.5, 0.0]], dtype=torch.float64)
    want = torch.tensor([1.0, 2.0, 2.0], dtype=torch.float64) / 5  # μP = μ by hand

    def step(x):
        return x @ P

    start = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    mu, _ = krylov.stationary_krylov(step, start)
    assert torch.allclose(mu, want, atol=1e-12)
    solve = krylov.krylov_solve
    monkeypatch.setattr(krylov, "krylov_solve", lambda *a, **k: (start, False, solve(*a, **k)[2]))
    mu, calls = krylov.stationary_krylov(step, start, tol=1e-14)
    assert torch.allclose(mu, want, atol=1e-12) and calls > 10


@pytest.mark.parametrize("vehicles,access", [(2, "scheduled"), (3, "collision")])
def test_the_factored_operators_are_the_joint_kernels(vehicles, access):
    """``step`` and ``expect`` (each vehicle's kernel as its queue and other-component factors,
    shared prefixes and merged parts) equal the joint kernels P_rw ⊗ K_1 ⊗ … ⊗ K_N written with
    each vehicle's dense [X, X] kernel, per joint action and uplink outcome, on a random measure,
    value and policy. The vehicles differ, so each vehicle's own factors must be used. Equal to
    rounding: the sums run in another order."""
    small = {"env.queue_capacity": 2}
    per = tuple(
        Params.from_overrides({**small, "env.p1.speed": s, "env.arrival_rate": r})
        for s, r in [(0.1, 1.0), (1.0, 2.5), (0.5, 1.5)][:vehicles]
    )
    m = FleetModel(FleetSpec(vehicles=vehicles, channels=1, access=access, per_vehicle=per))
    g = torch.Generator().manual_seed(0)
    S, A = m.num_states, m.num_actions
    x = torch.rand(m.shape(), generator=g, dtype=torch.float64)
    V = torch.rand(m.shape(), generator=g, dtype=torch.float64)
    probs = torch.rand(S, A, generator=g, dtype=torch.float64)
    probs[:, 1] = 0.0  # an action never taken is skipped
    probs = probs / probs.sum(1, keepdim=True)

    def joint_kernel(W, names, forward):  # (P_rw ⊗ K_1 ⊗ … ⊗ K_N) one axis at a time
        kernels = [m.P_rw] + [m.kernels[i].K[n] for i, n in enumerate(names)]
        for axis, K in enumerate(kernels):
            K = K if forward else K.T
            W = torch.tensordot(K, W, dims=([0], [axis])).movedim(0, axis)
        return W

    step = torch.zeros(m.shape(), dtype=torch.float64)
    expect = torch.zeros(A, *m.shape(), dtype=torch.float64)
    for a in range(A):
        for p, names, _ in m.joint[a]:
            step += p * joint_kernel(x * probs[:, a].reshape(m.shape()), names, True)
            expect[a] += p * joint_kernel(V, names, False)
    close = {"rtol": 1e-12, "atol": 1e-15}
    assert torch.allclose(m.step(x.reshape(-1), probs), step.reshape(-1), **close)
    assert torch.allclose(m.expect(V), expect.reshape(A, -1), **close)
    names = ["comm"] * vehicles
    assert torch.allclose(m.push(x, names), joint_kernel(x, names, True), **close)
    assert torch.allclose(m.expected_next(V, names), joint_kernel(V, names, False), **close)
    if vehicles == 2:  # the axis-at-a-time reference is the Kronecker product
        K = torch.kron(torch.kron(m.P_rw, m.kernels[0].K["comm"]), m.kernels[1].K["comm"])
        assert torch.allclose(joint_kernel(x, names, True).reshape(-1), x.reshape(-1) @ K, **close)


@pytest.mark.parametrize("vehicles", [1, 2, 3])
def test_the_fleet_sums_are_those_of_its_tables(vehicles):
    """``FleetModel.sums`` (each vehicle's terms against the occupancy's marginal on its own state)
    equals ``expected_sums`` under the tables over the joint states, for the fleet and for each
    vehicle: a random occupancy with one joint action never taken, vehicles that differ, and an
    imperfect radar (false alarms and quiet radar time count)."""
    from irdrc.core.exact.mdp import expected_sums

    small = {"env.queue_capacity": 2, "env.false_alarm_prob": 0.1, "env.detection_prob": 0.8}
    per = tuple(
        Params.from_overrides({**small, "env.p1.speed": s, "reward.r4": r})
        for s, r in [(0.1, 5.0), (1.0, 50.0), (0.5, 20.0)][:vehicles]
    )
    m = FleetModel(FleetSpec(vehicles=vehicles, channels=1, share=0.3, per_vehicle=per))
    occ = torch.rand(m.num_actions, m.num_states, generator=torch.Generator().manual_seed(1))
    occ = occ.to(torch.float64)
    occ[0] = 0.0  # every vehicle in comm: never
    occ = occ / occ.sum()
    cases = [(m.sums(occ), m.fleet_tables())]
    cases += [(m.sums(occ, i), m.vehicle_tables(i)) for i in range(vehicles)]
    for got, tables in cases:
        want = expected_sums(occ, tables)
        assert set(got) == set(want)
        for key in want:
            assert got[key] == pytest.approx(want[key], rel=1e-12, abs=1e-15), key
        assert got["false_alarms"] > 0 and got["quiet_radar"] > 0
