"""The exact model without the S × S matrix (MODEL.md § B.4): the transition operator factorises
into the queue (d, the channel level c, the action and the arrivals) and the joint chain of the
Markov factors (c, r, w, v, m, with the radar reaction coupling v and m with the action), so P_a·V
is computed on V reshaped to [D + 1, 32] — the factor chain as a 32 × 32 matrix along the last axis,
the queue as a correlation of each column with the arrival distribution along the first — in
O(S · (32 + K)) per sweep, K the arrivals kept (Poisson mass to 1e-17).

The same expectations as ``irdrc.core.model.ExactModel`` (R, event, sent, dropped, capacity per
action and state) with the queue-free parts stored once per factor configuration. Value iteration
(with McQueen's bounds), policy evaluation, the stationary distribution and exact metrics run on
the operator, on CPU or GPU; ``irdrc.core.model.build_model`` stays the dense cross-check for
small S (tests/test_factored.py holds the two to 1e-9).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from irdrc.core.metrics import Metrics
from irdrc.core.params import Params
from irdrc.core.solve import DEFAULT_OPTIMUM_GAMMA, ExactScorer, false_alarm_rate
from irdrc.core.tables import model_tables

NEGLIGIBLE_MASS = 1e-30
"""Queue lengths holding less stationary mass than this (summed over the factors) are stepped by
the power iteration only within the arrivals' reach of the mass (below what any metric resolves)."""
GMRES_RTOL = 1e-12
"""Relative residual at which the GMRES solve for a stationary distribution stops (its L1 error
against power iteration to 1e-13 was ≈ 1e-10 on the persistent, deep-queue scenario)."""
GMRES_MAX_MATVECS = 3000
"""GMRES gives up after this many operator products (and power iteration takes over)."""
AUTO_POWER_STEPS = 300
"""``method="auto"``: power steps before aggregation (a fast-mixing chain has converged by then)."""
IAD_MAX_ITER = 5000
"""``method="auto"``: aggregation-disaggregation rounds before plain power iteration takes over."""
ARRIVAL_TAIL = 1e-17
"""Arrivals are summed exactly up to the smallest K with P(A ≥ K) < this; the rest (below float64's
resolution of the sums) goes into the last bucket, so the operator stays stochastic."""


