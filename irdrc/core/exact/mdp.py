"""The one interface of every exact model: an MDP over S states and A actions that can take
expectations of a value function and step a distribution, without saying how it stores its
transitions (a dense tensor, factors, or a fleet's joint kernels).

Solvers (``irdrc.core.exact.solve``) and scorers (``irdrc.core.exact.scorer``) use nothing else, so
value iteration, stationary distributions and exact metrics are written once for every model and
for any number of actions: v1's two (comm, radar), G levels of the radar share (MODEL.md § D), or a
fleet's 2^N joint actions (MODEL.md § C).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import torch

EXPECTATIONS = ("R", "missed", "false_alarms", "sent", "dropped", "capacity")
"""Per-step expectations of every exact model, each [A, S]: reward, missed events, radar false
alarms, packets sent, packets dropped, link capacity. ``event`` and ``queue`` are [S], and ``radar``
[A] (or [A, S]) is the share of each step spent in radar mode."""


def power_cycle(
    step: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    schedule: Sequence[torch.Tensor],
    mu: torch.Tensor,
    tol: float,
    max_iter: int,
) -> list[torch.Tensor]:
    """The distribution [S] at each phase of a periodic policy (``schedule``: one [S, A] table per
    phase, applied in turn by ``step(x, probs)``, x·P_π) by power iteration over whole cycles from
    ``mu``, until a cycle's L1 change is below ``tol``."""
    for _ in range(max_iter):
        start, path = mu, []
        for probs in schedule:
            path.append(mu)
            mu = step(mu, probs)
            mu = mu / mu.sum()
        if float((mu - start).abs().sum()) < tol:
            return path
    raise RuntimeError(f"the stationary distribution did not converge in {max_iter} cycles")


