"""The constrained problem of MODEL.md § A over the radar share ρ ∈ [0, 1] (§ D, "the trade-off
region"): the most data subject to a miss-detection target when each step may share its frame.

Two exact bounds enclose the optimum over every policy (randomised, history-dependent):

- **above**, weak duality. For a multiplier μ ≥ 0 the Lagrangian reward
  J(s, ρ) − μ·(missed(s, ρ) − m*·event(s)) has, on each segment between the queue's breakpoints,
  the form of § D's rewards (span {1, ρ, u(ρ)}), so its Bellman maximisation over ρ is exact on the
  continuum operator (``irdrc.core.exact.continuum``). For *any* bias h,
  U(μ) = max_s [max_ρ (J − μ·(missed − m*·event) + P h)(s, ρ) − h(s)] bounds every policy's
  long-run Lagrangian gain (sum the inequality over n steps, divide by n), and every feasible
  policy's J is at most that gain: min_μ U(μ) bounds the constrained optimum. h comes from
  average-reward policy iteration, whose U meets its policy's own gain when it settles; the
  grid's shortfall (``continuum.step_bound``) is added.
- **below**, feasible policies: the LP of § A over G equally spaced shares (``levels``), and a
  randomised ρ policy that mixes the two deterministic policies optimal on either side of the best
  multiplier so that the target binds — the continuum's counterpart of the LP's randomisation in
  a few states. When the multiplier search has closed, its value equals the dual bound up to
  the grid's shortfall.

The multiplier is found by cutting planes: each policy found is a line J − μ·slack under the
(convex, piecewise-linear) dual function; the next μ is where the best line of each slope sign
cross, until the dual function there adds nothing to the lines.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from irdrc.core.cmdp import CMDPSolution, InfeasibleTarget, objective_table, solve_cmdp
from irdrc.core.exact import DenseModel, build_model, stationary_distribution, stationary_metrics
from irdrc.core.exact.continuum import chain_at, maximise, policy_model, segments, step_bound
from irdrc.core.metrics import Metrics
from irdrc.core.params import Params

LEVELS = 21
"""Shares of the feasible LP (MODEL.md § D: G ≥ 21)."""

MU_MAX = 1e9
"""No policy is feasible when even this multiplier's is not (the target is below what any reaches)."""

CUTS = 60
"""At most this many cutting-plane steps (each one exact policy-iteration solve)."""

TOL = 1e-10
"""A cut that adds less than this (relative) to the lines closes the search,"""

GAP = 1e-6
"""… as does a dual bound within this (relative) of the feasible mixture's value."""


@dataclass(frozen=True)
class Lagrangian:
    """The Lagrangian problem at one multiplier, solved by average-reward policy iteration.

    Attributes:
        mu: the multiplier.
        upper: U(μ), an upper bound on every policy's Lagrangian gain at μ.
        rho: [S] the deterministic policy found.
        objective, slack: its long-run objective and missed − target·events per step (exact).
    """

    mu: float
    upper: float
    rho: torch.Tensor
    objective: float
    slack: float

    def gain(self, mu: float) -> float:
        """The policy's Lagrangian gain at multiplier ``mu``: its line."""
        return self.objective - mu * self.slack


@dataclass(frozen=True)
class SharePolicy:
    """A stationary ρ policy that uses the share ``rho`` in each state, or ``rho_alt`` there with
    probability ``p_alt`` (0 where it is deterministic).

    Attributes:
        rho, rho_alt, p_alt: [S] each.
        metrics: its exact long-run metrics.
    """

    rho: torch.Tensor
    rho_alt: torch.Tensor
    p_alt: torch.Tensor
    metrics: Metrics

    @property
    def randomised(self) -> list[int]:
        """States where it uses both shares."""
        both = (self.p_alt > 0) & (self.p_alt < 1) & (self.rho != self.rho_alt)
        return both.nonzero().flatten().tolist()

    @classmethod
    def from_probs(cls, shares: Any, probs: torch.Tensor, metrics: Metrics) -> SharePolicy:
        """The policy of an LP over the actions' ``shares`` ([S, A] ``probs``; § A's LP with one
        constraint randomises between two actions at most): the likelier share and the other.

        Raises:
            ValueError: a state that uses three shares or more.
        """
        shares = torch.as_tensor(shares, dtype=torch.float64)
        top = probs.topk(min(3, probs.shape[1]), -1)
        if probs.shape[1] > 2 and bool((top.values[:, 2] > 1e-9).any()):
            raise ValueError("the policy uses three shares or more in a state")
        alt = top.values[:, 1] > 0
        return cls(
            rho=shares[top.indices[:, 0]],
            rho_alt=torch.where(alt, shares[top.indices[:, 1]], shares[top.indices[:, 0]]),
            p_alt=torch.where(alt, top.values[:, 1], torch.zeros_like(top.values[:, 1])),
            metrics=metrics,
        )


