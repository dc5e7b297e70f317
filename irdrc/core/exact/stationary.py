"""Stationary distributions on the factored operator (``irdrc.core.exact.factored``), fast for deep
queues: power iteration over the queue lengths that hold mass, aggregation-disaggregation over the
queue length (its rounds extrapolated), and GMRES. Every ``model`` here is a factored model
(``irdrc.core.exact.factored.FactoredModel``, which calls in here); ``FactoredChain`` names what
these solvers read of it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Protocol

import torch

from irdrc.core.exact.banded import banded_stationary, product_stationary
from irdrc.core.exact.krylov import krylov_solve
from irdrc.core.exact.mdp import as_probs, power_cycle


class FactoredChain(Protocol):
    """What these solvers read of a factored model (``irdrc.core.exact.factored.FactoredModel``)."""

    @property
    def num_states(self) -> int: ...

    @property
    def num_actions(self) -> int: ...

    @property
    def num_configs(self) -> int: ...

    @property
    def device(self) -> torch.device: ...

    @property
    def F(self) -> torch.Tensor: ...

    @property
    def pmf(self) -> torch.Tensor: ...

    @property
    def per_config(self) -> dict[str, torch.Tensor]: ...

    @property
    def group(self) -> torch.Tensor: ...

    @property
    def sent_q(self) -> torch.Tensor: ...

    @property
    def dropped_q(self) -> torch.Tensor: ...

    @property
    def cols(self) -> tuple[tuple[tuple[slice | torch.Tensor, int, int], ...], ...]: ...

    def step(self, x: torch.Tensor, probs: torch.Tensor) -> torch.Tensor: ...

    def step_rows(self, X: torch.Tensor, probs: torch.Tensor) -> torch.Tensor: ...


NEGLIGIBLE_MASS = 1e-30
"""Queue lengths holding less stationary mass than this (summed over the factors) are stepped only
within a few steps' reach of the mass: above and below it by the power steps, above it by the
aggregation rounds (below what any metric resolves)."""
GMRES_RTOL = 1e-12
"""Relative residual at which the GMRES solve for a stationary distribution stops (its L1 error
against power iteration to 1e-13 was ≈ 1e-10 on the persistent, deep-queue scenario)."""
GMRES_MAX_MATVECS = 3000
"""GMRES gives up after this many operator products (and power iteration takes over)."""
AUTO_POWER_STEPS = 300
"""``method="auto"``: power steps at most before aggregation (a fast-mixing chain has converged by
then)."""
SLOW_CHECK = 10
"""``method="auto"``: every this many power steps (from twice as many on), the L1 change's decay over
the last ones predicts the steps still needed; when they would not fit in ``AUTO_POWER_STEPS``,
aggregation takes over at once (power steps before it hardly shorten it)."""
IAD_MAX_ITER = 5000
"""``method="auto"``: aggregation-disaggregation rounds before plain power iteration takes over."""
EXTRAPOLATE_EVERY = 5
"""Aggregation rounds between two extrapolations of their iterates (``_extrapolate``)."""


def _start_queue(model: FactoredChain, probs: torch.Tensor) -> int:
    """Where the power iteration starts: the first queue length at which the policy's expected
    drift E[d′ − d] (averaged over the factor configurations as they occur) is ≤ 0 — where the
    queue settles — or D if it grows everywhere. A deep queue then need not be crossed step by
    step. ``probs``: [D + 1, F, A]."""
    D1 = probs.shape[0]
    nf = model.num_configs
    # [A, D + 1, F]: expected packets leaving the queue (sent + dropped) per action, d, f
    out = (model.sent_q + model.dropped_q)[model.group].transpose(1, 2)
    # weight the factor configurations by how often they occur (the factor chain's stationary
    # distribution under comm; the reaction only perturbs it)
    F = model.F[0]
    A = torch.cat([F.T - torch.eye(nf, dtype=F.dtype, device=F.device), F.new_ones(1, nf)])
    b = F.new_zeros(nf + 1)
    b[-1] = 1.0
    w = torch.linalg.lstsq(A.cpu(), b.cpu()[:, None]).solution[:, 0].clamp(min=0).to(F.device)
    lam = float((model.per_config["rate"] * w).sum() / w.sum())  # mean arrivals per step
    leaving = (probs.permute(2, 0, 1) * out).sum(0)  # [D + 1, F]
    drift = lam - (leaving * w).sum(-1) / w.sum()  # [D + 1]
    settled = (drift <= 0).nonzero()
    return int(settled[0]) if settled.numel() else D1 - 1


def stationary_distribution_factored(
    model: FactoredChain,
    policy: torch.Tensor,
    tol: float = 1e-13,
    max_iter: int = 1_000_000,
    method: str = "auto",
    progress: Callable[[int, float], None] | None = None,
) -> tuple[torch.Tensor, int]:
    """The stationary distribution of a stationary policy ([S] actions or [S, A] probabilities) on
    the factored operator. Returns (μ [S], operator applications).

    ``method``: ``power`` steps the chain until the L1 change of a step is below ``tol``, from where
    the policy's queue settles (``_start_queue``) and only over the queue lengths that hold mass
    (above ``NEGLIGIBLE_MASS``) and a few steps' reach around them (``_window``: a queue that stays
    full is stepped near D alone); ``iad`` alternates one step (from d = 0) with an exact solve of
    the queue-length chain aggregated over the factors (``_stationary_iad``), so the queue — the
    slow part of a deep buffer — settles in one round and the rounds needed are set by the factors'
    mixing, cut by extrapolating every ``EXTRAPOLATE_EVERY`` rounds (``large``: 70–120 rounds);
    ``gmres`` solves (I − P_πᵀ + 11ᵀ/S)·μ = 1/S (SciPy's restarted GMRES, relative residual
    ``GMRES_RTOL``, at most ``GMRES_MAX_MATVECS`` products; CPU); ``auto`` steps the chain up to
    ``AUTO_POWER_STEPS`` times — fewer when the change's decay says that would not converge
    (``SLOW_CHECK``) — then hands the iterate to ``iad`` (at most ``IAD_MAX_ITER`` rounds) and goes
    on stepping if that does not converge. The operator applications returned count one per power
    step or round; ``progress(step, change)`` is called after each. Assumes one recurrent class."""
    if method not in ("auto", "gmres", "iad", "power"):
        raise ValueError(f"method={method!r} must be auto, gmres, iad or power")
    probs = as_probs(policy, model.num_states, model.num_actions).to(model.device)
    rows = probs.reshape(-1, model.num_configs, model.num_actions)
    if method == "power":
        return _stationary_power(model, rows, tol, max_iter, progress=progress)
    if method == "gmres":
        mu, calls = _stationary_gmres(model, rows)
        if mu is None:
            raise RuntimeError("GMRES did not converge on this chain; use method='power'")
        return mu, calls
    if method == "iad":
        mu, calls, done = _stationary_iad(model, rows, tol, max_iter, progress=progress)
        if not done:
            raise RuntimeError(f"the stationary distribution did not converge in {max_iter} rounds")
        return mu, calls
    start, steps, done = _stationary_power(
        model, rows, tol, AUTO_POWER_STEPS, partial=True, progress=progress, give_up=True
    )
    if done:
        return start, steps
    mu, calls, done = _stationary_iad(
        model, rows, tol, IAD_MAX_ITER, start=start, progress=progress
    )
    if done:
        return mu, steps + calls
    mu, more = _stationary_power(model, rows, tol, max_iter, start=mu, progress=progress)
    return mu, steps + calls + more


def _initial(model: FactoredChain, probs: torch.Tensor, start: torch.Tensor | None) -> torch.Tensor:
    """The iterate to start from: ``start``, or uniform over the factors where the queue settles."""
    D1, nf = probs.shape[:2]
    if start is not None:
        return start.reshape(D1, nf).clone()
    X = torch.zeros(D1, nf, dtype=torch.float64, device=model.device)
    X[_start_queue(model, probs)] = 1.0 / nf
    return X


def _advance(
    X: torch.Tensor, Y: torch.Tensor, it: int, progress: Callable[[int, float], None] | None
) -> tuple[torch.Tensor, float]:
    """One power step's result ``Y`` normalised, and its L1 change from ``X`` (reported to
    ``progress`` with the step's number)."""
    Y = Y / Y.sum()
    change = float((Y - X).abs().sum())
    if progress is not None:
        progress(it, change)
    return Y, change


