"""Linear solves on operators that are never built as matrices (restarted GMRES, SciPy's), and the
stationary distribution of a chain as one such solve.

The stationary x of a chain with step x ↦ x·P solves x(I − P + 1vᵀ) = vᵀ for any v with vᵀ1 = 1
(here v uniform): the rank-one term pins the scale that I − P leaves free. On a slowly mixing chain
(a fleet's queues, each waiting on the other's uplink) GMRES needs tens of operator products where
power iteration needs hundreds; a solve that does not reach its tolerance is finished by power
iteration on the lazy chain (x + x·P)/2, which has the same stationary law and no period.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

Operator = Callable[[torch.Tensor], torch.Tensor]


def krylov_solve(
    apply: Operator, rhs: torch.Tensor, x0: torch.Tensor, *, rtol: float, restart: int, maxiter: int
) -> tuple[torch.Tensor, bool, int]:
    """Solve ``apply(y) = rhs`` by GMRES restarted every ``restart`` products, at most ``maxiter``
    restarts, from ``x0`` (CPU float64). Returns (y, whether the relative residual reached
    ``rtol``, operator products)."""
    import numpy as np
    from scipy.sparse.linalg import LinearOperator, gmres

    n = rhs.numel()
    calls = 0

    def matvec(y: np.ndarray) -> np.ndarray:
        nonlocal calls
        calls += 1
        return apply(
            torch.from_numpy(np.ascontiguousarray(y, dtype=np.float64).reshape(-1))
        ).numpy()

    op = LinearOperator((n, n), matvec=matvec, dtype=np.float64)
    y, info = gmres(
        op, rhs.numpy(), x0=x0.numpy(), rtol=rtol, atol=0.0, restart=restart, maxiter=maxiter
    )
    return torch.from_numpy(y), info == 0, calls


STATIONARY_RTOL = 1e-12
"""Relative residual at which a stationary solve stops (the fleet's joint chains: L1 residual
‖x·P − x‖ ≈ 1e-13 at 30 976 – 952 576 states)."""
RESTART, MAX_RESTARTS = 60, 400
"""GMRES's restart length and most restarts per stationary solve."""


def stationary_krylov(
    step: Operator, start: torch.Tensor, *, tol: float = STATIONARY_RTOL, max_iter: int = 100_000
) -> tuple[torch.Tensor, int]:
    """The stationary distribution of the chain ``step`` (x ↦ x·P, linear) from ``start`` (module
    docstring): GMRES to ``STATIONARY_RTOL``, finished if need be by at most ``max_iter`` lazy
    power steps until the L1 change is below ``tol``. Returns (x, operator products)."""
    v = torch.full_like(start, 1.0 / start.numel())
    x, ok, calls = krylov_solve(
        lambda y: y - step(y) + v * y.sum(),
        v,
        start,
        rtol=STATIONARY_RTOL,
        restart=RESTART,
        maxiter=MAX_RESTARTS,
    )
    x = x.clamp_min(0.0)
    x = x / x.sum()
    if ok:
        return x, calls
    for _ in range(max_iter):
        nxt = 0.5 * (x + step(x))
        nxt = nxt / nxt.sum()
        calls += 1
        if float((nxt - x).abs().sum()) < tol:
            return nxt, calls
        x = nxt
    raise RuntimeError(
        f"the stationary distribution did not converge: GMRES, then {max_iter} lazy power steps"
    )
