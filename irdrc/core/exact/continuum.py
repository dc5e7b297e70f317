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
        inverse: [K, 4, 4] the basis at the nodes, inverted: weights = basis @ inverse.
        scale: [K, 5] each segment's constants of its basis (``_basis``): c, a₀, a₁, a₂, c_w.
        sensing, gain: the sensing curve the basis's ũ follows.
    """

    shares: torch.Tensor
    nodes: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    grid: torch.Tensor
    weights: torch.Tensor
    inverse: torch.Tensor
    scale: torch.Tensor
    sensing: str
    gain: float

    def at(self, rho: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """([S] the segment of each share, [S, 4] its weights on that segment's nodes): any
        function in the span takes the value weights @ (its values at the nodes) at ``rho``."""
        rho = torch.as_tensor(rho, dtype=torch.float64)
        k = torch.searchsorted(self.hi, rho).clamp(max=self.hi.shape[0] - 1)
        lo, hi = self.lo[k], self.hi[k]
        u = reaction(torch.stack([rho, lo, hi]), self.sensing, self.gain)
        t = (rho - lo) / (hi - lo)
        du = u[2] - u[1]
        flat = du < FLAT_REACTION
        ut = torch.where(flat, t, (u[0] - u[1]) / torch.where(flat, 1.0, du))
        return k, torch.einsum("sj,sjk->sk", _basis(t, ut, self.scale[k].T), self.inverse[k])


FLAT_REACTION = 1e-12
"""A segment over which the sensing reaction u rises by less than this is flat: its ũ is the share
t itself. At a large κ the reaction reaches 1 in float64 before ρ = 1 (κ = 50: from ρ = 0.75 on),
and u is then a constant the span {1, ρ} already holds."""


def _basis(t: torch.Tensor, ut: torch.Tensor, k: Any) -> torch.Tensor:
    """[…, 4]: a basis of the span of {1, ρ, u, ρu} on one segment that stays well conditioned
    where the segment is narrow (there ũ ≈ t and tũ ≈ t², so the plain basis {1, t, ũ, tũ} is
    nearly dependent): 1, t, v = (ũ − t)/c and w = (tũ − a₀ − a₁t − a₂v)/c_w, the part of tũ
    outside {1, t, v}, each of order 1. t and ũ are the share and the reaction rescaled to the
    segment; ``k`` = (c, a₀, a₁, a₂, c_w), ``segments`` fits them."""
    c, a0, a1, a2, cw = k
    v = (ut - t) / c
    w = (t * ut - a0 - a1 * t - a2 * v) / cw
    return torch.stack([torch.ones_like(t), t, v, w], -1)


def _fit_basis(tg: torch.Tensor, ug: torch.Tensor) -> tuple[float, ...]:
    """``_basis``'s constants on a segment from t and ũ on its grid."""
    bend = float((ug - tg).abs().max())
    c = bend if bend > 1e-12 else 1.0  # linear sensing: ũ = t, v ≡ 0
    v = (ug - tg) / c
    A = torch.stack([torch.ones_like(tg), tg, v], -1)
    a = torch.linalg.lstsq(A, (tg * ug)[:, None], driver="gelsd").solution[:, 0]
    rest = float((tg * ug - A @ a).abs().max())
    return (c, *a.tolist(), rest if rest > 1e-12 else 1.0)


def segments(params: Params, grid: int = GRID) -> Segments:
    """The segments of ``params`` (see ``Segments``)."""
    env = params.env
    ends = breakpoints(params)
    shares: list[float] = [0.0]
    nodes, los, his, grids, weights, inverses, scales = [], [], [], [], [], [], []
    frac = torch.tensor(NODES, dtype=torch.float64)
    tg = torch.linspace(0.0, 1.0, grid, dtype=torch.float64)
    for lo, hi in itertools.pairwise(ends):
        idx = [len(shares) - 1]
        for x in NODES[1:]:
            shares.append(lo + x * (hi - lo))
            idx.append(len(shares) - 1)
        ua, ub = (
            float(reaction(torch.tensor(x, dtype=torch.float64), env.sensing, env.dwell_gain))
            for x in (lo, hi)
        )

        def rescaled(
            t: torch.Tensor, lo: Any = lo, hi: Any = hi, ua: Any = ua, ub: Any = ub
        ) -> torch.Tensor:
            if ub - ua < FLAT_REACTION:
                return t
            u = reaction(lo + t * (hi - lo), env.sensing, env.dwell_gain)
            return (u - ua) / (ub - ua)

        scales.append(_fit_basis(tg, rescaled(tg)))
        B = _basis(frac, rescaled(frac), scales[-1])  # [4 nodes, 4 functions]
        inverses.append(torch.linalg.pinv(B, rtol=1e-12))
        weights.append(_basis(tg, rescaled(tg), scales[-1]) @ inverses[-1])
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
        inverse=torch.stack(inverses),
        scale=torch.tensor(scales, dtype=torch.float64),
        sensing=env.sensing,
        gain=env.dwell_gain,
    )