def _stationary_iad(
    model: FactoredChain,
    probs: torch.Tensor,
    tol: float,
    max_iter: int,
    start: torch.Tensor | None = None,
    progress: Callable[[int, float], None] | None = None,
) -> tuple[torch.Tensor, int, bool]:
    """Iterative aggregation-disaggregation (Koury, McAllister and Stewart) over the queue length.
    Each round: one power step X → X·P_π (stop when its L1 change is below ``tol``); the factors'
    conditional distribution given d, c(f | d) = X[d, f] / Σ_f X[d, f]; the aggregated chain on
    d alone, A[d, d′] = Σ_{a, f} c(f | d)·π(a | d, f)·P(d′ | d, ν(a, f), arrivals of f) — exact for
    the true μ, since the factors' next value does not enter d′ — solved for its stationary α
    exactly (``banded_stationary``: d′ − d lies between −ν and the arrivals kept); then
    X = α(d)·c(f | d); every ``EXTRAPOLATE_EVERY`` rounds X is extrapolated from the last three
    (``_extrapolate``). Both work on the queue lengths from 0 to the top of those that hold mass
    (above ``NEGLIGIBLE_MASS``) plus twice the arrivals' reach (``_window``'s top).
    Returns (μ [S], rounds, converged)."""
    path, rounds, done = _cycle_iad(model, [probs], tol, max_iter, start, progress)
    return path[0], rounds, done


