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
from irdrc.core.model import _factor_transitions, event_and_reward
from irdrc.core.params import Params

NUM_FACTOR_CONFIGS = 32
NEGLIGIBLE_MASS = 1e-30
"""Queue lengths holding less stationary mass than this (summed over the factors) are stepped by
the power iteration only within the arrivals' reach of the mass (below what any metric resolves)."""
GMRES_RTOL = 1e-12
"""Relative residual at which the GMRES solve for a stationary distribution stops (its L1 error
against power iteration to 1e-13 was ≈ 1e-10 on the persistent, deep-queue scenario)."""
GMRES_MAX_MATVECS = 3000
"""GMRES gives up after this many operator products (and power iteration takes over)."""
AUTO_POWER_STEPS = 300
"""``method="auto"``: power steps before GMRES (a fast-mixing chain has converged by then)."""
ARRIVAL_TAIL = 1e-17
"""Arrivals are summed exactly up to the smallest K with P(A ≥ K) < this; the rest (below float64's
resolution of the sums) goes into the last bucket, so the operator stays stochastic."""


@dataclass(frozen=True)
class FactoredModel:
    """The exact MDP of ``params`` as factors (see the module docstring). S = (D + 1)·32.

    Attributes:
        params: the parameters it was built from.
        F: [2, 32, 32] P(factors′ | a, factors).
        pmf: [K] arrival probabilities, the last entry holding the tail P(A ≥ K − 1).
        nu: [2, 2] link capacity per (action, channel level).
        R: [2, 32] expected reward per (action, factor configuration) (independent of d).
        event: [32] event probability per factor configuration.
        sent, dropped: [2, 2, D + 1] expected packets sent / dropped per (action, c, d).
        device: where the tensors live.
    """

    params: Params
    F: torch.Tensor
    pmf: torch.Tensor
    nu: torch.Tensor
    R: torch.Tensor
    event: torch.Tensor
    sent: torch.Tensor
    dropped: torch.Tensor
    device: torch.device

    @property
    def queue_capacity(self) -> int:
        """D."""
        return int(self.sent.shape[-1]) - 1

    @property
    def num_states(self) -> int:
        """S = (D + 1)·32."""
        return (self.queue_capacity + 1) * NUM_FACTOR_CONFIGS

    # ---- per-state tables, [2, S] in the state order of irdrc.core.env -------------------------

    def _per_f(self, table: torch.Tensor) -> torch.Tensor:
        """[2, 32] → [2, S] (constant in d)."""
        return (
            table[:, None, :].expand(2, self.queue_capacity + 1, NUM_FACTOR_CONFIGS).reshape(2, -1)
        )

    def _per_cd(self, table: torch.Tensor) -> torch.Tensor:
        """[2, 2, D + 1] (a, c, d) → [2, S]."""
        c = torch.arange(NUM_FACTOR_CONFIGS, device=self.device) >> 4
        return table[:, c, :].transpose(1, 2).reshape(2, -1)

    def reward_table(self) -> torch.Tensor:
        """[2, S] expected reward."""
        return self._per_f(self.R)

    def tables(self) -> dict[str, torch.Tensor]:
        """[2, S] (or [S]) expectations by name, as in ``ExactModel``: R, event, missed, sent,
        dropped, capacity, queue."""
        D1 = self.queue_capacity + 1
        c = torch.arange(NUM_FACTOR_CONFIGS, device=self.device) >> 4
        event = self.event.repeat(D1)
        return {
            "R": self.reward_table(),
            "event": event,
            "missed": torch.stack([event, torch.zeros_like(event)]),
            "sent": self._per_cd(self.sent),
            "dropped": self._per_cd(self.dropped),
            "capacity": self._per_f(self.nu[:, c]),
            "queue": torch.arange(D1, device=self.device, dtype=torch.float64).repeat_interleave(
                NUM_FACTOR_CONFIGS
            ),
        }

    # ---- the operator ---------------------------------------------------------------------------

    def _queue_expect(self, W: torch.Tensor, a: int) -> torch.Tensor:
        """out[d, f] = Σ_k pmf[k]·W[clamp(d + k − ν(a, c(f)), 0, D), f] for W [D + 1, 32]."""
        D1 = W.shape[0]
        K = self.pmf.shape[0]
        out = torch.empty_like(W)
        for ch in (0, 1):
            cols = slice(16 * ch, 16 * ch + 16)
            nu = int(self.nu[a, ch])
            w = W[:, cols].T[:, None, :]  # [16, 1, D + 1]
            # Pad so that index d + k − ν is clamped: ν copies of row 0 before, K copies of row D
            # after; then a correlation with the pmf.
            left = w[..., :1].expand(-1, -1, nu)
            right = w[..., -1:].expand(-1, -1, K)
            padded = torch.cat([left, w, right], -1)
            conv = torch.nn.functional.conv1d(padded, self.pmf.view(1, 1, -1))  # [16, 1, L]
            out[:, cols] = conv[:, 0, :D1].T
        return out

    def expect(self, V: torch.Tensor, a: int) -> torch.Tensor:
        """(P_a V)(s) = E[V(s′) | s, a] for V [S] (or [S, B]… as [S])."""
        D1 = self.queue_capacity + 1
        W = V.reshape(D1, NUM_FACTOR_CONFIGS) @ self.F[a].T  # W[d′, f] = Σ_f′ F[a,f,f′] V(d′,f′)
        return self._queue_expect(W, a).reshape(-1)

    def push(self, x: torch.Tensor, a: int) -> torch.Tensor:
        """(x P_a)(s′) for a measure x [S] over states: the distribution after one step of a."""
        return self._push_rows(x.reshape(-1, NUM_FACTOR_CONFIGS), a).reshape(-1)

    def _push_rows(self, X: torch.Tensor, a: int) -> torch.Tensor:
        """One step of a for a measure X [n, 32] on the queue lengths 0 … n − 1 (n = D + 1: the
        whole chain; a shorter prefix clamps at n − 1 instead of D, exact while no mass comes
        within the arrivals' reach of n − 1)."""
        n = X.shape[0]
        Z = torch.empty_like(X)
        for ch in (0, 1):
            cols = slice(16 * ch, 16 * ch + 16)
            nu = int(self.nu[a, ch])
            # full[j] = Σ_k pmf[k]·X[j − k]: mass at d + k; its queue is clamp(j − ν, 0, n − 1).
            full = torch.nn.functional.conv_transpose1d(
                X[:, cols].T[:, None, :], self.pmf.view(1, 1, -1)
            )[:, 0, :]  # [16, n + K − 1]
            z = full[:, nu : nu + n].clone()
            z[:, 0] += full[:, :nu].sum(-1)
            z[:, -1] += full[:, nu + n :].sum(-1)
            Z[:, cols] = z.T
        return Z @ self.F[a]

    def step_measure(self, x: torch.Tensor, p_radar: torch.Tensor) -> torch.Tensor:
        """One step of the chain of a stationary policy (``p_radar`` [S]) from measure x [S]."""
        return self.push(x * (1 - p_radar), 0) + self.push(x * p_radar, 1)

    def step_rows(self, X: torch.Tensor, P: torch.Tensor) -> torch.Tensor:
        """``step_measure`` on the first n queue lengths: X, P [n, 32] (measure, P(radar))."""
        return self._push_rows(X * (1 - P), 0) + self._push_rows(X * P, 1)