def chain_at(nodes: DenseModel, seg: Segments, rho: torch.Tensor) -> DenseModel:
    """``policy_model`` of the ρ policy ``rho`` [S] from the node model ``nodes`` (built on
    ``seg.shares``): every row of its transitions and expectations is in the span of the four
    functions on its segment, so it is the weighted sum of the nodes' rows — the same chain to
    rounding (a test), without rebuilding the queue's tables."""
    k, w = seg.at(rho)
    idx = seg.nodes[k]  # [S, 4]
    s = torch.arange(nodes.num_states)

    def rows(table: torch.Tensor) -> torch.Tensor:
        return (w.reshape(*w.shape, *([1] * (table.ndim - 2))) * table[idx, s[:, None]]).sum(1)

    e = {n: rows(getattr(nodes, n))[None] for n in ("R", "missed", "false_alarms", "sent")}
    return DenseModel(
        params=nodes.params,
        P=rows(nodes.P)[None],
        event=nodes.event,
        dropped=rows(nodes.dropped)[None],
        capacity=rows(nodes.capacity)[None],
        queue=nodes.queue,
        radar=torch.as_tensor(rho, dtype=torch.float64)[None],
        **e,
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
    eye = torch.eye(nodes.num_states, dtype=torch.float64)
    it = 0
    while True:
        it += 1
        if it > max_iter:
            raise RuntimeError(f"policy iteration over ρ did not settle in {max_iter} steps")
        pm = policy_model(params, rho)
        V = torch.linalg.solve(eye - gamma * pm.P[0], pm.R[0])
        Q = nodes.q_values(V, gamma).T  # [S, N]
        best, share = maximise(seg, Q)
        better = best > V + 1e-12 * V.abs().clamp(min=1.0)
        if not bool(better.any()):
            break
        rho = torch.where(better, share, rho)
    step = step_bound(params, seg, Q)
    return ContinuumSolution(
        rho=rho,
        values=V,
        iterations=it,
        step_bound=step,
        value_bound=step / (1.0 - gamma),
        model=pm,
    )


def maximise(seg: Segments, Q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """([S] the largest value, [S] its share) of Q(s, ρ) over every segment's grid, from Q at the
    nodes ``Q`` [S, N] (any function in the span of {1, ρ, u, ρu} on each segment)."""
    Qg = torch.bmm(Q[:, seg.nodes].transpose(0, 1), seg.weights.transpose(1, 2))  # [K, S, GRID]
    top, at = Qg.max(-1)  # [K, S]
    best, k = top.max(0)
    return best, seg.grid[k, at.gather(0, k[None])[0]]


def step_bound(params: Params, seg: Segments, Q: torch.Tensor) -> float:
    """h²/8 · sup |∂²Q/∂ρ²| over states and segments, from Q's coefficients in ``_basis``
    (Q = b₀ + b₁t + b₂v + b₃w; t = (ρ − lo)/Δ, ũ = (u − u_lo)/δ): t″ = 0, v″ = ũ″/c and
    w″ = ((tũ)″ − a₂v″)/c_w with |(tũ)″| ≤ 2|ũ′|/Δ + |ũ″|; |ũ′| = u′/δ and |ũ″| = |u″|/δ are
    largest at lo (u′ > 0 falls, |u″| falls)."""
    env = params.env
    out = 0.0
    for j in range(seg.nodes.shape[0]):
        lo, hi = float(seg.lo[j]), float(seg.hi[j])
        width = hi - lo
        c, _, _, a2, cw = seg.scale[j].tolist()
        u = reaction(torch.tensor([lo, hi], dtype=torch.float64), env.sensing, env.dwell_gain)
        du = float(u[1] - u[0])
        coef = Q[:, seg.nodes[j]] @ seg.inverse[j].T  # [S, 4]
        d1, d2 = reaction_slope_bound(lo, env.sensing, env.dwell_gain)
        u1, u2 = (1.0 / width, 0.0) if du < FLAT_REACTION else (d1 / du, d2 / du)
        v2 = u2 / c
        w2 = (2 * u1 / width + u2 + abs(a2) * v2) / cw
        curv = coef[:, 2].abs() * v2 + coef[:, 3].abs() * w2
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