def _cycle_iad(
    model: FactoredChain,
    phases: list[torch.Tensor],
    tol: float,
    max_iter: int,
    start: torch.Tensor | None = None,
    progress: Callable[[int, float], None] | None = None,
) -> tuple[list[torch.Tensor], int, bool]:
    """``_stationary_iad`` for a periodic policy (``phases``: one [D + 1, F, A] table per step,
    applied in turn). A round steps X₀ through one whole period (X₁ … X_k; stop when X_k is within
    ``tol`` of X₀), aggregates each phase j on its own conditional c_j (c₀ from X_k), and solves the
    product of the phases' aggregated chains, A₀·A₁ ⋯ A_{k−1}, for the queue's marginal α₀ at phase
    0 — exact for the true measures, since α_{j+1} = α_j·A_j — then X₀ = α₀(d)·c₀(f | d),
    extrapolated every ``EXTRAPOLATE_EVERY`` rounds. Returns (the measure [S] at each phase,
    rounds, converged)."""
    import numpy as np

    probs = phases[0]
    nf = probs.shape[1]
    chain: tuple[int, list[Any], Any, Any] = (0, [], None, None)  # n, and its queue chain
    X = _initial(model, probs, start)
    uniform = torch.full_like(X, 1.0 / nf)
    recent: list[torch.Tensor] = []  # the last rounds' iterates, for ``_extrapolate``
    for it in range(1, max_iter + 1):
        # from d = 0 up to the window's top: the aggregated solve puts mass below its floor
        n = _window(model, X, len(phases))[1]
        path = [X]
        for p in phases[:-1]:
            path.append(_step_window(model, path[-1], p, 0, n))
        step = _step_window(model, path[-1], phases[-1], 0, n, False)
        X, change = _advance(X, step, it, progress)
        path[0] = X
        if change < tol:
            return [x.reshape(-1) for x in path], it, True
        if chain[0] != n:
            chain = (n, *_queue_chain(model, n))
        _, parts, src_all, dst_all = chain
        conds, kernels = [], []
        for x, p in zip(path, phases, strict=True):
            mass = x[:n].sum(1, keepdim=True)
            cond = torch.where(mass > 0, x[:n] / mass.clamp(min=1e-300), uniform[:n])
            vals = []
            for a, cols, src, pmf in parts:
                w = (cond[:, cols] * p[:n, cols, a]).sum(1).cpu().numpy()
                vals.append(w[src] * pmf)
            conds.append(cond)
            kernels.append(np.concatenate(vals))
        if len(phases) == 1:
            alpha = banded_stationary(src_all, dst_all, kernels[0], n)
        else:
            alpha = product_stationary(src_all, dst_all, kernels, n)
        X = torch.zeros_like(X)
        X[:n] = torch.from_numpy(alpha).to(X.device)[:, None] * conds[0]
        recent = [*recent[-2:], X]
        if it % EXTRAPOLATE_EVERY == 0 and len(recent) == 3:
            X, recent = _extrapolate(*recent), []
    return [x.reshape(-1) for x in path], max_iter, False


