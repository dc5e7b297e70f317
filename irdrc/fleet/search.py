"""The best decentralised policy search finds: how far own-observation policies can go.

With own observations (``env.observe=own``) each vehicle sees its own state and the shared road and
weather, not the others' queues, so the centralised optimum may be out of reach of any policy the
vehicles can execute. The policies here are deterministic, one table per vehicle over its own
single-vehicle state ([N, S]); every value is the fleet's exact long-run average reward.

- ``ascend_tables``: first-order improvement. At the current tables one solve gives the stationary
  distribution d and the differential values h of the joint chain, hence Q(s, a) = R + E[h]; the
  exact derivative of the fleet's reward along "vehicle i switches its action in its own state o"
  (randomising that entry) is Σ_{s: o_i(s) = o} d(s)·(Q(s, a ⊕ i) − Q(s, a)). Every entry with a
  positive derivative is switched at once; if that does not raise the exact reward, the better
  half by derivative is tried, and so on down to the single best entry.
- ``improve_tables``: exact local search — each single entry switched and evaluated exactly, kept
  when it raises the reward, until a whole sweep changes nothing: its result is a local optimum of
  the decentralised policies (no single change of either table improves it).

``best_decentralised`` runs both from many starts and keeps the best.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from irdrc.core.exact.krylov import MAX_RESTARTS, RESTART, krylov_solve, stationary_krylov
from irdrc.fleet.model import FleetModel
from irdrc.fleet.policies import joint_policy

TOL = 1e-12
"""Relative tolerance of the exact solves, and the least relative gain a search step keeps."""


@dataclass(frozen=True)
class SearchResult:
    """``tables`` [N, S] the local optimum, its fleet ``reward``, the start's ``start_reward``,
    ``flips`` kept, ``sweeps`` run, ``evaluations`` and ``seconds``."""

    tables: torch.Tensor
    reward: float
    start_reward: float
    flips: int
    sweeps: int
    evaluations: int
    seconds: float


class Chain:
    """The joint chain of decentralised tables on ``model``: its stationary distribution, gain and
    differential values, each solve warm-started from the last.

    Both are linear systems in the chain's operator, solved by GMRES to ``TOL``: with v uniform,
    the stationary x solves x(I − P + 1vᵀ) = vᵀ, and the differential values h solve
    (I − P + 1vᵀ)h = r − g·1 (h up to a constant, which no derivative reads). Power iteration, the
    obvious alternative, never converges on a periodic chain (two vehicles taking turns on one
    channel can make one) and crawls on a slowly mixing one; a solve that does not reach ``TOL`` is
    finished by power iteration on the lazy chain (x + xP)/2, which has the same stationary law and
    no period.
    """

    def __init__(self, model: FleetModel) -> None:
        self.model = model
        S = model.num_states
        self.owner = model.vehicle_states()  # [S_fleet, N]: each vehicle's own state
        self.x = torch.full((S,), 1.0 / S, dtype=torch.float64)
        self.h = torch.zeros(S, dtype=torch.float64)

    def joint(self, tables: torch.Tensor) -> torch.Tensor:
        """[S_fleet] the joint actions of ``tables`` [N, S]."""
        return joint_policy(self.model, tables.reshape(-1))

    def value(self, tables: torch.Tensor, max_iter: int = 100_000) -> float:
        """The fleet's exact long-run average reward of ``tables`` (see the class docstring)."""
        model, pol = self.model, self.joint(tables)
        probs = torch.nn.functional.one_hot(pol, model.num_actions).to(torch.float64)
        weights = model.weights(probs)
        x, _ = stationary_krylov(
            lambda y: model.step(y, weights), self.x, tol=TOL, max_iter=max_iter
        )
        self.x = x
        return float(x @ model.R.gather(0, pol[None])[0])

    def derivatives(self, tables: torch.Tensor) -> torch.Tensor:
        """[N, S] the exact derivative of the reward along each entry's switch (module docstring)."""
        model, pol = self.model, self.joint(tables)
        g = self.value(tables)
        r = model.R.gather(0, pol[None])[0]
        v = torch.full_like(r, 1.0 / r.numel())

        def apply(y: torch.Tensor) -> torch.Tensor:
            return y - model.expect(y).gather(0, pol[None])[0] + (v @ y)

        self.h, _, _ = krylov_solve(
            apply, r - g, self.h, rtol=TOL, restart=RESTART, maxiter=MAX_RESTARTS
        )
        Q = model.R + model.expect(self.h)  # [A, S]
        now = Q.gather(0, pol[None])[0]
        out = torch.zeros(tables.shape, dtype=torch.float64)
        for i in range(model.N):
            switched = Q.gather(0, (pol ^ (1 << i))[None])[0]
            out[i].scatter_add_(0, self.owner[:, i], self.x * (switched - now))
        return out


