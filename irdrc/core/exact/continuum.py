"""The exact optimum over the radar share ρ ∈ [0, 1] (MODEL.md § D, ``env.actions=continuous``),
and the exact metrics of any ρ policy.

Between two consecutive ``breakpoints`` every state's Q(s, ρ) lies in the span of
{1, ρ, u(ρ), ρ·u(ρ)}: the queue's transition is linear in ρ there (the capacity's random
rounding), the factors' is linear in the reaction u(ρ), the reward linear in both. So four values
of Q on a segment give it everywhere on that segment: the solver computes Q exactly at four nodes
per segment (one dense model whose actions are the nodes), interpolates it exactly in that span,
and maximises it over a fine grid of each segment. The grid's error is bounded from a bound on
|∂²Q/∂ρ²| (``ContinuumSolution.step_bound``), and policy iteration on the resulting deterministic ρ
policies ends, in a few iterations, at a policy within ``value_bound`` of the optimum's values.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import Any

import torch

from irdrc.core.exact.dense import DenseModel, _queue_tables, build_model
from irdrc.core.exact.solve import check_gamma, value_iteration
from irdrc.core.params import Params
from irdrc.core.share import breakpoints, reaction, reaction_slope_bound, share_tables

NODES = (0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)
"""Where on each segment (as a fraction of it) Q is computed exactly."""

GRID = 4097
"""Points of each segment's grid (ends included) over which Q is maximised."""


@dataclass(frozen=True)
class Segments:
    """The segments of [0, 1] between breakpoints, and the interpolation on them.

    Attributes:
        shares: [N] the node shares (each segment's four, ends shared).
        nodes: [K, 4] indices into ``shares`` of each segment's nodes.
        lo, hi: [K] each segment's ends.
        grid: [K, GRID] the shares of each segment's grid.
        weights: [K, GRID, 4] Q(grid) = weights @ Q(nodes), exact on the span.
    """

    shares: torch.Tensor
    nodes: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    grid: torch.Tensor
    weights: torch.Tensor


def _basis(t: torch.Tensor, ut: torch.Tensor) -> torch.Tensor:
    """[…, 4]: 1, t, ũ, t·ũ (t and ũ the share and the reaction, each rescaled to the segment)."""
    return torch.stack([torch.ones_like(t), t, ut, t * ut], -1)


def segments(params: Params, grid: int = GRID) -> Segments:
    """The segments of ``params`` (see ``Segments``)."""
    env = params.env
    ends = breakpoints(params)
    shares: list[float] = [0.0]
    nodes, los, his, grids, weights = [], [], [], [], []
    frac = torch.tensor(NODES, dtype=torch.float64)
    tg = torch.linspace(0.0, 1.0, grid, dtype=torch.float64)
    for lo, hi in itertools.pairwise(ends):
        idx = [len(shares) - 1]
        for x in NODES[1:]:
            shares.append(lo + x * (hi - lo))
            idx.append(len(shares) - 1)
        ua, ub = (float(reaction(torch.tensor(x), env.sensing, env.dwell_gain)) for x in (lo, hi))

        def rescaled(t: torch.Tensor, lo=lo, hi=hi, ua=ua, ub=ub) -> torch.Tensor:
            u = reaction(lo + t * (hi - lo), env.sensing, env.dwell_gain)
            return (u - ua) / (ub - ua)

        B = _basis(frac, rescaled(frac))  # [4 nodes, 4 functions]
        weights.append(_basis(tg, rescaled(tg)) @ torch.linalg.pinv(B, rtol=1e-12))
        nodes.append(idx)
        los.append(lo)
        his.append(hi)
        grids.append(lo + tg * (hi - lo))
    return Segments(
        shares=torch.tensor(shares, dtype=torch.float64),
        nodes=torch.tensor(nodes),
        lo=torch.tensor(los, dtype=torch.float64),
        hi=torch.tensor(his, dtype=torch.float64),
        grid=torch.stack(grids),
        weights=torch.stack(weights),
    )


