"""The constrained problem on its Lagrangian dual (``irdrc.core.cmdp_dual``): the LP's optimum,
against the LP and a hand-solved case, step by step as in one go, and resumed mid-way."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from irdrc.core import chains, cmdp_dual
from irdrc.core.chains import dense_transitions
from irdrc.core.cmdp import (
    Constraint,
    InfeasibleTarget,
    build_constraints,
    objective_table,
    solve_lp,
    transitions,
)
from irdrc.core.cmdp_dual import DualPlanner, solve_dual
from irdrc.core.exact import build_model, stationary_metrics
from irdrc.core.params import Params

PERSISTENT = {"env.stay_good.channel": 0.95, "env.stay_bad.channel": 0.9}


@pytest.fixture(scope="module")
def models():
    return {
        "paper": build_model(Params()),
        "persistent": build_model(Params.from_overrides(PERSISTENT)),
    }


@pytest.mark.parametrize(
    ("name", "target"),
    [(n, t) for n in ("paper", "persistent") for t in (0.01, 0.05, 0.1)]
    + [("paper", 0.2), ("persistent", 0.3)],
)
def test_the_dual_reaches_the_lps_optimum_and_its_policy_attains_it(models, name, target):
    """The value is the LP's to 1e-7 below and 1e-6 above (relative: HiGHS's feasibility
    tolerance is 1e-9 on occupancies summing to 1; near the arrivals' cap of one packet a step,
    at 0.2 and 0.3, HiGHS ends 1.5e-7 below the dual, whose policy attains its value); the
    policy's exact long-run packets are that value and its miss detection is the target (it
    binds) to 1e-9. The last two cases end on the two ends' mixture: the walk reaches its
    breaking end still keeping the target (paper, 0.2), or cannot start (persistent, 0.3)."""
    model = models[name]
    obj, con = objective_table(model, "throughput"), build_constraints(model, target)
    lp = solve_lp(transitions(model), obj, con)
    dual = solve_dual(model, obj, con[0])
    assert lp.value * (1 - 1e-7) <= dual.value <= lp.value * (1 + 1e-6)
    metrics = stationary_metrics(model, dual.policy)
    assert metrics.throughput == pytest.approx(dual.value, rel=1e-9)
    assert metrics.miss_detection == pytest.approx(target, abs=1e-9)


def test_a_target_no_policy_meets_is_refused_as_the_lp_refuses_it():
    """With an imperfect radar (P_d = 0.9) radar everywhere misses a tenth of the events: a 5 %
    target is out of reach of both solvers."""
    model = build_model(Params.from_overrides({"env.detection_prob": 0.9}))
    obj, con = objective_table(model, "throughput"), build_constraints(model, 0.05)
    with pytest.raises(InfeasibleTarget):
        solve_lp(transitions(model), obj, con)
    with pytest.raises(InfeasibleTarget, match="no policy keeps the constraint"):
        solve_dual(model, obj, con[0])


def test_the_hand_solved_two_state_problem():
    """States A, B drawn afresh every step; comm sends a packet and misses the events (0.1 in A,
    0.5 in B). At m* = 0.5 the budget 0.15 = 0.05 + 0.25·π_B: comm everywhere in A and with
    probability 0.4 in B, throughput ½(1 + 0.4) = 0.7 (``tests/test_cmdp.py``'s LP case)."""
    P = np.full((2, 2, 2), 0.5)
    obj = torch.tensor([[1.0, 1.0], [0.0, 0.0]], dtype=torch.float64)
    event = torch.tensor([0.1, 0.5], dtype=torch.float64)
    missed = torch.stack([event, torch.zeros(2, dtype=torch.float64)])
    out = DualPlanner(P, obj, Constraint("miss", missed - 0.5 * event[None], 0.0)).solve()
    assert out.value == pytest.approx(0.7, abs=1e-12)
    assert out.policy[:, 0].tolist() == pytest.approx([1.0, 0.4], abs=1e-12)


def test_a_target_at_the_radars_own_floor_gives_a_policy_of_probabilities():
    """The two-state problem with a radar that misses 70 % of the events, at m* = 0.7: only radar
    everywhere keeps the target, and its C comes out 7e-18 over the bound in floating point. The
    plan is a policy all the same (probabilities in [0, 1] summing to 1), radar everywhere; with
    the mixing weight left unclamped (the mutation) one probability is −5e-16."""
    P = np.full((2, 2, 2), 0.5)
    obj = torch.tensor([[1.0, 1.0], [0.0, 0.0]], dtype=torch.float64)
    event = torch.tensor([0.1, 0.5], dtype=torch.float64)
    missed = torch.stack([event, event / (1 / 0.7)])
    out = DualPlanner(P, obj, Constraint("miss", missed - 0.7 * event[None], 0.0)).solve()
    assert (out.policy >= 0).all() and torch.allclose(
        out.policy.sum(1), torch.ones(2, dtype=torch.float64)
    )
    assert out.policy[:, 1].tolist() == pytest.approx([1.0, 1.0]) and out.value == pytest.approx(0)


def test_a_slack_target_gives_the_best_policy_of_the_objective(models):
    """At m* = 1 the constraint cannot bind: the best throughput of any policy, with the first
    policy iteration alone (the LP, a vertex to HiGHS's tolerance, is within 2e-7 of it)."""
    model = models["paper"]
    obj, con = objective_table(model, "throughput"), build_constraints(model, 1.0)
    planner = DualPlanner(dense_transitions(model), obj, con[0])
    out = planner.solve()
    assert planner.stage == 0 and planner.lo is None
    assert out.value == pytest.approx(solve_lp(transitions(model), obj).value, rel=1e-6)


def test_step_by_step_and_resumed_midway_it_ends_where_one_solve_ends(models):
    """``advance(1)`` until done gives the one-go result bit for bit, and a fresh planner loaded
    from a mid-way ``state_dict`` ends there too, with the evaluations left; started again from
    the saved policy alone (the mutation), it needs more."""
    model = models["persistent"]
    obj, con = objective_table(model, "throughput"), build_constraints(model, 0.05)
    P = dense_transitions(model)
    one_go = DualPlanner(P, obj, con[0])
    whole = one_go.solve()
    stepped, steps, saved, walking = DualPlanner(P, obj, con[0]), 0, None, None
    while (out := stepped.advance(1)) is None:
        steps += 1
        if stepped.stage == 2 and saved is None:
            saved = stepped.state_dict()
        if stepped.walk is not None and walking is None:
            walking = stepped.state_dict()
    assert torch.equal(out.policy, whole.policy) and out.value == whole.value
    assert saved is not None and walking is not None and steps > 3

    for state in (saved, walking):
        resumed = DualPlanner(P, obj, con[0])
        resumed.load_state_dict(state)
        assert torch.equal(resumed.solve().policy, whole.policy)
        assert resumed.evaluations == stepped.evaluations == one_go.evaluations
    broken = DualPlanner(P, obj, con[0])
    broken.load_state_dict({**saved, "lo": None, "hi": None, "stage": 0, "lam": 0.0})
    broken.solve()
    assert broken.evaluations > one_go.evaluations
    lost = DualPlanner(P, obj, con[0])  # mid-walk without the walk's own state
    lost.load_state_dict({k: v for k, v in walking.items() if k not in ("walk", "stride")})
    assert not torch.equal(lost.solve().policy, whole.policy)


def test_a_deep_queue_gets_a_policy_whose_own_chain_keeps_the_target():
    """The paper's model with a 40-packet queue (S = 1 312) at m* = 0.05. The two ends of λ*
    live apart: comm in the favourable states drains the queue, radar everywhere keeps it full.
    Their occupancies mixed at once (the mutation) balance on flows of 1e-25 between the two
    parts, and that policy's own chain misses 0.0500002 of the events. The walk's last two
    policies differ in one state, visited on 38 % of the steps: the policy randomises there alone,
    and its own exact throughput is the value (1e-9, relative: an LU's rounding), its miss
    detection the target (1e-9), and the value the LP's (1e-7, as above)."""
    model = build_model(Params.from_overrides({"env.queue_capacity": 40}))
    obj, con = objective_table(model, "throughput"), build_constraints(model, 0.05)
    dual = solve_dual(model, obj, con[0])
    randomised = ((dual.policy > 1e-9).sum(1) > 1).nonzero().flatten().tolist()
    assert len(randomised) == 1 and float(dual.occupancy[:, randomised].sum()) > 0.3
    metrics = stationary_metrics(model, dual.policy)
    assert metrics.throughput == pytest.approx(dual.value, rel=1e-9)
    assert metrics.miss_detection == pytest.approx(0.05, abs=1e-9)
    assert dual.value == pytest.approx(solve_lp(transitions(model), obj, con).value, rel=1e-7)


def test_the_search_takes_the_first_policy_that_keeps_the_constraint(models):
    """After the best policy at λ = 0 breaks the target, the search needs only a policy that keeps
    it: the one that keeps it best one step ahead (radar wherever an event can be missed) does on
    the paper's model, and one evaluation of it is all of stage 1 (policy iteration on the
    constraint from the breaking policy, the mutation, takes more)."""
    model = models["paper"]
    obj, con = objective_table(model, "throughput"), build_constraints(model, 0.05)

    def stage_one(planner: DualPlanner) -> int:
        stages = []
        while True:
            stages.append(planner.stage)
            if planner.step() is not None:
                return stages.count(1)

    assert stage_one(DualPlanner(dense_transitions(model), obj, con[0])) == 1
    slow = DualPlanner(dense_transitions(model), obj, con[0])
    while slow.stage == 0:
        slow.step()
    slow.policy = slow.lo[0].copy()  # stage 1 from the breaking policy
    assert stage_one(slow) > 1


def test_a_long_walk_takes_logarithmically_many_evaluations():
    """A walk of 256 states at λ* whose constraint breaks once 100 of them are switched (every
    policy's chain draws the next state uniformly; the constraint counts comm states). One state a
    step, it would take 101 evaluations; switching twice as many after each keeping policy and
    half as many after each breaking one, it takes at most 2·log₂ 256 + 2, and ends randomising
    in one state with the constraint binding."""
    S, broken_at = 256, 100
    P = np.full((2, S, S), 1.0 / S)
    coef = torch.stack([torch.ones(S), torch.zeros(S)]).to(torch.float64)
    con = Constraint("c", coef, (broken_at - 0.5) / S)
    planner = DualPlanner(P, coef.clone(), con)
    planner.stage, planner.toward = 3, np.zeros(S, dtype=np.int64)  # from radar toward comm
    out = planner.solve()
    assert planner.evaluations <= 2 * 8 + 2
    assert int(((out.policy > 1e-9).sum(1) > 1).sum()) == 1
    assert float((out.occupancy * coef).sum()) == pytest.approx(con.bound, abs=1e-12)


def test_policy_iteration_that_comes_back_to_a_policy_stops_at_once(models, monkeypatch):
    """Evaluations too coarse to rank the actions (made here to favour comm everywhere, then radar
    everywhere) send policy iteration round a cycle, which exact arithmetic never does: the planner
    stops with ``SolverFailed`` at the first return, not after ``MAX_EVALUATIONS``."""
    model = models["paper"]
    obj, con = objective_table(model, "throughput"), build_constraints(model, 0.05)
    planner = DualPlanner(dense_transitions(model), obj, con[0])
    flip = itertools.cycle([0, 1])

    def coarse(h: np.ndarray) -> np.ndarray:
        q = np.zeros((2, len(h)))
        q[next(flip)] = 1e3
        return q

    monkeypatch.setattr(planner, "_expect", coarse)
    with pytest.raises(cmdp_dual.SolverFailed, match="came back to a policy it had left"):
        planner.solve()
    assert planner.evaluations == 2


@pytest.mark.parametrize("name", ["paper", "persistent"])
def test_the_sparse_chain_plans_as_the_dense_one(models, name):
    """SuperLU on the sparse rows (``transitions``) against the dense LU: the same evaluations,
    the same policy and value to rounding (1e-12)."""
    model = models[name]
    obj, con = objective_table(model, "throughput"), build_constraints(model, 0.05)[0]
    dense, sparse = (
        DualPlanner(dense_transitions(model), obj, con),
        DualPlanner(transitions(model), obj, con),
    )
    a, b = dense.solve(), sparse.solve()
    assert sparse.rows is not None and dense.evaluations == sparse.evaluations
    assert b.value == pytest.approx(a.value, rel=1e-12)
    assert torch.allclose(a.policy, b.policy, atol=1e-12, rtol=0)


@pytest.mark.parametrize("chain", ["dense", "sparse"])
def test_the_states_never_visited_are_the_policys_transient_states(models, chain):
    """The states with no occupancy are those outside the recurrent class of the plan's own chain,
    found here by closing the set of states reached from its most visited one (the LU leaves
    rounding dust, 1e-18, on transient states: counted by it, some would seem visited), and the
    plan takes radar there."""
    model = models["paper"]
    obj, con = objective_table(model, "throughput"), build_constraints(model, 0.05)[0]
    P = dense_transitions(model) if chain == "dense" else transitions(model)
    result = DualPlanner(P, obj, con).solve()
    moves = np.einsum("sa,ast->st", result.policy.numpy(), dense_transitions(model)) > 0
    reached = np.zeros(model.num_states, dtype=bool)
    reached[int(result.occupancy.sum(0).argmax())] = True
    while not reached[moves[reached].any(0)].all():
        reached |= moves[reached].any(0)
    never = (result.occupancy.sum(0) == 0).numpy()
    assert never.sum() == 192 and np.array_equal(never, ~reached)
    assert (result.policy[torch.from_numpy(never), -1] == 1).all()


@pytest.mark.parametrize("sparse", [False, True])
def test_a_state_of_tiny_probability_that_the_chain_reaches_is_visited(sparse):
    """States 0 and 1 alternate; 0 goes to 2 once in 1e14 steps, 2 comes back; nothing enters 3.
    State 2's stationary probability (5e-15) is under the dust the LU leaves on transient states,
    yet the chain reaches it: it is visited, and 3 is not."""
    from scipy import sparse as sp

    P = np.zeros((4, 4))
    P[0, 1], P[0, 2], P[1:, 0] = 1 - 1e-14, 1e-14, 1.0
    chains = [sp.csr_matrix(P), sp.csr_matrix(P)] if sparse else np.stack([P, P])
    obj = torch.ones(2, 4, dtype=torch.float64)
    con = Constraint("c", torch.zeros(2, 4, dtype=torch.float64), 0.0)
    mass = DualPlanner(chains, obj, con).solve().occupancy.sum(0)
    assert 0 < mass[2] < cmdp_dual.DUST and mass[3] == 0
    assert mass[2] == pytest.approx(1e-14 / (2 + 1e-14), rel=1e-6)


def test_above_sparse_from_states_solve_dual_takes_the_sparse_chain(monkeypatch):
    """``chain`` gives the paper model's 352 states the dense chain; with ``SPARSE_FROM_STATES``
    lowered under them, ``solve_dual`` on its factored model plans on the sparse chain
    (``transitions`` called; the dense one refused) and reaches the LP's value (1e-7, as above)."""
    from irdrc.core.exact import build_factored

    model = build_factored(Params())
    assert isinstance(chains.chain(model), np.ndarray)
    obj, con = objective_table(model, "throughput"), build_constraints(model, 0.05)
    lp = solve_lp(transitions(model), obj, con)
    calls = []
    monkeypatch.setattr(chains, "SPARSE_FROM_STATES", 300)
    monkeypatch.setattr(chains, "transitions", lambda m: calls.append(m) or transitions(m))
    monkeypatch.setattr(chains, "dense_transitions", None)  # calling it fails
    assert solve_dual(model, obj, con[0]).value == pytest.approx(lp.value, rel=1e-7)
    assert calls == [model]


def test_a_singular_sparse_chain_stops_the_planner():
    """The two absorbing states of the dense case below, as sparse matrices: SuperLU's singular
    factor is said as the dense one is."""
    from scipy import sparse

    P = [sparse.identity(2, format="csr"), sparse.identity(2, format="csr")]
    obj = torch.ones(2, 2, dtype=torch.float64)
    con = Constraint("c", torch.zeros(2, 2, dtype=torch.float64), 0.0)
    with pytest.raises(cmdp_dual.SolverFailed, match="more than one recurrent class"):
        DualPlanner(P, obj, con).solve()


def test_a_factored_models_dense_chain_is_its_sparse_one():
    """``FactoredModel.dense`` writes the entries ``sparse`` holds, for both actions, on a model
    with bursty arrivals (several queue dynamics per action)."""
    from irdrc.core.exact import build_factored

    bursty = {"rates": [0.5, 3.0], "transition": [[0.95, 0.05], [0.15, 0.85]]}
    model = build_factored(Params.from_overrides({"env.arrival_rate": None, "env.bursty": bursty}))
    for a in range(model.num_actions):
        assert np.array_equal(model.dense(a), model.sparse(a).toarray())
    assert dense_transitions(model).shape == (2, model.num_states, model.num_states)


def test_a_singular_chain_stops_the_planner():
    """Two absorbing states (two recurrent classes under every policy): the evaluation's system is
    singular, and the planner says so rather than return a policy."""
    P = np.stack([np.eye(2), np.eye(2)])
    obj = torch.ones(2, 2, dtype=torch.float64)
    con = Constraint("c", torch.zeros(2, 2, dtype=torch.float64), 0.0)
    with pytest.raises(cmdp_dual.SolverFailed, match="more than one recurrent class"):
        DualPlanner(P, obj, con).solve()


def test_a_sparse_lu_past_memory_is_said_in_one_line(monkeypatch):
    """SuperLU's MemoryError (``env=large``: 100 800 states) becomes ``SolverFailed`` naming the
    chain's size and what makes it smaller (the recipes answer it in one line)."""
    import scipy.sparse.linalg

    def no_memory(_):
        raise MemoryError

    monkeypatch.setattr(scipy.sparse.linalg, "splu", no_memory)
    model = build_model(Params())
    obj, con = objective_table(model, "throughput"), build_constraints(model, 0.05)[0]
    with pytest.raises(cmdp_dual.SolverFailed, match="S = 352 states does not fit in memory"):
        DualPlanner(transitions(model), obj, con).solve()
