"""Exact solutions of any exact model (``irdrc.core.exact.mdp.ExactMDP``): one value iteration, one
routine from a state-action occupancy to the metrics, and the long-run (stationary) and episodic
occupancies of any policy — stationary, randomised or periodic (round-robin is two phases).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from irdrc.core.checks import check_number
from irdrc.core.exact.mdp import ExactMDP, as_schedule
from irdrc.core.metrics import Metrics, long_run_rates

if TYPE_CHECKING:
    from irdrc.core.exact.dense import DenseModel

DEFAULT_OPTIMUM_GAMMA = 0.99
"""The discount that defines the optimum every optimality ratio is read against (MODEL.md, ref
impl); recipes expose it as ``optimum_gamma``."""


@dataclass(frozen=True)
class Solution:
    """Result of value iteration.

    Attributes:
        policy: [S] int64 optimal action per state (ties go to the lowest action: ``greedy``).
        values: [S] the optimal discounted values V*, within ``bound`` everywhere.
        q: [A, S] action values R + γ·E[V(s′)] at ``values``.
        iterations: sweeps done.
        bound: McQueen's bound on |values − V*|.
    """

    policy: torch.Tensor
    values: torch.Tensor
    q: torch.Tensor
    iterations: int
    bound: float


def check_gamma(gamma: float) -> float:
    """``gamma`` if it is a discount in [0, 1), else a ``ValueError``."""
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma={gamma!r} must be in [0, 1)")
    return float(gamma)


class ValueIteration:
    """Value iteration a few sweeps at a time: an anytime planner's (a vehicle that plans between
    its steps), stopped by McQueen's bounds as ``value_iteration``, which runs it to the end.

    Args:
        mdp: the model.
        gamma: the discount.
        tol: stop when McQueen's bound on |V − V*| is below it.
        values: [S] the start (default zeros): a neighbouring model's values start closer.
    """

    def __init__(
        self,
        mdp: ExactMDP,
        gamma: float = DEFAULT_OPTIMUM_GAMMA,
        tol: float = 1e-9,
        values: torch.Tensor | None = None,
    ) -> None:
        check_gamma(gamma)
        if tol <= 0:
            raise ValueError(f"tol={tol!r} must be > 0")
        self.mdp, self.gamma, self.tol = mdp, gamma, tol
        R = mdp.R
        if values is None:
            self.values = torch.zeros(mdp.num_states, dtype=torch.float64, device=R.device)
        elif values.shape != (mdp.num_states,):
            raise ValueError(
                f"values: shape {tuple(values.shape)}, the model has {mdp.num_states} states"
            )
        else:
            self.values = values.to(dtype=torch.float64, device=R.device)
        self.iterations = 0
        self.bound = math.inf

    def sweep(self, sweeps: int = 1, progress: Any = None) -> Solution | None:
        """Up to ``sweeps`` more sweeps; the ``Solution`` once the bound is below ``tol``, else
        None (``values`` then holds the latest iterate). ``progress`` as ``value_iteration``'s."""
        gamma, mdp = self.gamma, self.mdp
        scale = gamma / (1.0 - gamma)
        V = self.values
        for _ in range(sweeps):
            V_new = (mdp.R + gamma * mdp.expect(V)).max(0).values
            delta = V_new - V
            lo, hi = float(delta.min()), float(delta.max())
            V = V_new
            self.iterations += 1
            self.bound = scale * (hi - lo) / 2
            if progress is not None:
                progress(self.iterations, self.bound)
            if self.bound < self.tol:
                V = V + scale * (hi + lo) / 2
                self.values = V
                Q = mdp.R + gamma * mdp.expect(V)
                return Solution(
                    policy=greedy(Q), values=V, q=Q, iterations=self.iterations, bound=self.bound
                )
        self.values = V
        return None