@dataclass(frozen=True)
class DualBound:
    """The dual side at one target: an upper bound on the constrained optimum over ρ, and the
    feasible randomised ρ policy of the best multiplier.

    Attributes:
        target_miss, objective: the problem (``irdrc.core.cmdp``).
        upper: min over the multipliers tried of U(μ), at ``mu``.
        policy: the feasible ρ policy (``SharePolicy``).
        multipliers: how many μ the search solved.
    """

    target_miss: float
    objective: str
    upper: float
    mu: float
    policy: SharePolicy
    multipliers: int

    @property
    def value(self) -> float:
        """The feasible policy's ``objective``."""
        return getattr(self.policy.metrics, self.objective)

    @property
    def gap(self) -> float:
        """``upper`` − ``value``."""
        return self.upper - self.value


@dataclass(frozen=True)
class ShareRegion:
    """The constrained optimum over ρ ∈ [0, 1] at one target, bounded on both sides, beside § A's
    optimum over the binary modes.

    Attributes:
        dual: the upper bound and the randomised ρ policy (``DualBound``).
        levels: G, the shares of ``levels_lp``.
        levels_lp: § A's LP over G equally spaced shares (randomised, feasible).
        binary: § A's LP over the binary modes (comm or radar a whole step).
    """

    dual: DualBound
    levels: int
    levels_lp: CMDPSolution
    binary: CMDPSolution

    @property
    def upper(self) -> float:
        """The dual bound."""
        return self.dual.upper

    @property
    def lower(self) -> float:
        """The best feasible value (the ρ policy's or the levels LP's)."""
        return max(self.levels_lp.value, self.dual.value)

    @property
    def gap(self) -> float:
        """``upper`` − ``lower``: how far the true optimum may be from either."""
        return self.upper - self.lower


def gain_bias(P: torch.Tensor, r: torch.Tensor) -> tuple[float, torch.Tensor]:
    """(g, h) with (I − P) h + g = r and h[0] = 0: a unichain policy's long-run gain and bias.
    A multichain one has no such pair: then a least-squares h (any h keeps ``U`` a bound)."""
    S = P.shape[0]
    M = torch.eye(S, dtype=torch.float64) - P
    M[:, 0] = 1.0  # h[0] = 0: its column carries g instead
    try:
        x = torch.linalg.solve(M, r)
    except RuntimeError:
        x = torch.linalg.lstsq(M, r[:, None], driver="gelsd").solution[:, 0]
    h = x.clone()
    h[0] = 0.0
    return float(x[0]), h


class RegionSolver:
    """The Lagrangian over ρ for one scenario, objective and target (see the module docstring),
    with the continuum's segments and node model built once."""

    def __init__(self, params: Params, objective: str, target_miss: float) -> None:
        self.params, self.objective, self.target = params, objective, float(target_miss)
        self.seg = segments(params)
        self.nodes = build_model(params, shares=self.seg.shares)
        self.solved = 0

    def _reward(self, model: Any, mu: float) -> torch.Tensor:
        cost = model.missed - self.target * model.event[None]
        return objective_table(model, self.objective) - mu * cost

    def solve(self, mu: float, rho: torch.Tensor, max_iter: int = 100) -> Lagrangian:
        """Average-reward policy iteration at ``mu`` from the ρ policy ``rho``."""
        self.solved += 1
        r_nodes = self._reward(self.nodes, mu)
        for _ in range(max_iter):
            pm = chain_at(self.nodes, self.seg, rho)
            r_pol = self._reward(pm, mu)[0]
            g, h = gain_bias(pm.P[0], r_pol)
            Q = (r_nodes + self.nodes.expect(h)).T  # [S, N]
            best, share = maximise(self.seg, Q)
            upper = float((best - h).max()) + step_bound(self.params, self.seg, Q)
            now = r_pol + pm.P[0] @ h
            better = best > now + 1e-12 * now.abs().clamp(min=1.0)
            if upper - g <= 1e-10 * max(1.0, abs(g)) or not bool(better.any()):
                break
            rho = torch.where(better, share, rho)
        x = stationary_distribution(pm.P[0])
        return Lagrangian(
            mu=mu,
            upper=upper,
            rho=rho,
            objective=float(x @ objective_table(pm, self.objective)[0]),
            slack=float(x @ (pm.missed[0] - self.target * pm.event)),
        )