def _extrapolate(x0: torch.Tensor, x1: torch.Tensor, x2: torch.Tensor) -> torch.Tensor:
    """Where three successive iterates head if their error keeps shrinking by one factor r a round
    (Aitken's extrapolation along the last difference): x2 + r/(1 − r)·(x2 − x1), r fitted by least
    squares to the last two differences, clipped at 0 and normalised; x2 itself unless 0 < r < 1.
    The aggregation rounds' error decays geometrically at the factors' mixing rate, so this skips
    rounds (``large``: a third to three fifths of them); the rounds that follow correct what it
    misses."""
    d0, d1 = x1 - x0, x2 - x1
    r = float((d1 * d0).sum() / (d0 * d0).sum().clamp(min=1e-300))
    if not 0.0 < r < 1.0:
        return x2
    y = (x2 + r / (1.0 - r) * d1).clamp(min=0.0)
    return y / y.sum()


def _window(model: FactoredChain, X: torch.Tensor, steps: int) -> tuple[int, int]:
    """The queue lengths [lo, hi) that ``steps`` chain steps from X [D + 1, F] work on: those
    holding mass (above ``NEGLIGIBLE_MASS``) and twice as far as those steps can carry it, down
    (the most packets a step sends) and up (the arrivals kept). The queue's dynamics do not depend
    on d away from 0 and D, so the window's own edges move only the mass left outside it."""
    D1 = X.shape[0]
    held = (X.sum(1) > NEGLIGIBLE_MASS).nonzero()
    if not held.numel():
        return 0, D1
    down = steps * (max(nu for cols in model.cols for _, nu, _ in cols) + 1)
    up = steps * (model.pmf.shape[-1] + 1)
    return max(0, int(held.min()) - 2 * down), min(D1, int(held.max()) + 1 + 2 * up)


def _step_window(
    model: FactoredChain,
    X: torch.Tensor,
    probs: torch.Tensor,
    lo: int,
    hi: int,
    normalise: bool = True,
) -> torch.Tensor:
    """One chain step of X [D + 1, F] over the queue lengths [lo, hi) (``_window``), normalised
    unless ``normalise`` is False."""
    Y = torch.zeros_like(X)
    Y[lo:hi] = model.step_rows(X[lo:hi], probs[lo:hi])
    return Y / Y.sum() if normalise else Y


def _queue_chain(model: FactoredChain, n: int) -> tuple[list[Any], Any, Any]:
    """The queue-length chain's entries on 0 … n − 1 (clamped at n − 1) per (action, queue
    dynamics): ([(action, its columns, src, P)], every src, every dst) for ``_cycle_iad``."""
    import numpy as np

    d = np.arange(n)
    parts, srcs, dsts = [], [], []
    for a in range(model.num_actions):
        for cols, nu, row in model.cols[a]:
            pmf = model.pmf[row].cpu().numpy()
            K = pmf.shape[0]
            src = np.repeat(d, K)
            srcs.append(src)
            dsts.append(np.clip(src + np.tile(np.arange(K), n) - nu, 0, n - 1))
            parts.append((a, cols, src, np.tile(pmf, n)))
    return parts, np.concatenate(srcs), np.concatenate(dsts)


