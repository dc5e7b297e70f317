"""The trade-off region over the radar share (MODEL.md § D, ``irdrc.core.share_cmdp``): its bounds
hold against policies the solver never saw, meet each other, reproduce what time-sharing is
worth at the paper's defaults, and reach the user through ``recipes/constrained.py``."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from irdrc import Params
from irdrc.core.cmdp import solve_cmdp
from irdrc.core.exact import build_model, stationary_distribution
from irdrc.core.exact.continuum import chain_at, policy_model, segments
from irdrc.core.share_cmdp import dual_bound, share_region

ROOT = Path(__file__).resolve().parents[1]
SMALL = {"env.actions": "continuous", "env.queue_capacity": 4}
"""S = 160: the LP over 21 levels in a few seconds."""


def shares(**overrides) -> Params:
    return Params.from_overrides({"env.actions": "continuous", **overrides})


@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"env.sensing": "linear"},
        # three segments of unequal width, an imperfect radar with false alarms
        {
            "env.packets_good": 3,
            "env.detection_prob": 0.9,
            "env.false_alarm_prob": 0.05,
            "reward.r5": 10,
        },
    ],
)
def test_the_interpolated_chain_is_the_policy_chain(overrides):
    """Every row of a ρ policy's chain lies in the span of the four functions on its segment:
    the weighted node rows equal the chain built directly, to rounding (1e-12 ≫ the ~1e-15 seen;
    a basis that leaves the span, or a share's ends rounded to float32, is off by 1e-8 or more)."""
    p = shares(**overrides)
    seg = segments(p)
    nodes = build_model(p, shares=seg.shares)
    rho = torch.rand(p.env.num_states, generator=torch.Generator().manual_seed(0)).double()
    rho[:20], rho[20:40], rho[40:60] = 0.0, 1.0, seg.shares[5]  # ends and a node
    a, b = chain_at(nodes, seg, rho), policy_model(p, rho)
    for name in ("P", "R", "missed", "false_alarms", "sent", "dropped", "capacity", "radar"):
        assert torch.allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-12), name


def _line(p: Params, rho: torch.Tensor, target: float, mu: float) -> float:
    """A ρ policy's exact Lagrangian gain: throughput − μ·(missed − target·events) per step."""
    m = policy_model(p, rho)
    x = stationary_distribution(m.P[0])
    return float(x @ m.sent[0]) - mu * float(x @ (m.missed[0] - target * m.event))


def test_the_dual_bound_holds_for_policies_it_never_saw_and_meets_the_feasible_side():
    """Weak duality, checked from outside: at the bound's multiplier no ρ policy — random ones,
    and the binary LP's modes — gains more than U(μ); the randomised policy meets the target and
    lies within the printed gap of the bound, above the LP over 21 levels (a subset of shares)."""
    p = Params.from_overrides(SMALL)
    region = share_region(p, 0.02)
    dual = region.dual
    g = torch.Generator().manual_seed(1)
    for _ in range(30):
        rho = torch.rand(p.env.num_states, generator=g).double()
        assert _line(p, rho, 0.02, dual.mu) <= dual.upper + 1e-12
    for rho in (torch.zeros(p.env.num_states), torch.ones(p.env.num_states)):
        assert _line(p, rho.double(), 0.02, dual.mu) <= dual.upper + 1e-12
    assert dual.policy.metrics.miss_detection <= 0.02 + 1e-9
    assert 0 <= region.gap <= 1e-5 * region.upper  # the grid's shortfall is ~1e-6 here
    assert region.levels_lp.value <= region.upper + 1e-9
    assert region.binary.value <= region.levels_lp.value + 1e-9  # 0 and 1 are levels
    assert region.lower == dual.value > region.binary.value * 2  # time-sharing pays here


