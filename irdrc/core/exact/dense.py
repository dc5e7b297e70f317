"""The exact model of MODEL.md with its transition tensor P[a, s, s′] in memory, in float64: the
cross-check of every other model on small state spaces.

Built from the same per-configuration tables as the simulator (``irdrc.core.tables``: the factor
chains as a Kronecker product, events, rewards), with the queue summed over Poisson arrivals exactly
here rather than sampled, so comparing the two catches a bug in either's queue or sampling. State
indexing is the one of ``irdrc.core.dynamics``: s = d·F + f (v1: s = d·32 + c·16 + r·8 + w·4 + v·2 + m).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import torch

from irdrc.core.exact.mdp import ExactMDP
from irdrc.core.params import Params

DENSE_MAX_STATES = 8192
"""The largest S the dense model is built for (2·S² float64: 1 GiB). Recipes stop earlier, at
``irdrc.core.sizes.DENSE_LIMIT_BYTES``."""


@dataclass(frozen=True, eq=False)
class DenseModel(ExactMDP):
    """Transition and expectation tensors of the MDP (float64; A actions, S = (D + 1)·Π L states).

    Attributes:
        params: the parameters it was built from.
        P: [A, S, S] transition probabilities P[a, s, s′].
        R: [A, S] expected reward of action a in state s.
        event: [S] probability of an unexpected event during a step from s (any action).
        missed, false_alarms: [A, S] expected missed events and radar false alarms.
        sent, dropped, capacity: [A, S] expected packets sent, dropped, and link capacity ν.
        queue: [S] queue length d of each state.
        radar: [A] share of the step in radar mode (v1: 0 for comm, 1 for radar).
    """

    params: Params
    P: torch.Tensor
    R: torch.Tensor
    event: torch.Tensor
    missed: torch.Tensor
    false_alarms: torch.Tensor
    sent: torch.Tensor
    dropped: torch.Tensor
    capacity: torch.Tensor
    queue: torch.Tensor
    radar: torch.Tensor

    @property
    def num_actions(self) -> int:
        """A."""
        return int(self.P.shape[0])

    @property
    def num_states(self) -> int:
        """S = (D + 1)·Π L (v1: (D + 1)·32)."""
        return int(self.P.shape[-1])

    def expect(self, V: torch.Tensor) -> torch.Tensor:
        """[A, S]: P V per action."""
        return self.P @ V

    def chain(self, probs: torch.Tensor) -> torch.Tensor:
        """[S, S] the transition matrix under action probabilities ``probs`` [S, A]."""
        terms = (probs[:, a, None] * self.P[a] for a in range(self.num_actions))
        return cast(torch.Tensor, sum(terms))

    def step(self, x: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
        """x·P_π."""
        return x @ self.chain(probs)

    def cycle(
        self, schedule: Sequence[torch.Tensor], tol: float = 1e-13, max_iter: int = 200_000
    ) -> list[torch.Tensor]:
        """The stationary distribution at each phase of ``schedule``, exactly: that of the product
        of one period's chains, then stepped through the phases."""
        chains = [self.chain(p) for p in schedule]
        product = chains[0]
        for ch in chains[1:]:
            product = product @ ch
        mu = stationary_distribution(product)
        path = []
        for ch in chains:
            path.append(mu)
            mu = mu @ ch
        return path

    def sparse(self, a: int) -> Any:
        """P_a as a SciPy CSR matrix."""
        from scipy import sparse

        return sparse.csr_matrix(self.P[a].numpy())

    def nonzeros(self, a: int) -> int:
        """The non-zeros of ``sparse(a)``: P_a's entries that are not 0."""
        return int(torch.count_nonzero(self.P[a]))


def stationary_distribution(P: torch.Tensor) -> torch.Tensor:
    """μ with μ P = μ, Σμ = 1: one LU solve of (P^T − I) with its last equation replaced by
    Σμ = 1, or, where that system is singular, a least-squares solve of the stacked system.

    Assumes the chain has a single recurrent class (true whenever every factor chain mixes, as
    with the defaults); raises if the solution is not a distribution to 1e-8.
    """
    n = P.shape[0]
    b = torch.zeros(n, dtype=P.dtype)
    b[-1] = 1.0
    A = P.T - torch.eye(n, dtype=P.dtype)
    A[-1] = 1.0
    mu, info = torch.linalg.solve_ex(A, b)
    if int(info) != 0 or not bool(torch.isfinite(mu).all()) or not _is_stationary(mu, P):
        A = torch.cat([P.T - torch.eye(n, dtype=P.dtype), torch.ones(1, n, dtype=P.dtype)])
        rhs = torch.cat([torch.zeros(n, dtype=P.dtype), torch.ones(1, dtype=P.dtype)])
        mu = torch.linalg.lstsq(A, rhs[:, None], driver="gelsd").solution[:, 0]
    if not _is_stationary(mu, P):
        raise RuntimeError("the chain has no unique stationary distribution")
    return mu.clamp(min=0) / mu.clamp(min=0).sum()