@dataclass(frozen=True)
class FactoredModel:
    """The exact MDP of ``params`` as factors (see the module docstring). S = (D + 1)·F, F = Π L
    the factor configurations (``irdrc.core.tables``; v1: 32).

    Attributes:
        params: the parameters it was built from.
        F: [2, F, F] P(factors′ | a, factors).
        pmf: [n_rates, K] arrival probabilities per distinct Poisson rate, the last kept entry of
            each row holding its tail (rows padded with zeros to the longest).
        nu: [2, F] link capacity per (action, factor configuration).
        R: [2, F] expected reward per (action, factor configuration) (independent of d).
        event: [F] event probability per factor configuration.
        missed, false_alarm: [2, F] expected missed events and radar false alarms.
        group: [2, F] int64, the queue dynamics (ν, λ) of each (action, configuration), an index
            into ``groups`` (ν, pmf row) and into the rows of ``sent`` / ``dropped``.
        groups: (ν, pmf row) per queue dynamics.
        sent, dropped: [G, D + 1] expected packets sent / dropped per queue dynamics and d.
        device: where the tensors live.
    """

    params: Params
    F: torch.Tensor
    pmf: torch.Tensor
    nu: torch.Tensor
    R: torch.Tensor
    event: torch.Tensor
    missed: torch.Tensor
    false_alarm: torch.Tensor
    group: torch.Tensor
    groups: tuple[tuple[int, int], ...]
    sent: torch.Tensor
    dropped: torch.Tensor
    rate: torch.Tensor
    device: torch.device

    def __post_init__(self) -> None:
        # Per action, the configurations of each queue dynamics: a slice when contiguous (v1: the
        # channel's halves), else an index tensor.
        cols = []
        for a in (0, 1):
            per = []
            g_a = self.group[a].cpu()
            for g in sorted(set(g_a.tolist())):
                idx = (g_a == g).nonzero().flatten()
                lo, hi = int(idx[0]), int(idx[-1]) + 1
                sel = slice(lo, hi) if hi - lo == idx.numel() else idx.to(self.device)
                per.append((sel, *self.groups[g]))
            cols.append(tuple(per))
        object.__setattr__(self, "_cols", tuple(cols))
        # each row's probabilities as floats, without the padding zeros (the shifts to add up)
        weights = []
        for r in self.pmf.cpu().tolist():
            while len(r) > 1 and r[-1] == 0.0:
                r.pop()
            weights.append(tuple(r))
        object.__setattr__(self, "_weights", tuple(weights))

    @property
    def num_configs(self) -> int:
        """F, the factor configurations."""
        return int(self.F.shape[-1])

    @property
    def queue_capacity(self) -> int:
        """D."""
        return int(self.sent.shape[-1]) - 1

    @property
    def num_states(self) -> int:
        """S = (D + 1)·F."""
        return (self.queue_capacity + 1) * self.num_configs

    # ---- per-state tables, [2, S] in the state order of irdrc.core.env -------------------------

    def _per_f(self, table: torch.Tensor) -> torch.Tensor:
        """[2, F] → [2, S] (constant in d)."""
        D1, nf = self.queue_capacity + 1, self.num_configs
        return table[:, None, :].expand(2, D1, nf).reshape(2, -1)

    def _per_group(self, table: torch.Tensor) -> torch.Tensor:
        """[G, D + 1] (queue dynamics, d) → [2, S]."""
        return table[self.group].transpose(1, 2).reshape(2, -1)

    def reward_table(self) -> torch.Tensor:
        """[2, S] expected reward."""
        return self._per_f(self.R)

    def tables(self) -> dict[str, torch.Tensor]:
        """[2, S] (or [S]) expectations by name, as in ``ExactModel``: R, event, missed,
        false_alarms, sent, dropped, capacity, queue."""
        D1 = self.queue_capacity + 1
        return {
            "R": self.reward_table(),
            "event": self.event.repeat(D1),
            "missed": self._per_f(self.missed),
            "false_alarms": self._per_f(self.false_alarm),
            "sent": self._per_group(self.sent),
            "dropped": self._per_group(self.dropped),
            "capacity": self._per_f(self.nu),
            "queue": torch.arange(D1, device=self.device, dtype=torch.float64).repeat_interleave(
                self.num_configs
            ),
        }

    # ---- the operator ---------------------------------------------------------------------------

    def _queue_expect(self, W: torch.Tensor, a: int) -> torch.Tensor:
        """out[d, f] = Σ_k pmf[k]·W[clamp(d + k − ν(a, f), 0, D), f] for W [D + 1, F]."""
        D1 = W.shape[0]
        out = torch.empty_like(W)
        for cols, nu, row in self._cols[a]:
            pmf = self._weights[row]
            K = len(pmf)
            w = W[:, cols]  # [D + 1, n]
            # Pad so that index d + k − ν is clamped: ν copies of row 0 before, K copies of row D
            # after; then out[d] = Σ_k pmf[k]·padded[d + k], one shifted add per k (cheaper than a
            # float64 conv1d or materialised windows at every size measured).
            padded = torch.cat([w[:1].expand(nu, -1), w, w[-1:].expand(K, -1)])
            acc = padded[:D1] * pmf[0]
            for k in range(1, K):
                acc.add_(padded[k : k + D1], alpha=pmf[k])
            out[:, cols] = acc
        return out

    def expect(self, V: torch.Tensor, a: int) -> torch.Tensor:
        """(P_a V)(s) = E[V(s′) | s, a] for V [S]."""
        D1 = self.queue_capacity + 1
        W = V.reshape(D1, self.num_configs) @ self.F[a].T  # W[d′, f] = Σ_f′ F[a,f,f′] V(d′,f′)
        return self._queue_expect(W, a).reshape(-1)

    def push(self, x: torch.Tensor, a: int) -> torch.Tensor:
        """(x P_a)(s′) for a measure x [S] over states: the distribution after one step of a."""
        return self._push_rows(x.reshape(-1, self.num_configs), a).reshape(-1)

    def _push_rows(self, X: torch.Tensor, a: int) -> torch.Tensor:
        """One step of a for a measure X [n, F] on the queue lengths 0 … n − 1 (n = D + 1: the
        whole chain; a shorter prefix clamps at n − 1 instead of D, exact while no mass comes
        within the arrivals' reach of n − 1)."""
        n = X.shape[0]
        Z = torch.empty_like(X)
        for cols, nu, row in self._cols[a]:
            pmf = self._weights[row]
            K = len(pmf)
            x = X[:, cols]  # [n, m]
            # full[j] = Σ_k pmf[k]·X[j − k]: mass at d + k; its queue is clamp(j − ν, 0, n − 1).
            full = x.new_zeros(n + K - 1, x.shape[1])
            for k in range(K):
                full[k : k + n].add_(x, alpha=pmf[k])
            z = full[nu : nu + n].clone()
            z[0] += full[:nu].sum(0)
            z[-1] += full[nu + n :].sum(0)
            Z[:, cols] = z
        return Z @ self.F[a]

    def step_measure(self, x: torch.Tensor, p_radar: torch.Tensor) -> torch.Tensor:
        """One step of the chain of a stationary policy (``p_radar`` [S]) from measure x [S]."""
        return self.push(x * (1 - p_radar), 0) + self.push(x * p_radar, 1)

    def step_rows(self, X: torch.Tensor, P: torch.Tensor) -> torch.Tensor:
        """``step_measure`` on the first n queue lengths: X, P [n, F] (measure, P(radar))."""
        return self._push_rows(X * (1 - P), 0) + self._push_rows(X * P, 1)