def test_time_sharing_is_worth_what_the_docs_say_at_the_paper_defaults():
    """p^v_1 = 0.1, dwell sensing: at 1 % missed events sharing the frame sends 0.4037 packets per
    step against the binary modes' 0.0826 (×4.9); at 5 % every packet (0.99999) against 0.4132.
    Bounds to 1e-5 (the printed gap is below 1e-6 at these targets)."""
    p = shares()
    for target, sent, binary in ((0.01, 0.403660, 0.082638), (0.05, 0.999989, 0.413192)):
        dual = dual_bound(p, target)
        assert dual.value == pytest.approx(sent, abs=1e-5)
        assert dual.upper == pytest.approx(sent, abs=1e-5)
        lp = solve_cmdp(build_model(p, shares=(0.0, 1.0)), target)
        assert lp.value == pytest.approx(binary, abs=1e-5)


def test_with_linear_sensing_time_sharing_gains_nothing_under_a_target_either():
    """MODEL.md § D: sharing pays only where sensing has diminishing returns. With linear sensing
    the dual bound is the binary modes' LP (within 1e-5 relative: the LP stops 1e-7 below its
    target); with dwell sensing the same target gets ×4 as much (the test above)."""
    p = shares(**{"env.sensing": "linear"})
    dual = dual_bound(p, 0.02)
    binary = solve_cmdp(build_model(p, shares=(0.0, 1.0)), 0.02).value
    assert binary <= dual.upper + 1e-9
    assert dual.upper == pytest.approx(binary, rel=1e-5)


def test_a_target_no_share_reaches_is_refused():
    """An imperfect radar (P_d = 0.9) misses at least 10 % of events whatever the share."""
    from irdrc.core.cmdp import InfeasibleTarget

    p = shares(**{"env.detection_prob": 0.9, "env.false_alarm_prob": 0.05, "reward.r5": 10})
    with pytest.raises(InfeasibleTarget):
        dual_bound(p, 0.05)


def run(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "constrained.py"),
            *overrides,
            f"hydra.run.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )


@pytest.mark.e2e
def test_the_recipe_over_rho_prints_both_bounds_and_writes_the_shares(tmp_path):
    res = run(tmp_path, "env.actions=continuous", "env.queue_capacity=4", "target_miss=0.02")
    assert res.returncode == 0, res.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["lower_bound"] <= s["upper_bound"] and s["gap"] == pytest.approx(
        s["upper_bound"] - s["lower_bound"]
    )
    assert s["value"] == s["lower_bound"] > 2 * s["binary_value"]
    assert s["metrics"]["miss_detection"] <= 0.02 + 1e-9
    rows = list(csv.DictReader((tmp_path / "policy.csv").open()))
    assert list(rows[0]) == ["d", "c", "r", "w", "v", "m", "rho", "rho_alt", "p_alt"]
    assert len(rows) == 160
    assert sum(0 < float(r["p_alt"]) < 1 for r in rows) == s["randomised_states"]
    assert "upper bound (dual" in res.stdout and "gap:" in res.stdout
    assert "sharing each step's frame gets throughput" in res.stdout


def test_the_recipe_over_levels_is_the_lp_over_levels(tmp_path):
    res = run(tmp_path, "env.actions=levels", "env.queue_capacity=4", "target_miss=0.02")
    assert res.returncode == 0, res.stderr
    rows = list(csv.DictReader((tmp_path / "policy.csv").open()))
    assert list(rows[0])[6:] == ["action", "rho", "action_alt", "rho_alt", "p_alt"]
    assert {r["rho"] for r in rows} <= {"0.0", "0.25", "0.5", "0.75", "1.0"}
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["binary_value"] < s["value"] and s["metrics"]["miss_detection"] <= 0.02 + 1e-9


@pytest.mark.parametrize(
    ("overrides", "says"),
    [
        (("env.actions=continuous", "learner=dqn_lagrangian"), "learns whole-step modes"),
        (("env.actions=levels", "frontier=true"), "env.actions=binary or continuous"),
        (("env.actions=continuous", "max_drop=0.1"), "env.actions=levels takes max_drop"),
        (("env.actions=continuous", "env=large"), "radar shares is built on the dense"),
    ],
)
def test_what_the_region_cannot_do_is_one_line(tmp_path, overrides, says):
    res = run(tmp_path / "x", *overrides)
    assert res.returncode == 2 and says in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.e2e