class ExactMDP:
    """An exact MDP (see the module docstring). Subclasses set ``params``, ``num_actions`` and the
    expectation tables (``EXPECTATIONS``, ``event``, ``queue``, ``radar``), and implement
    ``expect`` and ``step``; ``stationary`` (power iteration) and ``sparse`` (for the LP) have
    defaults a subclass may replace with something faster or exact.

    Attributes:
        params: the model's parameters (a fleet's: its first vehicle's).
        num_actions: A.
        horizon: steps per episode (for per-episode rewards).
    """

    if TYPE_CHECKING:  # what every model provides, as attributes or (cached) properties

        @property
        def params(self) -> Any: ...

        @property
        def num_actions(self) -> int: ...

        @property
        def R(self) -> torch.Tensor: ...

        @property
        def missed(self) -> torch.Tensor: ...

        @property
        def false_alarms(self) -> torch.Tensor: ...

        @property
        def sent(self) -> torch.Tensor: ...

        @property
        def dropped(self) -> torch.Tensor: ...

        @property
        def capacity(self) -> torch.Tensor: ...

        @property
        def event(self) -> torch.Tensor: ...

        @property
        def queue(self) -> torch.Tensor: ...

        @property
        def radar(self) -> torch.Tensor: ...

    # -- what every model provides ----------------------------------------------------------------

    @property
    def num_states(self) -> int:
        """S."""
        raise NotImplementedError

    @property
    def horizon(self) -> int:
        """Steps per episode (``env.horizon``)."""
        return int(self.params.env.horizon)

    def expect(self, V: torch.Tensor) -> torch.Tensor:
        """[A, S]: E[V(s′) | s, a] for a value function V [S]."""
        raise NotImplementedError

    def step(self, x: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
        """[S]: the measure after one step from measure ``x`` [S] under the stationary policy
        ``probs`` [S, A] (x·P_π)."""
        raise NotImplementedError

    # -- defaults -----------------------------------------------------------------------------------

    @property
    def device(self) -> torch.device:
        """Where the model's tensors live."""
        return self.R.device

    def stationary(
        self, probs: torch.Tensor, tol: float = 1e-13, max_iter: int = 200_000
    ) -> torch.Tensor:
        """[S] the stationary distribution of ``probs`` [S, A] by power iteration from uniform
        (one recurrent class assumed, as every chain here whose factors mix)."""
        return self.cycle([probs], tol, max_iter)[0]

    def cycle(
        self, schedule: Sequence[torch.Tensor], tol: float = 1e-13, max_iter: int = 200_000
    ) -> list[torch.Tensor]:
        """The stationary distribution at each phase of a periodic policy (``schedule``: one
        [S, A] table per phase, applied in turn), by power iteration over whole cycles."""
        mu = torch.full((self.num_states,), 1.0 / self.num_states, dtype=torch.float64)
        return power_cycle(self.step, schedule, mu.to(self.device), tol, max_iter)

    def q_values(self, V: torch.Tensor, gamma: float) -> torch.Tensor:
        """[A, S]: R + γ·E[V(s′)]."""
        return self.R + gamma * self.expect(V)

    def tables(self) -> Mapping[str, torch.Tensor]:
        """The per-step expectations (``EXPECTATIONS``, ``event``, ``queue``, ``radar``) by name."""
        names = (*EXPECTATIONS, "event", "queue", "radar")
        return {n: getattr(self, n) for n in names}

    def sums(self, occ: torch.Tensor) -> dict[str, float]:
        """The per-step expectations of a state-action occupancy ``occ`` [A, S] under this model's
        tables (``expected_sums``); a model may compute them without building its tables."""
        return expected_sums(occ, self.tables())

    def sparse(self, a: int) -> Any:
        """P_a as a SciPy CSR matrix [S, S] (the LP of ``irdrc.core.cmdp``)."""
        raise NotImplementedError(f"{type(self).__name__} has no sparse transitions")

    def nonzeros(self, a: int) -> int:
        """The non-zeros of ``sparse(a)`` (a model may count them without building it)."""
        return int(self.sparse(a).nnz)

    def radar_share(self) -> torch.Tensor:
        """[A, S]: the share of a step in radar mode under each action (v1: 0 comm, 1 radar)."""
        radar = torch.as_tensor(self.radar, dtype=torch.float64, device=self.device)
        if radar.dim() == 1:
            radar = radar[:, None].expand(-1, self.num_states)
        return radar


def expected_sums(occ: torch.Tensor, tables: Mapping[str, torch.Tensor]) -> dict[str, float]:
    """Per-step expectations of a state-action occupancy ``occ`` [A, S] (summing to 1 over the
    steps) under per-step expectation ``tables`` (``irdrc.core.exact.mdp.EXPECTATIONS`` [A, S],
    ``event`` and ``queue`` [S], ``radar`` [A] or [A, S]; ``denied`` and ``comm`` [A, S] where a
    fleet's uplink may deny): the sums ``irdrc.core.metrics.long_run_rates`` turns into rates."""
    occ = occ.to(torch.float64)
    per_state = occ.sum(0)
    radar = tables["radar"]
    if radar.dim() == 1:  # per action: weights of the per-action sums (exact for 0 / 1)
        w = [float(r) for r in radar]

        def weighted(x: torch.Tensor) -> float:
            return sum(w[a] * float(x[a].sum()) for a in range(len(w)) if w[a] != 0.0)

    else:

        def weighted(x: torch.Tensor) -> float:
            return float((x * radar).sum())

    sums = {
        "reward": float((occ * tables["R"]).sum()),
        "event": float((per_state * tables["event"]).sum()),
        "missed": float((occ * tables["missed"]).sum()),
        "sent": float((occ * tables["sent"]).sum()),
        "dropped": float((occ * tables["dropped"]).sum()),
        "capacity": float((occ * tables["capacity"]).sum()),
        "radar": weighted(occ),
        "quiet_radar": weighted(occ * (1.0 - tables["event"])),
        "false_alarms": float((occ * tables["false_alarms"]).sum()),
        "queue": float((per_state * tables["queue"]).sum()),
    }
    for key in ("denied", "comm"):
        if key in tables:
            sums[key] = float((occ * tables[key]).sum())
    return sums


def as_probs(policy: Any, num_states: int, num_actions: int) -> torch.Tensor:
    """[S, A] float64 action probabilities from an [S] action table or [S, A] probabilities.

    Raises:
        ValueError: another shape, an action out of range, or rows that are not distributions.
    """
    t = torch.as_tensor(policy)
    if t.shape == (num_states,):
        if t.dtype.is_floating_point and not bool((t == t.round()).all()):
            raise ValueError("an [S] policy table holds actions (whole numbers)")
        t = t.long()
        if bool(((t < 0) | (t >= num_actions)).any()):
            raise ValueError(f"policy actions must be in 0 … {num_actions - 1}")
        return torch.nn.functional.one_hot(t, num_actions).to(torch.float64)
    if t.shape != (num_states, num_actions):
        raise ValueError(
            f"policy table has shape {tuple(t.shape)}; expected [{num_states}] or "
            f"[{num_states}, {num_actions}]"
        )
    t = t.to(torch.float64)
    ones = torch.ones(num_states, dtype=torch.float64, device=t.device)
    if bool((t < 0).any()) or not torch.allclose(t.sum(-1), ones):
        raise ValueError("policy probabilities must be non-negative and sum to 1 per state")
    return t


NAMED_POLICIES = ("round_robin", "always_comm", "always_radar", "random")
"""Baselines by name: round-robin (comm at even steps, radar at odd), comm or radar always, and
each action with probability 1/A."""


def as_schedule(policy: Any, num_states: int, num_actions: int = 2) -> list[torch.Tensor]:
    """A policy as a schedule: a list of k tables [S, A], the one used at step t being
    ``schedule[t % k]``. Accepts an [S] action table, [S, A] probabilities, a list of those
    (periodic), or a name of ``NAMED_POLICIES`` (comm is action 0, radar the last action)."""
    if isinstance(policy, str):
        if policy not in NAMED_POLICIES:
            raise ValueError(f"unknown policy {policy!r}; named policies: {sorted(NAMED_POLICIES)}")
        comm = torch.zeros(num_states, dtype=torch.int64)
        radar = torch.full((num_states,), num_actions - 1, dtype=torch.int64)
        if policy == "random":
            return [torch.full((num_states, num_actions), 1.0 / num_actions, dtype=torch.float64)]
        named = {"always_comm": [comm], "always_radar": [radar], "round_robin": [comm, radar]}
        return [as_probs(t, num_states, num_actions) for t in named[policy]]
    if isinstance(policy, Sequence) and not _one_table(policy, num_states):
        return [t for p in policy for t in as_schedule(p, num_states, num_actions)]
    return [as_probs(policy, num_states, num_actions)]


def _one_table(policy: Sequence[Any], num_states: int) -> bool:
    """Whether a Python sequence is one table (numbers, or rows of numbers: a ``tolist()`` of a
    table, of any length, so that a wrong one is refused by its shape) rather than a schedule of
    tables (rows of S numbers, or a list of tables)."""
    try:
        t = torch.as_tensor(policy)
    except (TypeError, ValueError, RuntimeError):  # tables of their own, or ragged
        return False
    return t.dim() == 1 or (t.dim() == 2 and t.shape[1] != num_states)