def policy_model(params: Params, rho: torch.Tensor) -> DenseModel:
    """The exact chain of the deterministic ρ policy ``rho`` [S] as a one-action ``DenseModel``:
    its stationary and episodic metrics are those of the policy (``stationary_metrics(m, 0)``)."""
    rho = torch.as_tensor(rho, dtype=torch.float64)
    S = params.env.num_states
    if rho.shape != (S,) or bool(((rho < 0) | (rho > 1)).any()):
        raise ValueError(f"a ρ policy is [{S}] radar shares in [0, 1]; got {tuple(rho.shape)}")
    st = share_tables(params, rho)  # one "action" per state: [S, F, …]
    t = st.base
    nf, D = t.num_configs, params.env.queue_capacity
    s = torch.arange(S)
    d, f = s // nf, s % nf
    k, p = st.k[s, f], st.p[s, f]
    pairs: dict[tuple[int, float], int] = {}
    lo = torch.tensor(
        [
            pairs.setdefault((int(a), float(t.rate[g])), len(pairs))
            for a, g in zip(k, f, strict=True)
        ]
    )
    hi = torch.tensor(
        [
            pairs.setdefault((int(a) + 1, float(t.rate[g])), len(pairs))
            for a, g in zip(k, f, strict=True)
        ]
    )
    q_next, q_sent, q_drop = _queue_tables(D, pairs)

    def queue(table: torch.Tensor) -> torch.Tensor:
        pp = p.reshape(-1, *([1] * (table.ndim - 2)))
        return (1.0 - pp) * table[lo, d] + pp * table[hi, d]

    P = (queue(q_next)[:, :, None] * st.F[s, f][:, None, :]).reshape(1, S, S)
    return DenseModel(
        params=params,
        P=P,
        R=st.R[s, f][None],
        event=t.event[f],
        missed=st.missed[s, f][None],
        false_alarms=st.false_alarm[s, f][None],
        sent=queue(q_sent)[None],
        dropped=queue(q_drop)[None],
        capacity=st.nu[s, f][None],
        queue=d.to(torch.float64),
        radar=rho[None],
    )


@dataclass(frozen=True)
class ContinuumSolution:
    """The optimum over ρ ∈ [0, 1].

    Attributes:
        rho: [S] the optimal radar share of each state.
        values: [S] its discounted values.
        iterations: policy-iteration steps.
        step_bound: how far each state's maximisation over the grid may be below the maximum
            over the continuum (h²/8 · sup |∂²Q/∂ρ²|, the largest over states and segments).
        value_bound: how far ``values`` may be below the continuum optimum's:
            step_bound / (1 − γ).
        model: the policy's exact chain (``policy_model``).
    """

    rho: torch.Tensor
    values: torch.Tensor
    iterations: int
    step_bound: float
    value_bound: float
    model: DenseModel


def solve_continuum(
    params: Params, gamma: float = 0.99, grid: int = GRID, max_iter: int = 100
) -> ContinuumSolution:
    """The optimal deterministic ρ policy of ``params`` (see the module docstring): policy
    iteration from the best node policy, each improvement the exact Q maximised on every segment's
    grid; a state's share changes only when that gains more than 1e-12 (no cycling)."""
    check_gamma(gamma)
    seg = segments(params, grid)
    nodes = build_model(params, shares=seg.shares)
    start = value_iteration(nodes, gamma=gamma, tol=1e-9)
    rho = seg.shares[start.policy]
    S = nodes.num_states
    eye = torch.eye(S, dtype=torch.float64)
    it = 0
    while True:
        it += 1
        if it > max_iter:
            raise RuntimeError(f"policy iteration over ρ did not settle in {max_iter} steps")
        pm = policy_model(params, rho)
        V = torch.linalg.solve(eye - gamma * pm.P[0], pm.R[0])
        Q = nodes.q_values(V, gamma).T  # [S, N]
        Qg = torch.einsum("skj,kgj->skg", Q[:, seg.nodes], seg.weights)  # [S, K, GRID]
        best, at = Qg.reshape(S, -1).max(-1)
        better = best > V + 1e-12 * V.abs().clamp(min=1.0)
        if not bool(better.any()):
            break
        rho = torch.where(better, seg.grid.reshape(-1)[at], rho)
    step = _step_bound(params, seg, Q)
    return ContinuumSolution(
        rho=rho,
        values=V,
        iterations=it,
        step_bound=step,
        value_bound=step / (1.0 - gamma),
        model=pm,
    )