def test_the_frontier_over_rho_writes_time_sharing_beside_the_binary_modes(tmp_path):
    res = run(
        tmp_path,
        "env.actions=continuous",
        "env.queue_capacity=4",
        "frontier=true",
        "frontier_grid.p1_speed=[0.1]",
        "frontier_grid.points=3",
        "frontier_grid.r4.lo=40",
        "frontier_grid.r4.hi=50",
        "frontier_grid.r4.step=10",
        "frontier_grid.targets=[0.02]",
    )
    assert res.returncode == 0, res.stderr
    rows = list(csv.DictReader((tmp_path / "frontier.csv").open()))
    assert {r["route"] for r in rows} == {"lp", "r4", "share"}
    share = [r for r in rows if r["route"] == "share"]
    lp = {r["target_miss"]: float(r["throughput"]) for r in rows if r["route"] == "lp"}
    assert len(share) == len(lp) == 4  # 3 points and the table's target
    for r in share:  # time-sharing is never below the binary modes, never above its bound
        assert lp[r["target_miss"]] - 1e-9 <= float(r["throughput"]) <= float(r["upper"]) + 1e-12
    table = (tmp_path / "tradeoff_region.md").read_text()
    assert "dual bound" in table and "LP over 21 levels" in table
    assert "time-sharing (MODEL.md § D" in res.stdout


def test_a_multilevel_scenario_keeps_its_factors_across_action_spaces():
    """DQN over levels reads the optimum over ρ of the same scenario, and the region reads the
    binary modes', by replacing ``env.actions``: a scenario with three-level factors keeps them
    (it was refused: its built factors were read back as a config)."""
    import dataclasses

    from irdrc.recipes.constrained.region import binary_params

    speed = {
        "levels": ["low", "medium", "high"],
        "transition": [[0.8, 0.2, 0.0], [0.1, 0.8, 0.1], [0.0, 0.25, 0.75]],
        "event": [0.003, 0.01, 0.1],
    }
    p = Params.from_overrides({"env.actions": "levels", "env.factors": {"speed": speed}})
    q = dataclasses.replace(p, env=dataclasses.replace(p.env, actions="continuous"))
    assert q.env.factors == p.env.factors and q.env.num_states == p.env.num_states == 528
    assert binary_params(q).env.factors == p.env.factors


def test_a_reaction_that_saturates_before_full_radar_is_solved():
    """At κ ≥ 49 the dwell reaction reaches 1 in float64 before ρ = 1, so the last segment's
    reaction is flat; its rescaled reaction divided by zero and torch's least squares failed
    (an internal assert). Past it the optimum over ρ goes on from where it was at κ = 48: no
    lower (sensing only improves), with a step bound that grows as smoothly as below it (∝ κ²,
    from the first segment's curvature), above the G-level and binary optima."""
    from irdrc.core.exact import build_model, stationary_metrics, value_iteration
    from irdrc.core.exact.continuum import ContinuumScorer

    def over_rho(gain):
        params = Params.from_overrides({"env.actions": "continuous", "env.dwell_gain": gain})
        scorer = ContinuumScorer(params)
        return scorer.optimal_metrics.avg_reward, scorer

    def optimum(overrides):
        model = build_model(Params.from_overrides(overrides))
        return stationary_metrics(model, value_iteration(model).policy).avg_reward

    below, at48 = over_rho(48.0)
    for gain in (50.0, 100.0):
        value, scorer = over_rho(gain)
        assert value >= below - 1e-9
        bound = scorer.optimal.step_bound
        assert 0.0 < bound < 1.2 * at48.optimal.step_bound * (gain / 48.0) ** 2
        levels = optimum({"env.actions": "levels", "env.levels": 3, "env.dwell_gain": gain})
        assert value >= max(levels, optimum({})) - 1e-9