def _poisson(lam: float, n: int) -> torch.Tensor:
    """P(A = k) for k = 0 … n − 1, A ~ Poisson(λ) (float64; underflows to 0 far in the tail)."""
    k = torch.arange(n, dtype=torch.float64)
    if lam == 0:
        return (k == 0).to(torch.float64)
    return torch.exp(k * math.log(lam) - lam - torch.lgamma(k + 1))


def _queue_expectations(lam: float, D: int, nu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[2, 2, D + 1] expected packets sent and dropped per (action, c, d), by finite sums:
    sent = E[min(d + A, ν)] = ν − Σ_{k < ν − d} (ν − d − k)·p_k, and dropped =
    E[(d + A − ν − D)^+] = Σ_{k > m} (k − m)·p_k with m = D + ν − d, from tail sums of p_k and
    k·p_k accumulated from the far tail inwards (no cancellation, whatever D)."""
    nu_max = int(nu.max())
    top = D + nu_max + 1
    p = _poisson(lam, top + int(50 * math.sqrt(lam)) + 60)
    k = torch.arange(p.shape[0], dtype=torch.float64)
    # tails: T0[m] = Σ_{k > m} p_k, T1[m] = Σ_{k > m} k·p_k
    T0 = torch.flip(torch.cumsum(torch.flip(p, [0]), 0), [0])
    T1 = torch.flip(torch.cumsum(torch.flip(k * p, [0]), 0), [0])
    T0 = torch.cat([T0[1:], T0.new_zeros(1)])
    T1 = torch.cat([T1[1:], T1.new_zeros(1)])
    d = torch.arange(D + 1)
    sent = torch.zeros(2, 2, D + 1, dtype=torch.float64)
    dropped = torch.zeros(2, 2, D + 1, dtype=torch.float64)
    for a in (0, 1):
        for ch in (0, 1):
            n = int(nu[a, ch])
            short = torch.zeros(D + 1, dtype=torch.float64)
            for kk in range(n):  # Σ_{k < ν − d} (ν − d − k)·p_k, only for d < ν
                gap = (n - d - kk).clamp(min=0).to(torch.float64)
                short += gap * p[kk]
            sent[a, ch] = n - short
            m = D + n - d
            dropped[a, ch] = T1[m] - m.to(torch.float64) * T0[m]
    return sent, dropped


def build_factored(params: Params, device: str | torch.device = "cpu") -> FactoredModel:
    """The factored exact model of ``params`` (any queue capacity D)."""
    env = params.env
    dev = torch.device(device)
    event, R = event_and_reward(params, torch.arange(NUM_FACTOR_CONFIGS))

    lam = env.arrival_rate
    p = _poisson(lam, int(lam + 50 * math.sqrt(lam) + 60))
    tail = torch.flip(torch.cumsum(torch.flip(p, [0]), 0), [0])  # tail[k] = P(A ≥ k)
    K = max(1, int((tail >= ARRIVAL_TAIL).sum()))  # A = 0 … K − 1 kept; P(A ≥ K) < ARRIVAL_TAIL
    pmf = p[:K].clone()
    pmf[-1] = tail[K - 1]  # the last bucket holds P(A ≥ K − 1)
    pmf = pmf / pmf.sum()
    nu = torch.zeros(2, 2, dtype=torch.float64)
    nu[0, 0], nu[0, 1] = env.packets_good, env.packets_bad
    sent, dropped = _queue_expectations(lam, env.queue_capacity, nu)
    return FactoredModel(
        params=params,
        F=_factor_transitions(params).to(dev),
        pmf=pmf.to(dev),
        nu=nu.to(dev),
        R=R.to(dev),
        event=event.to(dev),
        sent=sent.to(dev),
        dropped=dropped.to(dev),
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
    c = torch.arange(NUM_FACTOR_CONFIGS, device=model.device) >> 4
    lam = float(model.params.env.arrival_rate)
    # [2, D + 1, 32]: expected packets leaving the queue (sent + dropped) per action, d, f
    out = (model.sent + model.dropped)[:, c, :].transpose(1, 2)
    # weight the factor configurations by how often they occur (the factor chain's stationary
    # distribution under comm; the reaction only perturbs it)
    F = model.F[0]
    A = torch.cat(
        [
            F.T - torch.eye(NUM_FACTOR_CONFIGS, dtype=F.dtype, device=F.device),
            F.new_ones(1, NUM_FACTOR_CONFIGS),
        ]
    )
    b = F.new_zeros(NUM_FACTOR_CONFIGS + 1)
    b[-1] = 1.0
    w = torch.linalg.lstsq(A.cpu(), b.cpu()[:, None]).solution[:, 0].clamp(min=0).to(F.device)
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
    mass (above ``NEGLIGIBLE_MASS``) plus the arrivals' reach; ``gmres`` solves
    (I − P_πᵀ + 11ᵀ/S)·μ = 1/S (SciPy's restarted GMRES, relative residual ``GMRES_RTOL``, at
    most ``GMRES_MAX_MATVECS`` products; CPU), several times faster when the chain mixes slowly;
    ``auto`` steps the chain ``AUTO_POWER_STEPS`` times, then (on CPU) hands the iterate to GMRES,
    and goes on stepping if GMRES does not converge. Assumes one recurrent class, as
    ``irdrc.core.solve.stationary_distribution``."""
    if method not in ("auto", "gmres", "power"):
        raise ValueError(f"method={method!r} must be auto, gmres or power")
    p = _p_radar(model, policy)
    rows = p.reshape(-1, NUM_FACTOR_CONFIGS)
    if method == "power" or (method == "auto" and model.device.type != "cpu"):
        return _stationary_power(model, rows, tol, max_iter)
    start, steps = None, 0
    if method == "auto":
        start, steps, done = _stationary_power(model, rows, tol, AUTO_POWER_STEPS, partial=True)
        if done:
            return start, steps
    mu, calls = _stationary_gmres(model, p, start)
    if mu is not None:
        return mu, steps + calls
    if method == "gmres":
        raise RuntimeError("GMRES did not converge on this chain; use method='power'")
    mu, more = _stationary_power(model, rows, tol, max_iter, start=start)
    return mu, steps + calls + more


def _stationary_gmres(
    model: FactoredModel, p: torch.Tensor, start: torch.Tensor | None = None
) -> tuple[torch.Tensor | None, int]:
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

    if start is None:
        start = torch.zeros(S, dtype=torch.float64)
        d0 = _start_queue(model, pc.reshape(-1, NUM_FACTOR_CONFIGS))
        start[d0 * NUM_FACTOR_CONFIGS : (d0 + 1) * NUM_FACTOR_CONFIGS] = 1.0 / NUM_FACTOR_CONFIGS
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
        X = torch.zeros(D1, NUM_FACTOR_CONFIGS, dtype=torch.float64, device=model.device)
        X[_start_queue(model, p)] = 1.0 / NUM_FACTOR_CONFIGS
    else:
        X = start.reshape(D1, NUM_FACTOR_CONFIGS).clone()
    reach = model.pmf.shape[0] + 1  # how far up the queue one step can carry mass
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
    model: FactoredModel, policy: torch.Tensor, tol: float = 1e-13
) -> Metrics:
    """Exact long-run metrics of a stationary policy ([S] actions or [S, 2] probabilities), the
    factored counterpart of ``irdrc.core.solve.stationary_metrics``."""
    p = _p_radar(model, policy)
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
    )