def _step_bound(params: Params, seg: Segments, Q: torch.Tensor) -> float:
    """h²/8 · sup |∂²Q/∂ρ²| over states and segments, from Q's coefficients in the basis
    {1, t, ũ, t·ũ} (t = (ρ − lo)/Δ, ũ = (u − u_lo)/δ): ∂²/∂ρ² = c₂ũ″ + c₃(2t′ũ′ + tũ″)."""
    env = params.env
    frac = torch.tensor(NODES, dtype=torch.float64)
    out = 0.0
    for j in range(seg.nodes.shape[0]):
        lo, hi = float(seg.lo[j]), float(seg.hi[j])
        width = hi - lo
        u = reaction(torch.tensor([lo, hi]), env.sensing, env.dwell_gain)
        du = float(u[1] - u[0])
        u_t = (reaction(lo + frac * width, env.sensing, env.dwell_gain) - u[0]) / du
        coef = Q[:, seg.nodes[j]] @ torch.linalg.pinv(_basis(frac, u_t), rtol=1e-12).T  # [S, 4]
        d1, d2 = reaction_slope_bound(lo, env.sensing, env.dwell_gain)
        curv = coef[:, 2].abs() * d2 / du + coef[:, 3].abs() * (2 * d1 / (width * du) + d2 / du)
        h = width / (seg.grid.shape[1] - 1)
        out = max(out, float(curv.max()) * h * h / 8)
    return out


class ContinuumScorer:
    """The ``Scorer`` of ρ policies (MODEL.md § D): the optimum over the continuum, and the exact
    long-run metrics of any table of radar shares [S] against it (cached).

    Attributes:
        params: the scenario.
        optimal: ``solve_continuum``'s solution (``optimal.rho`` its policy).
        optimal_metrics: its exact long-run metrics.
    """

    def __init__(self, params: Params, gamma: float = 0.99) -> None:
        from irdrc.core.exact.solve import stationary_metrics

        self.params = params
        self.optimal = solve_continuum(params, gamma=gamma)
        self._still = torch.zeros(params.env.num_states, dtype=torch.int64)
        self.optimal_metrics = stationary_metrics(self.optimal.model, self._still)
        self._cache: dict[bytes, Any] = {}

    def metrics(self, rho: torch.Tensor) -> Any:
        """Exact stationary ``Metrics`` of the deterministic ρ policy ``rho`` [S]."""
        from irdrc.core.exact.solve import stationary_metrics

        t = torch.as_tensor(rho, dtype=torch.float64).cpu().clamp(0.0, 1.0)
        key = t.numpy().tobytes()
        if key not in self._cache:
            self._cache[key] = stationary_metrics(policy_model(self.params, t), self._still)
        return self._cache[key]

    def ratio(self, rho: torch.Tensor) -> float:
        """Average reward of ``rho`` over the continuum optimum's (both long-run)."""
        return self.metrics(rho).avg_reward / self.optimal_metrics.avg_reward


def continuum_optimum(params: Params, gamma: float = 0.99) -> float | None:
    """With ``env.actions=levels``: the long-run average reward of the optimum over ρ ∈ [0, 1] of
    the same scenario, which G levels approach (MODEL.md § D); else None."""
    if params.env.actions != "levels":
        return None
    shares = dataclasses.replace(params, env=dataclasses.replace(params.env, actions="continuous"))
    return ContinuumScorer(shares, gamma).optimal_metrics.avg_reward