def _poisson(lam: float, n: int) -> torch.Tensor:
    """P(A = k) for k = 0 … n − 1, A ~ Poisson(λ) (float64; underflows to 0 far in the tail)."""
    k = torch.arange(n, dtype=torch.float64)
    if lam == 0:
        return (k == 0).to(torch.float64)
    return torch.exp(k * math.log(lam) - lam - torch.lgamma(k + 1))


def _queue_expectations(
    lam: float, D: int, n: int, nu_max: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """[D + 1] expected packets sent and dropped per d for capacity ν = ``n``, by finite sums:
    sent = E[min(d + A, ν)] = ν − Σ_{k < ν − d} (ν − d − k)·p_k, and dropped =
    E[(d + A − ν − D)^+] = Σ_{k > m} (k − m)·p_k with m = D + ν − d, from tail sums of p_k and
    k·p_k accumulated from the far tail inwards (no cancellation, whatever D)."""
    top = D + nu_max + 1
    p = _poisson(lam, top + int(50 * math.sqrt(lam)) + 60)
    k = torch.arange(p.shape[0], dtype=torch.float64)
    # tails: T0[m] = Σ_{k > m} p_k, T1[m] = Σ_{k > m} k·p_k
    T0 = torch.flip(torch.cumsum(torch.flip(p, [0]), 0), [0])
    T1 = torch.flip(torch.cumsum(torch.flip(k * p, [0]), 0), [0])
    T0 = torch.cat([T0[1:], T0.new_zeros(1)])
    T1 = torch.cat([T1[1:], T1.new_zeros(1)])
    d = torch.arange(D + 1)
    short = torch.zeros(D + 1, dtype=torch.float64)
    for kk in range(n):  # Σ_{k < ν − d} (ν − d − k)·p_k, only for d < ν
        gap = (n - d - kk).clamp(min=0).to(torch.float64)
        short += gap * p[kk]
    m = D + n - d
    return n - short, T1[m] - m.to(torch.float64) * T0[m]


def _arrival_pmf(lam: float) -> torch.Tensor:
    """P(A = k), k = 0 … K − 1, K the smallest with P(A ≥ K) < ``ARRIVAL_TAIL``; the last entry
    holds P(A ≥ K − 1), so the row sums to 1."""
    p = _poisson(lam, int(lam + 50 * math.sqrt(lam) + 60))
    tail = torch.flip(torch.cumsum(torch.flip(p, [0]), 0), [0])  # tail[k] = P(A ≥ k)
    K = max(1, int((tail >= ARRIVAL_TAIL).sum()))  # A = 0 … K − 1 kept; P(A ≥ K) < ARRIVAL_TAIL
    pmf = p[:K].clone()
    pmf[-1] = tail[K - 1]  # the last bucket holds P(A ≥ K − 1)
    return pmf / pmf.sum()


def build_factored(params: Params, device: str | torch.device = "cpu") -> FactoredModel:
    """The factored exact model of ``params`` (any queue capacity D; the general model of
    MODEL.md § B too)."""
    dev = torch.device(device)
    D = params.env.queue_capacity
    t = model_tables(params)
    nf = t.num_configs
    rates = sorted(set(t.rate.tolist()))
    pmfs = [_arrival_pmf(r) for r in rates]
    width = max(p.shape[0] for p in pmfs)
    pmf = torch.stack([torch.cat([p, p.new_zeros(width - p.shape[0])]) for p in pmfs])
    nu_max = int(t.nu.max())
    keys: dict[tuple[int, int], int] = {}
    group = torch.zeros(2, nf, dtype=torch.int64)
    for a in (0, 1):
        for g in range(nf):
            key = (int(t.nu[a, g]), rates.index(float(t.rate[g])))
            group[a, g] = keys.setdefault(key, len(keys))
    sent, dropped = [], []
    for nu, row in keys:
        s_, d_ = _queue_expectations(rates[row], D, nu, nu_max)
        sent.append(s_)
        dropped.append(d_)
    return FactoredModel(
        params=params,
        F=t.F.to(dev),
        pmf=pmf.to(dev),
        nu=t.nu.to(dev),
        R=t.R.to(dev),
        event=t.event.to(dev),
        missed=t.missed.to(dev),
        false_alarm=t.false_alarm.to(dev),
        group=group.to(dev),
        groups=tuple((nu, row) for nu, row in keys),
        sent=torch.stack(sent).to(dev),
        dropped=torch.stack(dropped).to(dev),
        rate=t.rate.to(dev),
        device=dev,
    )


@dataclass(frozen=True)
class FactoredSolution:
    """Value iteration's result: greedy ``policy`` [S] (0 comm, 1 radar; ties → comm), its
    ``values`` [S] (within ``bound`` of the optimal values V*, by McQueen's bounds), sweeps."""

    policy: torch.Tensor
    values: torch.Tensor
    iterations: int
    bound: float


def value_iteration_factored(
    model: FactoredModel, gamma: float = 0.99, tol: float = 1e-6, max_iter: int = 1_000_000
) -> FactoredSolution:
    """Optimal policy by value iteration on the factored operator, stopped by McQueen's bounds:
    with δ = V_{k+1} − V_k, V* lies in [V_{k+1} + γ/(1−γ)·min δ, V_{k+1} + γ/(1−γ)·max δ], so the
    midpoint is within ``bound`` = γ/(1−γ)·span(δ)/2 of V* everywhere; iteration stops when that is
    below ``tol``. The span contracts at the chain's mixing rate, usually far faster than γ."""
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma={gamma!r} must be in [0, 1)")
    if tol <= 0 or max_iter < 1:
        raise ValueError("tol must be > 0 and max_iter >= 1")
    R = model.reward_table()
    V = torch.zeros(model.num_states, dtype=torch.float64, device=model.device)
    scale = gamma / (1.0 - gamma)
    bound = math.inf
    for it in range(1, max_iter + 1):  # noqa: B007 - reported after the loop
        Q = torch.stack([R[a] + gamma * model.expect(V, a) for a in (0, 1)])
        V_new = Q.max(0).values
        delta = V_new - V
        lo, hi = float(delta.min()), float(delta.max())
        V = V_new
        bound = scale * (hi - lo) / 2
        if bound < tol:
            V = V + scale * (hi + lo) / 2
            break
    else:
        raise RuntimeError(
            f"value iteration did not reach tol {tol:g} in {max_iter} sweeps (bound {bound:.3g})"
        )
    Q = torch.stack([R[a] + gamma * model.expect(V, a) for a in (0, 1)])
    return FactoredSolution(policy=Q.argmax(0), values=V, iterations=it, bound=bound)


def _p_radar(model: FactoredModel, policy: torch.Tensor) -> torch.Tensor:
    """[S] P(radar) from an [S] action table or [S, 2] probabilities."""
    t = torch.as_tensor(policy, device=model.device)
    if t.shape == (model.num_states,):
        return t.to(torch.float64)
    if t.shape == (model.num_states, 2):
        return t[:, 1].to(torch.float64)
    raise ValueError(f"policy must be [{model.num_states}] actions or [{model.num_states}, 2]")


def _start_queue(model: FactoredModel, p: torch.Tensor) -> int:
    """Where the power iteration starts: the first queue length at which the policy's expected
    drift E[d′ − d] (averaged over the factor configurations as they occur) is ≤ 0 — where the queue settles —
    or D if it grows everywhere. A deep queue then need not be crossed step by step."""
    D1 = p.shape[0]
    nf = model.num_configs
    # [2, D + 1, F]: expected packets leaving the queue (sent + dropped) per action, d, f
    out = (model.sent + model.dropped)[model.group].transpose(1, 2)
    # weight the factor configurations by how often they occur (the factor chain's stationary
    # distribution under comm; the reaction only perturbs it)
    F = model.F[0]
    A = torch.cat(
        [
            F.T - torch.eye(nf, dtype=F.dtype, device=F.device),
            F.new_ones(1, nf),
        ]
    )
    b = F.new_zeros(nf + 1)
    b[-1] = 1.0
    w = torch.linalg.lstsq(A.cpu(), b.cpu()[:, None]).solution[:, 0].clamp(min=0).to(F.device)
    lam = float((model.rate * w).sum() / w.sum())  # mean arrivals per step
    drift = lam - (((1 - p) * out[0] + p * out[1]) * w).sum(-1) / w.sum()  # [D + 1]
    settled = (drift <= 0).nonzero()
    return int(settled[0]) if settled.numel() else D1 - 1


def stationary_distribution_factored(
    model: FactoredModel,
    policy: torch.Tensor,
    tol: float = 1e-13,
    max_iter: int = 1_000_000,
    method: str = "auto",
) -> tuple[torch.Tensor, int]:
    """The stationary distribution of a stationary policy on the factored operator. Returns
    (μ [S], operator applications).

    ``method``: ``power`` steps the chain until the L1 change of a step is below ``tol``, from
    where the policy's queue settles (``_start_queue``) and only over the queue lengths that hold
    mass (above ``NEGLIGIBLE_MASS``) plus the arrivals' reach; ``iad`` alternates one such step
    with an exact solve of the queue-length chain aggregated over the factors
    (``_stationary_iad``), so the queue — the slow part of a deep buffer — settles in one round
    and the rounds needed are set by the factors' mixing (``large``: ≈ 150 rounds, 5–8× faster
    than GMRES); ``gmres`` solves (I − P_πᵀ + 11ᵀ/S)·μ = 1/S (SciPy's restarted GMRES, relative
    residual ``GMRES_RTOL``, at most ``GMRES_MAX_MATVECS`` products; CPU); ``auto`` steps the
    chain ``AUTO_POWER_STEPS`` times, then hands the iterate to ``iad`` (at most
    ``IAD_MAX_ITER`` rounds) and goes on stepping if that does not converge. The operator
    applications returned count one per power step or round. Assumes one recurrent class, as
    ``irdrc.core.solve.stationary_distribution``."""
    if method not in ("auto", "gmres", "iad", "power"):
        raise ValueError(f"method={method!r} must be auto, gmres, iad or power")
    p = _p_radar(model, policy)
    rows = p.reshape(-1, model.num_configs)
    if method == "power":
        return _stationary_power(model, rows, tol, max_iter)
    if method == "gmres":
        mu, calls = _stationary_gmres(model, p)
        if mu is None:
            raise RuntimeError("GMRES did not converge on this chain; use method='power'")
        return mu, calls
    if method == "iad":
        mu, calls, done = _stationary_iad(model, rows, tol, max_iter)
        if not done:
            raise RuntimeError(f"the stationary distribution did not converge in {max_iter} rounds")
        return mu, calls
    start, steps, done = _stationary_power(model, rows, tol, AUTO_POWER_STEPS, partial=True)
    if done:
        return start, steps
    mu, calls, done = _stationary_iad(model, rows, tol, IAD_MAX_ITER, start=start)
    if done:
        return mu, steps + calls
    mu, more = _stationary_power(model, rows, tol, max_iter, start=mu)
    return mu, steps + calls + more


def _stationary_iad(
    model: FactoredModel,
    p: torch.Tensor,
    tol: float,
    max_iter: int,
    start: torch.Tensor | None = None,
) -> tuple[torch.Tensor, int, bool]:
    """Iterative aggregation-disaggregation (Koury, McAllister and Stewart) over the queue length.
    Each round: one power step X → X·P_π (stop when its L1 change is below ``tol``); the factors'
    conditional distribution given d, c(f | d) = X[d, f] / Σ_f X[d, f]; the aggregated chain on
    d alone, A[d, d′] = Σ_{a, f} c(f | d)·π(a | d, f)·P(d′ | d, ν(a, f), arrivals of f) — exact for
    the true μ, since the factors' next value does not enter d′ — solved for its stationary α by a
    sparse LU (banded: d′ − d between −ν and the arrivals kept); then X = α(d)·c(f | d).
    Returns (μ [S], rounds, converged)."""
    import numpy as np
    import scipy.sparse as sparse
    from scipy.sparse.linalg import spsolve

    D1, nf = p.shape
    d = np.arange(D1)
    # per (action, queue dynamics): the columns it covers and A's entries (src d → dst d′, P)
    parts = []
    for a in (0, 1):
        for cols, nu, row in model._cols[a]:
            pmf = model.pmf[row].cpu().numpy()
            K = pmf.shape[0]
            src = np.repeat(d, K)
            dst = np.clip(src + np.tile(np.arange(K), D1) - nu, 0, D1 - 1)
            parts.append((a, cols, src, np.tile(pmf, D1), dst))
    # (Aᵀ − I)·α = 0, entries (dst, src), with the row of one queue length r replaced by α_r = 1
    # (r holds the most mass, so it is recurrent): the matrix stays banded — d′ − d between −ν and
    # the arrivals kept — and its LU costs O(D), where a row of ones (Σ α = 1) fills it in.
    ri = np.concatenate([pt[4] for pt in parts] + [d])
    ci = np.concatenate([pt[2] for pt in parts] + [d])
    diag = -np.ones(D1)
    if start is None:
        X = torch.zeros(D1, nf, dtype=torch.float64, device=model.device)
        X[_start_queue(model, p)] = 1.0 / nf
    else:
        X = start.reshape(D1, nf).clone()
    uniform = torch.full_like(X, 1.0 / nf)
    choice = (1 - p, p)
    for it in range(1, max_iter + 1):
        Y = model.step_rows(X, p)
        Y = Y / Y.sum()
        change = float((Y - X).abs().sum())
        X = Y
        if change < tol:
            return X.reshape(-1), it, True
        mass = X.sum(1, keepdim=True)
        cond = torch.where(mass > 0, X / mass.clamp(min=1e-300), uniform)
        vals = []
        for a, cols, src, pmf, _ in parts:
            w = (cond[:, cols] * choice[a][:, cols]).sum(1).cpu().numpy()
            vals.append(w[src] * pmf)
        r = int(mass.argmax())
        keep = ri != r
        M = sparse.csc_matrix(
            (
                np.append(np.concatenate([*vals, diag])[keep], 1.0),
                (np.append(ri[keep], r), np.append(ci[keep], r)),
            ),
            shape=(D1, D1),
        )
        b = np.zeros(D1)
        b[r] = 1.0
        alpha = torch.from_numpy(np.clip(spsolve(M, b), 0.0, None)).to(X.device)
        X = (alpha / alpha.sum())[:, None] * cond
    return X.reshape(-1), max_iter, False


def _stationary_gmres(model: FactoredModel, p: torch.Tensor) -> tuple[torch.Tensor | None, int]:
    import numpy as np
    from scipy.sparse.linalg import LinearOperator, gmres

    S = model.num_states
    pc = p.cpu()
    calls = 0

    def matvec(x):
        nonlocal calls
        calls += 1
        xt = torch.from_numpy(np.asarray(x, dtype=np.float64).reshape(-1))
        return (xt - model.step_measure(xt, pc) + xt.sum() / S).numpy()

    start = torch.zeros(S, dtype=torch.float64)
    nf = model.num_configs
    d0 = _start_queue(model, pc.reshape(-1, nf))
    start[d0 * nf : (d0 + 1) * nf] = 1.0 / nf
    A = LinearOperator((S, S), matvec=matvec, dtype=np.float64)
    b = np.full(S, 1.0 / S)
    x, info = gmres(
        A,
        b,
        x0=start.cpu().numpy(),
        rtol=GMRES_RTOL,
        atol=0.0,
        restart=100,
        maxiter=GMRES_MAX_MATVECS // 100,
    )
    if info != 0 or float(np.min(x)) < -1e-9 * float(np.max(np.abs(x))):
        return None, calls
    mu = torch.from_numpy(np.clip(x, 0.0, None))
    return (mu / mu.sum()).to(model.device), calls


def _stationary_power(
    model: FactoredModel,
    p: torch.Tensor,
    tol: float,
    max_iter: int,
    start: torch.Tensor | None = None,
    partial: bool = False,
):
    """Power iteration (see ``stationary_distribution_factored``). Returns (μ, steps), or with
    ``partial`` (μ, steps, converged) instead of raising when ``max_iter`` steps do not converge."""
    D1 = p.shape[0]
    if start is None:
        nf = model.num_configs
        X = torch.zeros(D1, nf, dtype=torch.float64, device=model.device)
        X[_start_queue(model, p)] = 1.0 / nf
    else:
        X = start.reshape(D1, model.num_configs).clone()
    reach = model.pmf.shape[-1] + 1  # how far up the queue one step can carry mass
    for it in range(1, max_iter + 1):
        held = (X.sum(1) > NEGLIGIBLE_MASS).nonzero()
        top = min(D1, int(held.max()) + 1 + 2 * reach) if held.numel() else D1
        Y = torch.zeros_like(X)
        Y[:top] = model.step_rows(X[:top], p[:top])
        Y = Y / Y.sum()
        change = float((Y - X).abs().sum())
        X = Y
        if change < tol:
            return (X.reshape(-1), it, True) if partial else (X.reshape(-1), it)
    if partial:
        return X.reshape(-1), max_iter, False
    raise RuntimeError(f"the stationary distribution did not converge in {max_iter} steps")


def stationary_metrics_factored(
    model: FactoredModel,
    policy: torch.Tensor,
    tol: float = 1e-13,
    mu: torch.Tensor | None = None,
) -> Metrics:
    """Exact long-run metrics of a stationary policy ([S] actions or [S, 2] probabilities), the
    factored counterpart of ``irdrc.core.solve.stationary_metrics``; ``mu``: its stationary
    distribution when already computed (``stationary_distribution_factored``)."""
    p = _p_radar(model, policy)
    if mu is None:
        mu, _ = stationary_distribution_factored(model, p, tol=tol)
    occ = torch.stack([mu * (1 - p), mu * p])
    t = model.tables()
    horizon = model.params.env.horizon
    avg_reward = float((occ * t["R"]).sum())
    events = float((occ.sum(0) * t["event"]).sum())
    missed = float((occ * t["missed"]).sum())
    return Metrics(
        avg_reward=avg_reward,
        episode_reward=avg_reward * horizon,
        throughput=float((occ * t["sent"]).sum()),
        link_capacity=float((occ * t["capacity"]).sum()),
        miss_detection=missed / events if events > 0 else float("nan"),
        radar_fraction=float(occ[1].sum()),
        drop_rate=float((occ * t["dropped"]).sum()),
        mean_queue=float((occ.sum(0) * t["queue"]).sum()),
        false_alarm_rate=false_alarm_rate(occ, t["event"], t["false_alarms"], model.params),
    )


class FactoredScorer(ExactScorer):
    """``ExactScorer`` on the factored model: the optimum by ``value_iteration_factored`` (to
    ``tol``), a table's metrics by ``stationary_metrics_factored``; for S beyond the dense model."""

    def __init__(
        self, model: FactoredModel, gamma: float = DEFAULT_OPTIMUM_GAMMA, tol: float = 1e-6
    ) -> None:
        self.model = model
        self.optimal = value_iteration_factored(model, gamma=gamma, tol=tol)
        self.optimal_metrics = stationary_metrics_factored(model, self.optimal.policy)
        self._cache = {}

    def _evaluate(self, table: torch.Tensor) -> Metrics:
        return stationary_metrics_factored(self.model, table.to(self.model.device))


def exact_scorer(params: Params, gamma: float = DEFAULT_OPTIMUM_GAMMA) -> ExactScorer:
    """The exact scorer of ``params``: on the dense model up to ``DENSE_MODEL_LIMIT_BYTES`` (the
    size ``recipes/solve.py`` switches at), else on the factored one."""
    from irdrc.core.model import DENSE_MODEL_LIMIT_BYTES, build_model

    if 16 * params.env.num_states**2 <= DENSE_MODEL_LIMIT_BYTES:
        return ExactScorer(build_model(params), gamma)
    return FactoredScorer(build_factored(params), gamma)