def share_policy(params: Params, lo: Lagrangian, hi: Lagrangian) -> SharePolicy:
    """The stationary policy whose occupancy is θ·(lo's) + (1 − θ)·(hi's), θ chosen so that the
    slack is 0 (``hi`` feasible, ``lo`` not; θ = 0 when ``lo`` is ``hi``): in each state the
    share of ``hi``, or of ``lo`` with probability θx_lo(s) / (θx_lo(s) + (1 − θ)x_hi(s))."""
    theta = 0.0 if lo is hi or lo.slack <= 0 else -hi.slack / (lo.slack - hi.slack)
    models = [policy_model(params, hi.rho), policy_model(params, lo.rho)]
    x_hi, x_lo = (stationary_distribution(m.P[0]) for m in models)
    num, den = theta * x_lo, theta * x_lo + (1.0 - theta) * x_hi
    p_alt = torch.where(den > 0, num / den.clamp(min=1e-300), torch.zeros_like(den))
    p_alt = torch.where(lo.rho == hi.rho, torch.zeros_like(p_alt), p_alt)
    both = DenseModel(
        **{
            name: torch.cat([getattr(m, name) for m in models])
            for name in ("P", "R", "missed", "false_alarms", "sent", "dropped", "capacity", "radar")
        },
        params=params,
        event=models[0].event,
        queue=models[0].queue,
    )
    probs = torch.stack([1.0 - p_alt, p_alt], -1)
    return SharePolicy(
        rho=hi.rho, rho_alt=lo.rho, p_alt=p_alt, metrics=stationary_metrics(both, probs)
    )


def dual_bound(
    params: Params,
    target_miss: float,
    objective: str = "throughput",
    start: torch.Tensor | None = None,
    mu: float = 1.0,
) -> DualBound:
    """The dual side of the constrained problem over ρ at ``target_miss`` (``DualBound``): μ = 0,
    then a bracket from ``mu`` (× or ÷ 4 until the policies on either side differ in
    feasibility), then cutting planes between its infeasible and its feasible policy (see the
    module docstring); ``start``, ``mu``: a ρ policy and a multiplier to begin from (a
    neighbouring target's).

    Raises:
        InfeasibleTarget: no multiplier up to ``MU_MAX`` gives a policy within the target.
    """
    solver = RegionSolver(params, objective, target_miss)
    S = params.env.num_states
    rho = torch.ones(S, dtype=torch.float64) if start is None else start.clone()
    lo = hi = solver.solve(0.0, rho)
    tried = [lo]
    if lo.slack > 0:
        at = solver.solve(max(mu, 1e-9), lo.rho)
        tried.append(at)
        while at.slack > 0:  # up until feasible
            if at.mu > MU_MAX:
                raise InfeasibleTarget(
                    f"target_miss={target_miss:g}: no ρ policy found within it up to μ = {MU_MAX:g}"
                )
            lo, at = at, solver.solve(at.mu * 4.0, at.rho)
            tried.append(at)
        hi = at
        while lo.mu == 0.0 and hi.mu > 1e-9:  # down until infeasible
            at = solver.solve(hi.mu / 4.0, hi.rho)
            tried.append(at)
            if at.slack > 0:
                lo = at
                break
            hi = at
        for _ in range(CUTS):
            top = min(t.upper for t in tried)
            if top - mixture_value(lo, hi) <= GAP * max(1.0, abs(top)):
                break
            mu = (lo.objective - hi.objective) / (lo.slack - hi.slack)
            at = solver.solve(mu, hi.rho)
            tried.append(at)
            line = lo.gain(mu)
            if at.gain(mu) <= line + TOL * max(1.0, abs(line)):
                break
            if at.slack > 0:
                lo = at
            else:
                hi = at
    bound = min(tried, key=lambda t: t.upper)
    return DualBound(
        target_miss=float(target_miss),
        objective=objective,
        upper=bound.upper,
        mu=bound.mu,
        policy=share_policy(params, lo, hi),
        multipliers=solver.solved,
    )


def mixture_value(lo: Lagrangian, hi: Lagrangian) -> float:
    """The objective of ``share_policy(lo, hi)``: the mixture whose slack is 0."""
    if lo is hi or lo.slack <= 0:
        return hi.objective
    theta = -hi.slack / (lo.slack - hi.slack)
    return theta * lo.objective + (1.0 - theta) * hi.objective


def share_region(
    params: Params,
    target_miss: float,
    objective: str = "throughput",
    levels: int = LEVELS,
    start: torch.Tensor | None = None,
) -> ShareRegion:
    """The constrained optimum over ρ at ``target_miss``: the dual bound above, the LP over
    ``levels`` shares and the randomised ρ policy below, and § A's binary LP beside them.

    Raises:
        InfeasibleTarget: no policy meets the target (the LPs' own message).
        ValueError: a bad value (named).
    """
    binary = solve_cmdp(build_model(params, shares=(0.0, 1.0)), target_miss, objective)
    grid = torch.linspace(0.0, 1.0, levels, dtype=torch.float64)
    levels_lp = solve_cmdp(build_model(params, shares=grid), target_miss, objective)
    return ShareRegion(
        dual=dual_bound(params, target_miss, objective, start),
        levels=levels,
        levels_lp=levels_lp,
        binary=binary,
    )