def value_iteration(
    mdp: ExactMDP,
    gamma: float = DEFAULT_OPTIMUM_GAMMA,
    tol: float = 1e-9,
    max_iter: int = 1_000_000,
    progress: Any = None,
) -> Solution:
    """The optimal policy by value iteration, stopped by McQueen's bounds: with δ = V_{k+1} − V_k,
    V* lies in [V_{k+1} + γ/(1−γ)·min δ, V_{k+1} + γ/(1−γ)·max δ], so the midpoint is within
    ``bound`` = γ/(1−γ)·span(δ)/2 of V* everywhere; iteration stops when that is below ``tol``.
    The span contracts at the chain's mixing rate, usually far faster than γ.

    ``progress``: called with (sweep, bound) after every sweep (long solves show it).

    Raises:
        ValueError: on a bad argument; RuntimeError if ``max_iter`` sweeps do not reach ``tol``.
    """
    if max_iter < 1:
        raise ValueError(f"max_iter={max_iter!r} must be >= 1")
    vi = ValueIteration(mdp, gamma, tol)  # checks gamma and tol
    solution = vi.sweep(max_iter, progress)
    if solution is None:
        raise RuntimeError(
            f"value iteration did not reach tol {tol:g} in {max_iter} sweeps (bound {vi.bound:.3g})"
        )
    return solution


TIE_TOL = 1e-9
"""Actions whose values are within this share of the largest |Q| of the best are ties (equal in
exact arithmetic, apart by rounding alone — a fleet's symmetric vehicles): the lowest wins."""


def greedy(Q: torch.Tensor) -> torch.Tensor:
    """[S] the best action per state of Q [A, S], ties (``TIE_TOL``) to the lowest action (comm
    first), so rounding never decides between equal actions."""
    best = Q.max(0).values
    tie = TIE_TOL * max(1.0, float(Q.abs().max()))
    return (best - tie <= Q).to(torch.int8).argmax(0)


def metrics_from_occupancy(mdp: ExactMDP, occ: torch.Tensor) -> Metrics:
    """The ``Metrics`` of a state-action occupancy [A, S] on ``mdp``; the false-alarm
    rate only where the scenario has false alarms (P_fa > 0)."""
    return metrics_from_sums(mdp, mdp.sums(occ))


def metrics_from_sums(mdp: ExactMDP, sums: Mapping[str, float]) -> Metrics:
    """The ``Metrics`` of an occupancy's per-step expectations on ``mdp`` (``ExactMDP.sums``)."""
    r = long_run_rates(dict(sums))
    if mdp.params is not None and mdp.params.env.false_alarm_prob == 0.0:
        r["false_alarm_rate"] = math.nan
    return Metrics(
        avg_reward=r["avg_reward"],
        episode_reward=r["avg_reward"] * mdp.horizon,
        throughput=r["throughput"],
        link_capacity=r["link_capacity"],
        miss_detection=r["miss_detection"],
        radar_fraction=r["radar_fraction"],
        drop_rate=r["drop_rate"],
        mean_queue=r["mean_queue"],
        false_alarm_rate=r["false_alarm_rate"],
    )


def occupancy(schedule: list[torch.Tensor], path: list[torch.Tensor]) -> torch.Tensor:
    """[A, S]: the state-action occupancy of a schedule whose phase k has distribution ``path[k]``."""
    occ = torch.zeros(schedule[0].shape[::-1], dtype=torch.float64, device=path[0].device)
    for mu, table in zip(path, schedule, strict=True):
        occ += (mu[:, None] * table).T
    return occ / len(schedule)


def stationary_occupancy(mdp: ExactMDP, policy: Any) -> torch.Tensor:
    """Long-run state-action occupancy [A, S] of a (periodic) policy (``as_schedule``)."""
    schedule = [t.to(mdp.device) for t in as_schedule(policy, mdp.num_states, mdp.num_actions)]
    if len(schedule) == 1:
        return occupancy(schedule, [mdp.stationary(schedule[0])])
    return occupancy(schedule, mdp.cycle(schedule))