def stationary_cycle_factored(
    model: FactoredChain, schedule: list[torch.Tensor], tol: float = 1e-13, max_iter: int = 200_000
) -> list[torch.Tensor]:
    """The stationary distribution at each phase of a periodic policy (``schedule``: one [S] action
    table or [S, A] probabilities per step, applied in turn) on the factored operator: by
    aggregation-disaggregation over whole periods (``_cycle_iad``; at most ``IAD_MAX_ITER``
    rounds), then power iteration over whole periods if that has not converged. Assumes one
    recurrent class."""
    S, A, nf = model.num_states, model.num_actions, model.num_configs
    phases = [as_probs(p, S, A).to(model.device).reshape(-1, nf, A) for p in schedule]
    path, _, done = _cycle_iad(model, phases, tol, min(max_iter, IAD_MAX_ITER))
    if done:
        return path
    return power_cycle(model.step, [p.reshape(S, A) for p in phases], path[0], tol, max_iter)


def _stationary_gmres(model: FactoredChain, probs: torch.Tensor) -> tuple[torch.Tensor | None, int]:
    S = model.num_states
    pc = probs.cpu().reshape(S, -1)
    start = _initial(model, probs.cpu(), None).reshape(-1)
    b = torch.full((S,), 1.0 / S, dtype=torch.float64)
    x, ok, calls = krylov_solve(
        lambda y: y - model.step(y, pc) + y.sum() / S,
        b,
        start.cpu(),
        rtol=GMRES_RTOL,
        restart=100,
        maxiter=GMRES_MAX_MATVECS // 100,
    )
    if not ok or float(x.min()) < -1e-9 * float(x.abs().max()):
        return None, calls
    mu = x.clamp_min(0.0)
    return (mu / mu.sum()).to(model.device), calls


def _stationary_power(
    model: FactoredChain,
    probs: torch.Tensor,
    tol: float,
    max_iter: int,
    start: torch.Tensor | None = None,
    partial: bool = False,
    progress: Callable[[int, float], None] | None = None,
    give_up: bool = False,
) -> tuple[Any, ...]:
    """Power iteration (see ``stationary_distribution_factored``). Returns (μ, steps), or with
    ``partial`` (μ, steps, converged) instead of raising when ``max_iter`` steps do not converge;
    with ``give_up`` (and ``partial``) it stops early when the change's decay over the last
    ``SLOW_CHECK`` steps predicts more steps to ``tol`` than ``max_iter`` leaves."""
    X = _initial(model, probs, start)
    before = math.inf
    for it in range(1, max_iter + 1):
        lo, hi = _window(model, X, 1)
        X, change = _advance(X, _step_window(model, X, probs, lo, hi, False), it, progress)
        if change < tol:
            return (X.reshape(-1), it, True) if partial else (X.reshape(-1), it)
        if give_up and it % SLOW_CHECK == 0:
            if it >= 2 * SLOW_CHECK and _steps_to(tol, change, before, SLOW_CHECK) > max_iter - it:
                return X.reshape(-1), it, False
            before = change
    if partial:
        return X.reshape(-1), max_iter, False
    raise RuntimeError(f"the stationary distribution did not converge in {max_iter} steps")


def _steps_to(tol: float, change: float, before: float, steps: int) -> float:
    """The power steps still needed to bring the L1 change from ``change`` to ``tol`` if it keeps
    decaying geometrically as it did from ``before`` over the last ``steps`` (inf if it did not)."""
    if not before > change:
        return math.inf
    return steps * math.log(tol / change) / math.log(change / before)
