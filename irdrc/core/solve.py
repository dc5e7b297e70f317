"""Exact solutions of the model: value iteration, policy evaluation, exact long-run and episodic metrics.

Policies are given as *schedules*: a list of k tables of action probabilities [S, 2], the table used
at step t being ``schedule[t % k]``. A deterministic stationary policy is one table (``[S]`` actions
are accepted and turned into one); round-robin is two (all-comm, all-radar), so it is evaluated
exactly with its two-phase chain.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from irdrc.core.metrics import Metrics
from irdrc.core.model import ExactModel
from irdrc.core.params import Params

Schedule = list[torch.Tensor]

DEFAULT_OPTIMUM_GAMMA = 0.99
"""The discount that defines the optimum every optimality ratio is read against (MODEL.md, ref impl);
recipes expose it as ``optimum_gamma``."""


@dataclass(frozen=True)
class Solution:
    """Result of value iteration.

    Attributes:
        policy: [S] int64 optimal action per state (ties go to comm, action 0).
        values: [S] optimal discounted values V*(s).
        q: [2, S] optimal action values Q*(a, s).
        iterations: sweeps done.
        residual: the last sup-norm change of V.
    """

    policy: torch.Tensor
    values: torch.Tensor
    q: torch.Tensor
    iterations: int
    residual: float


def value_iteration(
    model: ExactModel,
    gamma: float = DEFAULT_OPTIMUM_GAMMA,
    tol: float = 1e-9,
    max_iter: int = 100_000,
) -> Solution:
    """Optimal policy by value iteration, stopped when sup |V_{k+1} − V_k| < tol.

    The returned values are the exact values of the returned greedy policy (a final policy
    evaluation), so they are not off by the stopping tolerance.

    Raises:
        ValueError: on a bad argument; RuntimeError if ``max_iter`` sweeps do not reach ``tol``.
    """
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma={gamma!r} must be in [0, 1)")
    if tol <= 0 or max_iter < 1:
        raise ValueError("tol must be > 0 and max_iter >= 1")
    V = torch.zeros(model.num_states, dtype=torch.float64)
    residual = float("inf")
    for it in range(1, max_iter + 1):  # noqa: B007 - reported after the loop
        Q = model.R + gamma * model.P @ V
        V_new = Q.max(0).values
        residual = float((V_new - V).abs().max())
        V = V_new
        if residual < tol:
            break
    else:
        raise RuntimeError(
            f"value iteration did not converge in {max_iter} sweeps (residual {residual:.3g} ≥ tol {tol:g})"
        )
    Q = model.R + gamma * model.P @ V
    policy = Q.argmax(0)  # first maximum: ties → comm
    V = policy_evaluation(model, policy, gamma)
    Q = model.R + gamma * model.P @ V
    return Solution(policy=policy, values=V, q=Q, iterations=it, residual=residual)


def as_schedule(policy, num_states: int) -> Schedule:
    """Normalise a policy into a schedule of [S, 2] action-probability tables.

    Accepts: an [S] table of actions, an [S, 2] table of probabilities, a list of those (periodic),
    or the names ``"round_robin"`` (comm at even steps), ``"always_comm"``, ``"always_radar"``,
    ``"random"``.
    """
    ones = torch.ones(num_states, dtype=torch.float64)
    named = {
        "always_comm": [torch.stack([ones, 0 * ones], -1)],
        "always_radar": [torch.stack([0 * ones, ones], -1)],
        "random": [torch.full((num_states, 2), 0.5, dtype=torch.float64)],
    }
    named["round_robin"] = [named["always_comm"][0], named["always_radar"][0]]
    if isinstance(policy, str):
        if policy not in named:
            raise ValueError(f"unknown policy {policy!r}; named policies: {sorted(named)}")
        return named[policy]
    if isinstance(policy, Sequence) and not isinstance(policy, torch.Tensor):
        return [t for p in policy for t in as_schedule(p, num_states)]
    t = torch.as_tensor(policy)
    if t.shape == (num_states,):
        t = torch.nn.functional.one_hot(t.long(), 2).to(torch.float64)
    if t.shape != (num_states, 2):
        raise ValueError(
            f"policy table has shape {tuple(t.shape)}; expected [{num_states}] or [{num_states}, 2]"
        )
    t = t.to(torch.float64)
    if bool((t < 0).any()) or not torch.allclose(
        t.sum(-1), torch.ones(num_states, dtype=torch.float64)
    ):
        raise ValueError("policy probabilities must be non-negative and sum to 1 per state")
    return [t]


def _chain(model: ExactModel, table: torch.Tensor) -> torch.Tensor:
    """[S, S] transition matrix under one action-probability table."""
    return table[:, 0, None] * model.P[0] + table[:, 1, None] * model.P[1]


def policy_evaluation(
    model: ExactModel, policy, gamma: float = DEFAULT_OPTIMUM_GAMMA
) -> torch.Tensor:
    """Exact discounted values V^π of a stationary policy: solves (I − γ P_π) V = R_π."""
    sched = as_schedule(policy, model.num_states)
    if len(sched) != 1:
        raise ValueError("policy_evaluation takes a stationary policy (one table)")
    table = sched[0]
    P = _chain(model, table)
    R = (table.T * model.R).sum(0)
    eye = torch.eye(model.num_states, dtype=torch.float64)
    return torch.linalg.solve(eye - gamma * P, R)


def stationary_distribution(P: torch.Tensor) -> torch.Tensor:
    """μ with μ P = μ, Σμ = 1, by a least-squares solve of the stacked linear system.

    Assumes the chain has a single recurrent class (true whenever every factor chain mixes, as
    with the defaults); raises if the solution is not a distribution to 1e-8.
    """
    n = P.shape[0]
    A = torch.cat([P.T - torch.eye(n, dtype=P.dtype), torch.ones(1, n, dtype=P.dtype)])
    b = torch.zeros(n + 1, dtype=P.dtype)
    b[-1] = 1.0
    mu = torch.linalg.lstsq(A, b[:, None], driver="gelsd").solution[:, 0]
    if bool((mu < -1e-8).any()) or float((mu @ P - mu).abs().max()) > 1e-8:
        raise RuntimeError("the chain has no unique stationary distribution")
    return mu.clamp(min=0) / mu.clamp(min=0).sum()


def metrics_from_occupancy(model: ExactModel, occupancy: torch.Tensor) -> Metrics:
    """Metrics of a state-action occupancy ``occupancy[a, s]`` (summing to 1 over the steps).

    Every metric is an expectation per step under the occupancy, except miss detection, the ratio
    of expected missed to expected events (the exact counterpart of the ratio of sums).
    """
    occ = occupancy.to(torch.float64)
    horizon = model.params.env.horizon
    avg_reward = float((occ * model.R).sum())
    events = float((occ.sum(0) * model.event).sum())
    missed = float((occ * model.missed).sum())
    return Metrics(
        avg_reward=avg_reward,
        episode_reward=avg_reward * horizon,
        throughput=float((occ * model.sent).sum()),
        link_capacity=float((occ * model.capacity).sum()),
        miss_detection=missed / events if events > 0 else float("nan"),
        radar_fraction=float(occ[1].sum()),
        drop_rate=float((occ * model.dropped).sum()),
        mean_queue=float((occ.sum(0) * model.queue).sum()),
        false_alarm_rate=false_alarm_rate(occ, model.event, model.false_alarms, model.params),
    )


def false_alarm_rate(
    occ: torch.Tensor, event: torch.Tensor, false_alarms: torch.Tensor, params: Params
) -> float:
    """Expected false alarms over expected radar steps without an event, under the occupancy
    ``occ`` [2, S]; NaN when the scenario has no false alarms (P_fa = 0) or no such step."""
    if params.env.false_alarm_prob == 0.0:
        return math.nan
    quiet = float((occ[1] * (1.0 - event)).sum())
    return float((occ * false_alarms).sum()) / quiet if quiet > 0 else math.nan


def stationary_occupancy(model: ExactModel, policy) -> torch.Tensor:
    """Long-run state-action occupancy [2, S] of a (periodic) policy."""
    sched = as_schedule(policy, model.num_states)
    chains = [_chain(model, t) for t in sched]
    cycle = chains[0]
    for ch in chains[1:]:
        cycle = cycle @ ch
    mu = stationary_distribution(cycle)  # distribution at phase 0
    occ = torch.zeros(2, model.num_states, dtype=torch.float64)
    for table, ch in zip(sched, chains, strict=True):
        occ += (mu[:, None] * table).T
        mu = mu @ ch
    return occ / len(sched)


DOUBLING_MAX_STATES = 2048
"""Up to this many states, long episodic horizons use repeated squaring (log2(T) matrix products);
above it, one matrix-vector product per step."""


def _power_sum(M: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(Σ_{m<n} M^m, M^n) by repeated squaring."""
    eye = torch.eye(M.shape[0], dtype=M.dtype)
    if n == 0:
        return torch.zeros_like(M), eye
    G, P = _power_sum(M, n // 2)
    G, P = G + P @ G, P @ P  # Σ_{m<2h} = Σ_{m<h} + M^h Σ_{m<h}
    if n % 2:
        G, P = G + P, P @ M
    return G, P


def episodic_occupancy(model: ExactModel, policy, horizon: int | None = None) -> torch.Tensor:
    """State-action occupancy [2, S] averaged over the steps of an episode from the reset
    distribution (uniform over all states), for ``horizon`` steps (default ``env.horizon``)."""
    sched = as_schedule(policy, model.num_states)
    horizon = model.params.env.horizon if horizon is None else horizon
    k, S = len(sched), model.num_states
    chains = [_chain(model, t) for t in sched]
    rho = torch.full((S,), 1.0 / S, dtype=torch.float64)
    occ = torch.zeros(2, S, dtype=torch.float64)
    if horizon <= 4 * S or S > DOUBLING_MAX_STATES:
        for t in range(horizon):
            j = t % k
            occ += (rho[:, None] * sched[j]).T
            rho = rho @ chains[j]
        return occ / horizon
    # Step t = m·k + j is at rho · M^m · C_0 ⋯ C_{j−1}, with M the product over one period.
    cycle = chains[0]
    for ch in chains[1:]:
        cycle = cycle @ ch
    prefix = torch.eye(S, dtype=torch.float64)
    for j in range(k):
        n_j = (horizon - j + k - 1) // k  # steps of phase j within the horizon
        G, _ = _power_sum(cycle, n_j)
        occ += ((rho @ G @ prefix)[:, None] * sched[j]).T
        prefix = prefix @ chains[j]
    return occ / horizon


def stationary_metrics(model: ExactModel, policy) -> Metrics:
    """Exact long-run metrics of a policy (see ``as_schedule`` for what a policy may be)."""
    return metrics_from_occupancy(model, stationary_occupancy(model, policy))


def episodic_metrics(model: ExactModel, policy, horizon: int | None = None) -> Metrics:
    """Exact metrics of episodes of ``horizon`` steps started from the uniform reset distribution.

    This is what a Monte-Carlo ``evaluate`` estimates; it differs from the stationary metrics
    because every episode starts from a uniform state (e.g. a mean queue of D/2).
    """
    return metrics_from_occupancy(model, episodic_occupancy(model, policy, horizon))


class ExactScorer:
    """Exact stationary metrics of greedy tables, cached (learners often revisit the same table)."""

    def __init__(self, model: ExactModel, gamma: float = DEFAULT_OPTIMUM_GAMMA) -> None:
        self.model = model
        self.optimal = value_iteration(model, gamma=gamma)
        self.optimal_metrics = stationary_metrics(model, self.optimal.policy)
        self._cache: dict[bytes, Any] = {}

    def metrics(self, table: torch.Tensor):
        """Exact stationary ``Metrics`` of the deterministic policy ``table`` ([S] actions)."""
        key = table.to(torch.uint8).cpu().numpy().tobytes()
        if key not in self._cache:
            self._cache[key] = self._evaluate(table.cpu())
        return self._cache[key]

    def _evaluate(self, table: torch.Tensor):
        return stationary_metrics(self.model, table)

    def ratio(self, table: torch.Tensor) -> float:
        """Average reward of ``table`` over the optimal average reward (both stationary)."""
        return self.metrics(table).avg_reward / self.optimal_metrics.avg_reward
