"""The exact model of MODEL.md: P[a, s, s′], R[a, s] and per-step expectations, in float64.

Built from the same per-configuration tables as the simulator (``irdrc.core.tables``: the factor
chains as a Kronecker product, events, rewards), with the queue summed over Poisson arrivals exactly
here rather than sampled, so comparing the two catches a bug in either's queue or sampling; the
tables themselves are checked against the config and hand-computed values (tests/test_general.py,
tests/test_exact.py). State indexing is the one of ``irdrc.core.env``: s = d·F + f (v1:
s = d·32 + c·16 + r·8 + w·4 + v·2 + m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from irdrc.core.params import Params


@dataclass(frozen=True)
class ExactModel:
    """Transition and expectation tensors of the MDP (float64, S = (D + 1)·32 states).

    Attributes:
        params: the parameters it was built from.
        P: [2, S, S] transition probabilities P[a, s, s′].
        R: [2, S] expected reward of action a in state s.
        event: [S] probability of an unexpected event during a step from s (either action).
        sent, dropped, capacity: [2, S] expected packets sent, dropped, and link capacity ν.
        queue: [S] queue length d of each state.
        missed_table, false_alarm: [2, S] expected missed events and false alarms (None: v1's
            perfect radar, see ``missed`` and ``false_alarms``).
    """

    params: Params
    P: torch.Tensor
    R: torch.Tensor
    event: torch.Tensor
    sent: torch.Tensor
    dropped: torch.Tensor
    capacity: torch.Tensor
    queue: torch.Tensor
    missed_table: torch.Tensor | None = None
    false_alarm: torch.Tensor | None = None

    @property
    def num_states(self) -> int:
        """S = (D + 1)·Π L (v1: (D + 1)·32)."""
        return self.P.shape[-1]

    @property
    def missed(self) -> torch.Tensor:
        """[2, S] expected missed events: the event probability in comm mode; in radar mode the
        event probability times 1 − P_d (0 with a perfect radar)."""
        if self.missed_table is not None:
            return self.missed_table
        return torch.stack([self.event, torch.zeros_like(self.event)])

    @property
    def false_alarms(self) -> torch.Tensor:
        """[2, S] expected radar false alarms (0 in comm mode, and with P_fa = 0)."""
        if self.false_alarm is not None:
            return self.false_alarm
        return torch.zeros(2, self.num_states, dtype=torch.float64)


def _poisson_pmf(rate: float, k: int) -> float:
    if rate == 0.0:
        return 1.0 if k == 0 else 0.0
    return math.exp(k * math.log(rate) - rate - math.lgamma(k + 1))


DENSE_MODEL_LIMIT_BYTES = 2**29
"""Recipes use the dense model while its transition tensor (2·S² float64) fits in this; above it
they switch to the factored operator (``irdrc.core.factored``) or refuse."""

DENSE_MAX_STATES = 8192
"""The largest S the dense model is built for (2·S² float64: 1 GiB); larger models use the factored
operator (``irdrc.core.factored``)."""


def build_model(params: Params) -> ExactModel:
    """The exact MDP of ``params`` (see ``ExactModel``), for the general model of MODEL.md § B too.

    Raises:
        ValueError: when S exceeds ``DENSE_MAX_STATES`` (use ``irdrc.core.factored``).
    """
    from irdrc.core.tables import model_tables

    env = params.env
    D = env.queue_capacity
    t = model_tables(params)
    nf = t.num_configs
    S = (D + 1) * nf
    if S > DENSE_MAX_STATES:
        raise ValueError(
            f"env.queue_capacity={D}: S = {S} states is too many for the dense S × S model "
            f"(at most {DENSE_MAX_STATES}); use the factored operator (irdrc.core.factored."
            "build_factored), as recipes/solve.py does"
        )
    s = torch.arange(S)
    d = s // nf
    f = s % nf

    # Queue: for each (ν, λ) the distribution of d′ and expected sent / dropped, summed over
    # A = 0 … K−1 exactly plus a tail bucket A ≥ K, where K = D + max ν + 1 makes every tail
    # outcome identical (sent = ν, d′ = D) except the drop, whose tail expectation is exact:
    # E[A; A ≥ K] = λ·P(A ≥ K − 1).
    nu_max = int(t.nu.max())
    K = D + nu_max + 1
    pairs: dict[tuple[int, float], int] = {}
    group = torch.zeros(2, nf, dtype=torch.int64)  # [a, f] → index of its (ν, λ)
    for a in (0, 1):
        for g in range(nf):
            key = (int(t.nu[a, g]), float(t.rate[g]))
            group[a, g] = pairs.setdefault(key, len(pairs))
    G = len(pairs)
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

    P = torch.zeros(2, S, S, dtype=torch.float64)
    for a in (0, 1):
        # P[a, (d, f), (d′, f′)] = Q[(ν, λ)(a, f), d, d′] · F[a, f, f′]
        qa = q_next[group[a][f], d]  # [S, D + 1]
        P[a] = (qa[:, :, None] * t.F[a][f][:, None, :]).reshape(S, S)
    sent = torch.stack([q_sent[group[a][f], d] for a in (0, 1)])
    dropped = torch.stack([q_drop[group[a][f], d] for a in (0, 1)])
    general = not env.is_v1
    return ExactModel(
        params=params,
        P=P,
        R=t.R[:, f],
        event=t.event[f],
        sent=sent,
        dropped=dropped,
        capacity=t.nu[:, f],
        queue=d.to(torch.float64),
        missed_table=t.missed[:, f] if general else None,
        false_alarm=t.false_alarm[:, f] if general else None,
    )
