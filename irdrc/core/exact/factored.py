"""The exact model without the S × S matrix (MODEL.md § B.4): the transition operator factorises
into the queue (d, the channel level c, the action and the arrivals) and the joint chain of the
Markov factors (c, r, w, v, m, with the radar reaction coupling v and m with the action), so P_a·V
is computed on V reshaped to [D + 1, F] — the factor chain as an F × F matrix along the last axis,
the queue as a correlation of each column with the arrival distribution along the first — in
O(S · (F + K)) per sweep, K the arrivals kept (Poisson mass to 1e-17). The expectations of
``irdrc.core.exact.dense.DenseModel`` (its cross-check for small S, to 1e-9 in tests), the
queue-free parts stored once per factor configuration; CPU or GPU. Stationary distributions:
``irdrc.core.exact.stationary``."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import torch

from irdrc.core.exact.mdp import ExactMDP
from irdrc.core.exact.stationary import stationary_cycle_factored, stationary_distribution_factored
from irdrc.core.params import Params
from irdrc.core.tables import ModelTables, model_tables

ARRIVAL_TAIL = 1e-17
"""Arrivals are summed exactly up to the smallest K with P(A ≥ K) < this; the rest (below float64's
resolution of the sums) goes into the last bucket, so the operator stays stochastic."""


@dataclass(frozen=True, eq=False)
class FactoredModel(ExactMDP):
    """The exact MDP of ``params`` as factors (see the module docstring). S = (D + 1)·F, F = Π L
    the factor configurations (``irdrc.core.tables``; v1: 32), A actions.

    Attributes:
        params: the parameters it was built from (None: a model a learner estimated).
        F: [A, F, F] P(factors′ | a, factors).
        pmf: [n_rates, K] arrival probabilities per distinct Poisson rate, the last kept entry of
            each row holding its tail (rows padded with zeros to the longest).
        per_config: [A, F] (``event`` and ``rate``: [F]) expectations per configuration: ``R``,
            ``missed``, ``false_alarms``, ``capacity`` (ν), ``event``, ``rate`` (Poisson arrivals).
        group: [A, F] int64, the queue dynamics (ν, λ) of each (action, configuration), an index
            into ``groups`` (ν, pmf row) and into the rows of ``sent_q`` / ``dropped_q``.
        groups: (ν, pmf row) per queue dynamics.
        sent_q, dropped_q: [G, D + 1] expected packets sent / dropped per queue dynamics and d.
        radar: [A] share of the step in radar mode.
        episode_steps: steps per episode of a model without ``params`` (a learner's).
    """

    params: Params | None
    F: torch.Tensor
    pmf: torch.Tensor
    per_config: dict[str, torch.Tensor]
    group: torch.Tensor
    groups: tuple[tuple[int, int], ...]
    sent_q: torch.Tensor
    dropped_q: torch.Tensor
    radar: torch.Tensor
    episode_steps: int | None = None
    # derived in __post_init__: per action, (configurations, ν, pmf row) of each queue dynamics;
    # each pmf row's probabilities without its padding zeros
    cols: tuple[tuple[tuple[slice | torch.Tensor, int, int], ...], ...] = field(
        init=False, repr=False
    )
    weights: tuple[tuple[float, ...], ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # Per action, the configurations of each queue dynamics: a slice when contiguous (v1: the
        # channel's halves), else an index tensor.
        cols = []
        for a in range(self.num_actions):
            per = []
            g_a = self.group[a].cpu()
            for g in sorted(set(g_a.tolist())):
                idx = (g_a == g).nonzero().flatten()
                lo, hi = int(idx[0]), int(idx[-1]) + 1
                sel = slice(lo, hi) if hi - lo == idx.numel() else idx.to(self.F.device)
                per.append((sel, *self.groups[g]))
            cols.append(tuple(per))
        object.__setattr__(self, "cols", tuple(cols))
        # each row's probabilities as floats, without the padding zeros (the shifts to add up)
        weights = []
        for r in self.pmf.cpu().tolist():
            while len(r) > 1 and r[-1] == 0.0:
                r.pop()
            weights.append(tuple(r))
        object.__setattr__(self, "weights", tuple(weights))

    @property
    def num_actions(self) -> int:
        """A."""
        return int(self.F.shape[0])

    @property
    def horizon(self) -> int:
        """Steps per episode (``env.horizon``, or ``episode_steps`` without a scenario)."""
        if self.params is not None:
            return int(self.params.env.horizon)
        if self.episode_steps is None:
            raise ValueError("a model without params needs episode_steps")
        return int(self.episode_steps)

    @property
    def device(self) -> torch.device:
        """Where the tensors live."""
        return self.F.device

    @property
    def num_configs(self) -> int:
        """F, the factor configurations."""
        return int(self.F.shape[-1])

    @property
    def queue_capacity(self) -> int:
        """D."""
        return int(self.sent_q.shape[-1]) - 1

    @property
    def num_states(self) -> int:
        """S = (D + 1)·F."""
        return (self.queue_capacity + 1) * self.num_configs

    # ---- per-state tables, [A, S] in the state order of irdrc.core.dynamics -------------------------

    def _per_f(self, table: torch.Tensor) -> torch.Tensor:
        """[A, F] → [A, S] (constant in d)."""
        D1, nf = self.queue_capacity + 1, self.num_configs
        return table[:, None, :].expand(-1, D1, nf).reshape(table.shape[0], -1)

    def _per_group(self, table: torch.Tensor) -> torch.Tensor:
        """[G, D + 1] (queue dynamics, d) → [A, S]."""
        return table[self.group].transpose(1, 2).reshape(self.num_actions, -1)

    @functools.cached_property
    def R(self) -> torch.Tensor:
        """[A, S] expected reward."""
        return self._per_f(self.per_config["R"])

    @functools.cached_property
    def event(self) -> torch.Tensor:
        """[S] event probability."""
        return self.per_config["event"].repeat(self.queue_capacity + 1)

    @property
    def missed(self) -> torch.Tensor:
        """[A, S] expected missed events."""
        return self._per_f(self.per_config["missed"])

    @property
    def false_alarms(self) -> torch.Tensor:
        """[A, S] expected radar false alarms."""
        return self._per_f(self.per_config["false_alarms"])

    @property
    def capacity(self) -> torch.Tensor:
        """[A, S] link capacity ν."""
        return self._per_f(self.per_config["capacity"])

    @property
    def sent(self) -> torch.Tensor:
        """[A, S] expected packets sent."""
        return self._per_group(self.sent_q)

    @property
    def dropped(self) -> torch.Tensor:
        """[A, S] expected packets dropped."""
        return self._per_group(self.dropped_q)

    @property
    def queue(self) -> torch.Tensor:
        """[S] queue length d of each state."""
        D1 = self.queue_capacity + 1
        d = torch.arange(D1, device=self.device, dtype=torch.float64)
        return d.repeat_interleave(self.num_configs)

    # ---- the operator ---------------------------------------------------------------------------

    def _queue_expect(self, W: torch.Tensor, a: int) -> torch.Tensor:
        """out[d, f] = Σ_k pmf[k]·W[clamp(d + k − ν(a, f), 0, D), f] for W [D + 1, F]."""
        D1 = W.shape[0]
        out = torch.empty_like(W)
        for cols, nu, row in self.cols[a]:
            pmf = self.weights[row]
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

    def expect_action(self, V: torch.Tensor, a: int) -> torch.Tensor:
        """(P_a V)(s) = E[V(s′) | s, a] for V [S]."""
        D1 = self.queue_capacity + 1
        W = V.reshape(D1, self.num_configs) @ self.F[a].T  # W[d′, f] = Σ_f′ F[a,f,f′] V(d′,f′)
        return self._queue_expect(W, a).reshape(-1)

    def expect(self, V: torch.Tensor) -> torch.Tensor:
        """[A, S]: E[V(s′) | s, a]."""
        return torch.stack([self.expect_action(V, a) for a in range(self.num_actions)])

    def push(self, x: torch.Tensor, a: int) -> torch.Tensor:
        """(x P_a)(s′) for a measure x [S] over states: the distribution after one step of a."""
        return self.push_rows(x.reshape(-1, self.num_configs), a).reshape(-1)

    def push_rows(self, X: torch.Tensor, a: int) -> torch.Tensor:
        """One step of a for a measure X [n, F] on the queue lengths 0 … n − 1 (n = D + 1: the
        whole chain; a shorter prefix clamps at n − 1 instead of D, exact while no mass comes
        within the arrivals' reach of n − 1)."""
        n = X.shape[0]
        Z = torch.empty_like(X)
        for cols, nu, row in self.cols[a]:
            pmf = self.weights[row]
            K = len(pmf)
            x = X[:, cols]  # [n, m]
            # full[j] = Σ_k pmf[k]·X[j − k]: mass at d + k; its queue is clamp(j − ν, 0, n − 1)
            # (rows up to ν + n, so that a link carrying more than the arrivals reach still
            # leaves n rows after it).
            full = x.new_zeros(max(n + K - 1, nu + n), x.shape[1])
            for k in range(K):
                full[k : k + n].add_(x, alpha=pmf[k])
            z = full[nu : nu + n].clone()
            z[0] += full[:nu].sum(0)
            z[-1] += full[nu + n :].sum(0)
            Z[:, cols] = z
        return Z @ self.F[a]

    def step_rows(self, X: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
        """One step on the first n queue lengths: X [n, F] the measure, ``probs`` [n, F, A]."""
        terms = (self.push_rows(X * probs[..., a], a) for a in range(self.num_actions))
        return cast(torch.Tensor, sum(terms))

    def step(self, x: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
        """x·P_π for ``probs`` [S, A]."""
        nf = self.num_configs
        return self.step_rows(x.reshape(-1, nf), probs.reshape(-1, nf, probs.shape[-1])).reshape(-1)

    def stationary(
        self, probs: torch.Tensor, tol: float = 1e-13, max_iter: int = 1_000_000
    ) -> torch.Tensor:
        """[S] by aggregation-disaggregation over the queue (``stationary_distribution_factored``)."""
        return stationary_distribution_factored(self, probs, tol=tol, max_iter=max_iter)[0]

    def cycle(
        self, schedule: Sequence[torch.Tensor], tol: float = 1e-13, max_iter: int = 200_000
    ) -> list[torch.Tensor]:
        """Each phase's stationary distribution (``stationary_cycle_factored``)."""
        return stationary_cycle_factored(self, list(schedule), tol=tol, max_iter=max_iter)

    def dense(self, a: int) -> Any:
        """P_a as a dense NumPy [S, S] array (the ``sparse`` matrix's entries, written block by
        block: for the small models whose chains are factorised)."""
        import numpy as np

        D1, nf = self.queue_capacity + 1, self.num_configs
        F = self.F[a].cpu().numpy()
        out = np.zeros((D1, nf, D1, nf))
        d = np.arange(D1)
        for sel, nu, prow in self.cols[a]:
            pmf = self.pmf[prow].cpu().numpy()
            keep = np.nonzero(pmf)[0]
            dn = np.clip(d[:, None] + keep[None, :] - nu, 0, D1 - 1)  # [D + 1, K]
            q = np.zeros((D1, D1))
            np.add.at(q, (np.repeat(d, keep.size), dn.ravel()), np.tile(pmf[keep], D1))
            fsel = np.arange(nf)[sel.cpu().numpy() if isinstance(sel, torch.Tensor) else sel]
            out[:, fsel] = q[:, None, :, None] * F[fsel][None, :, None, :]
        return out.reshape(D1 * nf, D1 * nf)

    def _blocks(self, a: int) -> Any:
        """``sparse``'s parts, one per queue dynamics (ν, arrivals) of action ``a``: the queue's
        (D + 1) × (D + 1) chain (CSR, the clamped ends summed) and the factor configurations it
        applies to."""
        import numpy as np
        from scipy import sparse

        D1, nf = self.queue_capacity + 1, self.num_configs
        d = np.arange(D1)
        for sel, nu, prow in self.cols[a]:
            pmf = self.pmf[prow].cpu().numpy()
            keep = np.nonzero(pmf)[0]
            dn = np.clip(d[:, None] + keep[None, :] - nu, 0, D1 - 1)  # [D + 1, K]
            q = sparse.csr_matrix(
                (
                    np.broadcast_to(pmf[keep], dn.shape).ravel(),
                    (np.repeat(d, keep.size), dn.ravel()),
                ),
                shape=(D1, D1),
            )
            q.sum_duplicates()
            yield q, np.arange(nf)[sel.cpu().numpy() if isinstance(sel, torch.Tensor) else sel]

    def _row_counts(self, per_config: Any, blocks: list[Any]) -> Any:
        """[D + 1, F] the non-zeros of each row (d, f) of P_a: its queue row's times its factor
        row's (``per_config``: [F] the non-zeros of each row of F[a])."""
        import numpy as np

        counts = np.zeros((self.queue_capacity + 1, self.num_configs), dtype=np.int64)
        for q, fsel in blocks:
            counts[:, fsel] = np.diff(q.indptr)[:, None] * per_config[fsel][None, :]
        return counts

    def sparse(self, a: int) -> Any:
        """P_a as a SciPy CSR matrix: P[(d, f), (d′, f′)] = Q(d′ | d, ν, λ)·F[a, f, f′], the queue's
        arrivals (``pmf``, tail folded into the last entry) clamped at 0 and D — O(S · fan-out)
        non-zeros, never S × S dense. Written in place into the CSR arrays, a few million entries
        at a time: it holds little more than the matrix it returns."""
        import numpy as np
        from scipy import sparse

        nf, S = self.num_configs, self.num_states
        F = self.F[a].cpu().numpy()
        blocks = list(self._blocks(a))
        per_config = np.count_nonzero(F, axis=1)
        indptr = np.zeros(S + 1, dtype=np.int64)
        np.cumsum(self._row_counts(per_config, blocks).ravel(), out=indptr[1:])
        indices = np.empty(int(indptr[-1]), dtype=np.int32 if S < 2**31 else np.int64)
        data = np.empty(int(indptr[-1]))
        for q, fsel in blocks:
            fr, fc = np.nonzero(F[fsel])  # row by row, columns ascending
            fv, ff = F[fsel][fr, fc], fsel[fr]
            j = np.arange(fr.size) - np.searchsorted(fr, fr)  # its place in its factor row
            qd = np.repeat(np.arange(q.shape[0]), np.diff(q.indptr))
            k = np.arange(q.nnz) - q.indptr[qd]  # its place in its queue row
            step = max(1, SPARSE_CHUNK // max(1, fr.size))
            for lo in range(0, q.nnz, step):
                at = slice(lo, lo + step)
                pos = indptr[qd[at, None] * nf + ff] + k[at, None] * per_config[ff] + j
                indices[pos] = q.indices[at, None] * nf + fc
                data[pos] = q.data[at, None] * fv
        return sparse.csr_matrix((data, indices, indptr), shape=(S, S))

    def nonzeros(self, a: int) -> int:
        """The non-zeros ``sparse(a)`` holds, counted from the factors without building it."""
        per_config = (self.F[a] != 0).sum(1).cpu().numpy()
        return int(self._row_counts(per_config, list(self._blocks(a))).sum())


SPARSE_CHUNK = 4_000_000
"""``FactoredModel.sparse`` writes at most about this many entries at a time."""


def _poisson(lam: float, n: int) -> torch.Tensor:
    """P(A = k) for k = 0 … n − 1, A ~ Poisson(λ) (float64; underflows to 0 far in the tail)."""
    k = torch.arange(n, dtype=torch.float64)
    if lam == 0:
        return (k == 0).to(torch.float64)
    return torch.exp(k * math.log(lam) - lam - torch.lgamma(k + 1))


SHORT_BLOCK = 256
"""Capacities k summed at once in ``_queue_expectations`` (memory ν·256 doubles at a time)."""


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
    short = torch.zeros(D + 1, dtype=torch.float64)  # Σ_{k < ν − d} (ν − d − k)·p_k: 0 for d ≥ ν
    rows = min(n, D + 1)
    for lo in range(0, n, SHORT_BLOCK):  # the sum over k in order, a block of k at a time
        k_block = torch.arange(lo, min(n, lo + SHORT_BLOCK))
        gap = (n - d[:rows, None] - k_block[None, :]).clamp(min=0).to(torch.float64)
        terms = gap * p[lo : lo + len(k_block)]
        short[:rows] = torch.cat([short[:rows, None], terms], 1).cumsum(1)[:, -1]
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
    return factored_model(model_tables(params), params.env.queue_capacity, params, device)


def factored_model(
    t: ModelTables,
    D: int,
    params: Params | None = None,
    device: str | torch.device = "cpu",
    episode_steps: int | None = None,
) -> FactoredModel:
    """The factored exact model of per-configuration tables ``t`` (``irdrc.core.tables``) with a
    queue of capacity ``D``: ``build_factored``'s, or a model a learner estimated (``params``
    None: no scenario behind it; ``episode_steps`` its episodes' length)."""
    dev = torch.device(device)
    A, nf = t.nu.shape
    rates = sorted(set(t.rate.tolist()))
    pmfs = [_arrival_pmf(r) for r in rates]
    width = max(p.shape[0] for p in pmfs)
    pmf = torch.stack([torch.cat([p, p.new_zeros(width - p.shape[0])]) for p in pmfs])
    nu_max = int(t.nu.max())
    keys: dict[tuple[int, int], int] = {}
    group = torch.zeros(A, nf, dtype=torch.int64)
    for a in range(A):
        for g in range(nf):
            key = (int(t.nu[a, g]), rates.index(float(t.rate[g])))
            group[a, g] = keys.setdefault(key, len(keys))
    sent, dropped = [], []
    for nu, row in keys:
        s_, d_ = _queue_expectations(rates[row], D, nu, nu_max)
        sent.append(s_)
        dropped.append(d_)
    per_config = {
        "R": t.R,
        "event": t.event,
        "missed": t.missed,
        "false_alarms": t.false_alarm,
        "capacity": t.nu,
        "rate": t.rate,
    }
    return FactoredModel(
        params=params,
        F=t.F.to(dev),
        pmf=pmf.to(dev),
        per_config={k: v.to(dev) for k, v in per_config.items()},
        group=group.to(dev),
        groups=tuple((nu, row) for nu, row in keys),
        sent_q=torch.stack(sent).to(dev),
        dropped_q=torch.stack(dropped).to(dev),
        radar=torch.tensor([0.0, 1.0], dtype=torch.float64, device=dev),
        episode_steps=episode_steps,
    )