def stationary_metrics(mdp: ExactMDP, policy: Any) -> Metrics:
    """Exact long-run metrics of a policy: an [S] action table, [S, A] probabilities, a list of
    those (periodic), or a name (``irdrc.core.exact.mdp.NAMED_POLICIES``)."""
    return metrics_from_occupancy(mdp, stationary_occupancy(mdp, policy))


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


def episodic_occupancy(mdp: ExactMDP, policy: Any, horizon: int | None = None) -> torch.Tensor:
    """State-action occupancy [A, S] averaged over the steps of an episode from the reset
    distribution (uniform over all states), for ``horizon`` steps (default ``env.horizon``)."""
    sched = as_schedule(policy, mdp.num_states, mdp.num_actions)
    horizon = mdp.horizon if horizon is None else check_number("horizon", horizon, 1, integer=True)
    k, S = len(sched), mdp.num_states
    rho = torch.full((S,), 1.0 / S, dtype=torch.float64)
    occ = torch.zeros(mdp.num_actions, S, dtype=torch.float64)
    chain = getattr(mdp, "chain", None)
    if chain is None or horizon <= 4 * S or S > DOUBLING_MAX_STATES:
        chains = [chain(t) for t in sched] if chain is not None else None
        for t in range(horizon):
            j = t % k
            occ += (rho[:, None] * sched[j]).T
            rho = rho @ chains[j] if chains is not None else mdp.step(rho, sched[j])
        return occ / horizon
    # Step t = m·k + j is at rho · M^m · C_0 ⋯ C_{j−1}, with M the product over one period.
    chains = [chain(t) for t in sched]
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


def episodic_metrics(mdp: ExactMDP, policy: Any, horizon: int | None = None) -> Metrics:
    """Exact metrics of episodes of ``horizon`` steps started from the uniform reset distribution:
    what a Monte-Carlo evaluation estimates. It differs from the stationary metrics because every
    episode starts from a uniform state (e.g. a mean queue of D/2)."""
    return metrics_from_occupancy(mdp, episodic_occupancy(mdp, policy, horizon))


def policy_evaluation(
    mdp: DenseModel, policy: Any, gamma: float = DEFAULT_OPTIMUM_GAMMA
) -> torch.Tensor:
    """Exact discounted values V^π of a stationary policy on a dense model: solves
    (I − γ P_π) V = R_π."""
    (table,) = as_schedule(policy, mdp.num_states, mdp.num_actions)
    P = mdp.chain(table)
    R = (table.T * mdp.R).sum(0)
    eye = torch.eye(mdp.num_states, dtype=torch.float64)
    return torch.linalg.solve(eye - check_gamma(gamma) * P, R)


def one_step_spread(mdp: ExactMDP, values: torch.Tensor, gamma: float) -> torch.Tensor:
    """[A, S] the standard deviation of one step's sampled value r + γ·V(s′) from each state under
    each action: √(Var[r] + γ²·Var[V(s′)]). Reward and next state are drawn independently given
    (s, a) (the event and the radar's draw move no factor, MODEL.md's step), so nothing else adds.
    A learner that estimates each action's value from samples needs about (z·σ/margin)² of them
    where the margin between the actions is small against σ. Defined for a scenario's binary
    model (comm or radar: v1 and § B); ``values`` [S] (e.g. value iteration's V*)."""
    from irdrc.core.tables import model_tables

    params = getattr(mdp, "params", None)
    if params is None or mdp.num_actions != 2 or params.env.actions != "binary":
        raise ValueError(
            "one_step_spread: defined on a scenario's binary model (comm or radar each step)"
        )
    t = model_tables(params)
    f = torch.arange(mdp.num_states, device=mdp.device) % t.num_configs
    V = values.to(torch.float64)
    var_r = (t.R2.to(mdp.device)[:, f] - mdp.R**2).clamp(min=0.0)
    mean = mdp.expect(V)
    var_v = (mdp.expect(V * V) - mean**2).clamp(min=0.0)
    return (var_r + check_gamma(gamma) ** 2 * var_v).sqrt()