def ascend_tables(
    model: FleetModel, tables: torch.Tensor, *, max_steps: int = 10_000
) -> SearchResult:
    """First-order improvement of ``tables`` [N, S] (or [S], every vehicle alike) until no entry
    with a positive derivative raises the exact reward (module docstring)."""
    S, N = model.single.num_states, model.N
    t = torch.as_tensor(tables).long().reshape(-1, S).expand(N, S).clone()
    chain, start = Chain(model), time.perf_counter()
    best = start_reward = chain.value(t)
    flips = evaluations = steps = 0
    while steps < max_steps:
        steps += 1
        grad = chain.derivatives(t)
        order = grad.reshape(-1).argsort(descending=True)
        k = int((grad.reshape(-1) > TOL * max(1.0, abs(best))).sum())
        improved = False
        while k >= 1:
            trial = t.clone().reshape(-1)
            trial[order[:k]] ^= 1
            v = chain.value(trial.reshape(N, S))
            evaluations += 1
            if v > best + TOL * max(1.0, abs(best)):
                t, best, flips, improved = trial.reshape(N, S), v, flips + k, True
                break
            k //= 2
        if not improved:
            break
    return SearchResult(
        t, best, start_reward, flips, steps, evaluations, time.perf_counter() - start
    )


def improve_tables(
    model: FleetModel,
    tables: torch.Tensor,
    *,
    max_sweeps: int = 10,
    progress: Callable[[int, float, int], None] | None = None,
) -> SearchResult:
    """Exact local search over per-vehicle tables (see the module docstring); ``tables`` is [S]
    (every vehicle the same) or [N·S]; ``progress(sweep, reward, flips)`` after each sweep."""
    S, N = model.single.num_states, model.N
    t = torch.as_tensor(tables).long().reshape(-1, S).expand(N, S).clone()
    chain, start = Chain(model), time.perf_counter()
    best = start_reward = chain.value(t)
    flips = evaluations = sweeps = 0
    for sweeps in range(1, max_sweeps + 1):
        changed = 0
        for i in range(N):
            for s in range(S):
                t[i, s] ^= 1
                v = chain.value(t)
                evaluations += 1
                if v > best + TOL * max(1.0, abs(best)):
                    best, changed = v, changed + 1
                else:
                    t[i, s] ^= 1
        flips += changed
        if progress is not None:
            progress(sweeps, best, changed)
        if not changed:
            break
    return SearchResult(
        t, best, start_reward, flips, sweeps, evaluations, time.perf_counter() - start
    )


@dataclass(frozen=True)
class BestFound:
    """The best decentralised policy found from several starts: its ``tables`` [N, S], exact
    ``reward``, the ``start`` it came from, and every start's (name, start reward, end reward)."""

    tables: torch.Tensor
    reward: float
    start: str
    runs: list[tuple[str, float, float]]


def best_decentralised(
    model: FleetModel,
    starts: Sequence[tuple[str, torch.Tensor]],
    *,
    certify: bool = True,
    progress: Callable[[str, SearchResult], None] | None = None,
) -> BestFound:
    """``ascend_tables`` from every named start, then (``certify``) ``improve_tables`` from the
    best end: a local optimum no single switch improves."""
    runs, best = [], None
    for name, tables in starts:
        res = ascend_tables(model, tables)
        runs.append((name, res.start_reward, res.reward))
        if progress is not None:
            progress(name, res)
        if best is None or res.reward > best[1].reward:
            best = (name, res)
    assert best is not None, "no start given"
    name, res = best
    if certify:
        res = improve_tables(model, res.tables)
        if progress is not None:
            progress(f"{name}, every single switch", res)
    return BestFound(res.tables, res.reward, name, runs)