def _is_stationary(mu: torch.Tensor, P: torch.Tensor) -> bool:
    """Whether ``mu`` is a distribution invariant under ``P``, to 1e-8."""
    return not bool((mu < -1e-8).any()) and float((mu @ P - mu).abs().max()) <= 1e-8


def _poisson_pmf(rate: float, k: int) -> float:
    if rate == 0.0:
        return 1.0 if k == 0 else 0.0
    return math.exp(k * math.log(rate) - rate - math.lgamma(k + 1))


def _queue_tables(
    D: int, pairs: dict[tuple[int, float], int]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For each (ν, λ): the distribution of d′ [D + 1, D + 1] and the expected sent and dropped
    [D + 1], summed over A = 0 … K−1 exactly plus a tail bucket A ≥ K, where K = D + max ν + 1 makes
    every tail outcome identical (sent = ν, d′ = D) except the drop, whose tail expectation is
    exact: E[A; A ≥ K] = λ·P(A ≥ K − 1)."""
    G = len(pairs)
    K = D + max(nu for nu, _ in pairs) + 1
    q_next = torch.zeros(G, D + 1, D + 1, dtype=torch.float64)  # [(ν, λ), d, d′]
    q_sent = torch.zeros(G, D + 1, dtype=torch.float64)
    q_drop = torch.zeros(G, D + 1, dtype=torch.float64)
    for (nu, lam), i in pairs.items():
        pmf = [_poisson_pmf(lam, k) for k in range(K)]
        tail = max(0.0, 1.0 - sum(pmf))  # P(A ≥ K)
        tail_prev = max(0.0, 1.0 - sum(pmf[: K - 1]))  # P(A ≥ K − 1)
        for dd in range(D + 1):
            for k, pk in enumerate(pmf):
                rest = max(0, dd + k - nu)
                dn = min(D, rest)
                q_next[i, dd, dn] += pk
                q_sent[i, dd] += pk * min(dd + k, nu)
                q_drop[i, dd] += pk * (rest - dn)
            q_next[i, dd, D] += tail
            q_sent[i, dd] += tail * nu
            q_drop[i, dd] += (dd - nu - D) * tail + lam * tail_prev
    return q_next, q_sent, q_drop


def build_model(params: Params, shares: Any = None) -> DenseModel:
    """The exact MDP of ``params`` (see ``DenseModel``), for the general model of MODEL.md § B too,
    with one action per radar share of ``shares`` (default ``params.env.shares``: v1's comm and
    radar, or § D's levels; ``continuous`` needs ``shares``, e.g. ``irdrc.core.exact.continuum``'s
    nodes).

    Raises:
        ValueError: when S exceeds ``DENSE_MAX_STATES`` (use ``build_factored``).
    """
    from irdrc.core.share import share_tables

    D = params.env.queue_capacity
    st = share_tables(params, shares)
    t = st.base
    nf = t.num_configs
    S = (D + 1) * nf
    if S > DENSE_MAX_STATES:
        raise ValueError(
            f"env.queue_capacity={D}: S = {S} states is too many for the dense S × S model "
            f"(at most {DENSE_MAX_STATES}); use the factored operator (irdrc.core.exact."
            "build_factored), as recipes/solve.py does"
        )
    A = st.k.shape[0]
    s = torch.arange(S)
    d, f = s // nf, s % nf
    pairs: dict[tuple[int, float], int] = {}
    split = bool((st.p > 0).any())  # a share whose capacity is rounded at random (§ D)
    group = torch.zeros(2, A, nf, dtype=torch.int64)  # [k or k + 1, a, f] → index of its (ν, λ)
    for a in range(A):
        for g in range(nf):
            for j in range(2 if split else 1):
                key = (int(st.k[a, g]) + j, float(t.rate[g]))
                group[j, a, g] = pairs.setdefault(key, len(pairs))
    q_next, q_sent, q_drop = _queue_tables(D, pairs)

    def queue(table: torch.Tensor, a: int) -> torch.Tensor:
        """The queue table of action a on every state: capacity k, or k + 1 w.p. p."""
        lo = table[group[0, a][f], d]
        if not split:
            return lo
        p = st.p[a][f].reshape(-1, *([1] * (lo.ndim - 1)))
        return (1.0 - p) * lo + p * table[group[1, a][f], d]

    P = torch.zeros(A, S, S, dtype=torch.float64)
    for a in range(A):
        # P[a, (d, f), (d′, f′)] = Q[(ν, λ)(a, f), d, d′] · F[a, f, f′]
        qa = queue(q_next, a)  # [S, D + 1]
        P[a] = (qa[:, :, None] * st.F[a][f][:, None, :]).reshape(S, S)
    return DenseModel(
        params=params,
        P=P,
        R=st.R[:, f],
        event=t.event[f],
        missed=st.missed[:, f],
        false_alarms=st.false_alarm[:, f],
        sent=torch.stack([queue(q_sent, a) for a in range(A)]),
        dropped=torch.stack([queue(q_drop, a) for a in range(A)]),
        capacity=st.nu[:, f],
        queue=d.to(torch.float64),
        radar=st.shares.clone(),
    )
