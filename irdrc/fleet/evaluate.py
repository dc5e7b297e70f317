"""Monte-Carlo long-run metrics of fleet policies at any N (beyond the exact model's reach), and
MODEL.md § C's baselines as action rules.

A policy here is a rule ``act(states, t) -> actions``: [n, N] single-vehicle states of n fleets
at step t → [n, N] actions (0 comm, 1 radar). ``simulate`` runs ``fleets`` fleets from a uniform
start, drops ``burn_in`` steps, and averages the per-step signals of ``FleetDynamics`` over the
next ``steps``: the long-run rates ``fleet_metrics`` computes exactly, with a 95 % confidence
half-width of the fleet's reward across the (independent) fleets.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from irdrc.core.metrics import Metrics, long_run_rates
from irdrc.fleet.model import FleetModel
from irdrc.fleet.sim import FleetDynamics

ActionRule = Callable[[torch.Tensor, int], torch.Tensor]
"""``act(states [n, N], t) -> actions [n, N]``."""


@dataclass(frozen=True)
class SimulatedMetrics:
    """``fleet`` metrics (``Metrics``), ``per_vehicle`` dicts (each vehicle's, then the fleet's,
    as ``irdrc.fleet.scorer.fleet_metrics``), ``ci95`` of the fleet's average reward, and the
    fleet steps simulated (burn-in included)."""

    fleet: Metrics
    per_vehicle: list[dict[str, float]]
    ci95: float
    fleet_steps: int


def table_rule(tables: torch.Tensor, num_single_states: int) -> ActionRule:
    """The rule of single-vehicle tables: one table [S] every vehicle applies to its own state,
    or one per vehicle [N·S] (vehicle-major)."""
    t = torch.as_tensor(tables).long().reshape(-1, num_single_states)  # [1 or N, S]

    def act(states: torch.Tensor, _t: int) -> torch.Tensor:
        if t.shape[0] == 1:
            return t[0][states]
        return torch.gather(t.T, 0, states)  # t.T[s, i] = vehicle i's action in state s

    return act


def baseline_rules(model: FleetModel, single_optimum: torch.Tensor) -> dict[str, ActionRule]:
    """MODEL.md § C's baselines (as ``irdrc.fleet.policies.baselines``; ``single_optimum`` [S] or
    each vehicle's own [N, S]) and radar always, as rules at any N."""
    N = model.N
    copies = table_rule(single_optimum, model.single.num_states)
    odd = torch.arange(N) % 2 == 1  # vehicles 2, 4, …

    def in_phase(states: torch.Tensor, t: int) -> torch.Tensor:
        return torch.full_like(states, t % 2)

    def anti_phase(states: torch.Tensor, t: int) -> torch.Tensor:
        return (odd.long() ^ (t % 2)).expand_as(states).clone()

    def rotation(states: torch.Tensor, t: int) -> torch.Tensor:
        return (torch.arange(N) == t % N).long().expand_as(states).clone()

    def radar(states: torch.Tensor, _t: int) -> torch.Tensor:
        return torch.ones_like(states)

    return {
        "N copies of the single optimum": copies,
        "round-robin in phase": in_phase,
        "round-robin in anti-phase": anti_phase,
        "sensing rotation": rotation,
        "always radar": radar,
    }


KEYS = ("reward", "missed", "event", "sent", "dropped", "radar", "comm", "denied", "queue")


def simulate(
    model: FleetModel,
    act: ActionRule,
    *,
    fleets: int = 256,
    steps: int = 2_000,
    burn_in: int = 200,
    seed: int = 0,
    sim: FleetDynamics | None = None,
) -> SimulatedMetrics:
    """Long-run metrics of ``act`` by simulation (see the module docstring)."""
    if fleets < 2 or steps < 1 or burn_in < 0:
        raise ValueError("simulate needs fleets >= 2, steps >= 1, burn_in >= 0")
    sim = sim or FleetDynamics(model)
    gen = torch.Generator().manual_seed(int(seed))
    N = model.N
    rw = torch.randint(0, model.RW, (fleets, 1), generator=gen).expand(fleets, N)
    states = model.index[rw, torch.randint(0, model.X, (fleets, N), generator=gen)]
    sums = {k: torch.zeros(fleets, N, dtype=torch.float64) for k in KEYS}
    for t in range(burn_in + steps):
        actions = act(states, t)
        res = sim.step(states, actions, gen)
        if t >= burn_in:
            radar = actions == 1
            for k, v in (
                ("reward", res.reward),
                ("missed", res.missed),
                ("event", res.event),
                ("sent", res.sent),
                ("dropped", res.dropped),
                ("radar", radar),
                ("comm", ~radar),
                ("denied", res.denied),
                ("queue", sim.dyn.split(states.reshape(-1))[0].reshape(fleets, N)),
            ):
                sums[k] += v.to(torch.float64)
        states = res.state
    per_fleet_reward = sums["reward"].sum(1) / steps
    ci = 1.96 * float(per_fleet_reward.std()) / math.sqrt(fleets)
    n = fleets * steps
    per: list[dict[str, Any]] = [
        long_run_rates({k: float(v[:, i].sum()) / n for k, v in sums.items()}) for i in range(N)
    ]
    total = {k: float(v.sum()) / n for k, v in sums.items()}
    fleet = long_run_rates(total)
    for i, r in enumerate(per):
        r["vehicle"] = i + 1
    per.append(
        {
            "vehicle": "fleet",
            **fleet,
            "radar_fraction": total["radar"] / N,
            "mean_queue": total["queue"] / N,
        }
    )
    metrics = Metrics(
        avg_reward=fleet["avg_reward"],
        episode_reward=fleet["avg_reward"] * model.spec.vehicle.env.horizon,
        throughput=fleet["throughput"],
        link_capacity=math.nan,
        miss_detection=fleet["miss_detection"],
        radar_fraction=total["radar"] / N,
        drop_rate=fleet["drop_rate"],
        mean_queue=total["queue"] / N,
    )
    return SimulatedMetrics(metrics, per, ci, fleets * (burn_in + steps))


class FleetMCScorer:
    """The fleet's scorer where the exact model does not reach: a policy's metrics by simulation
    (``simulate``, cached per table), and as reference (``optimal_metrics``) the best of the
    baselines (``baseline_rules``) measured the same way — ratios are to the best baseline.

    Policies are single-vehicle tables ([S] for every vehicle, or [N·S] one per vehicle)."""

    def __init__(
        self,
        model: FleetModel,
        single_optimum: torch.Tensor,
        *,
        fleets: int = 256,
        steps: int = 2_000,
        burn_in: int = 200,
        seed: int = 0,
    ) -> None:
        self.model = model
        self.sim = FleetDynamics(model)
        self.kw = {"fleets": fleets, "steps": steps, "burn_in": burn_in, "seed": seed}
        self.baselines = {
            name: simulate(model, rule, sim=self.sim, **self.kw)
            for name, rule in baseline_rules(model, single_optimum).items()
        }
        self.reference = max(self.baselines, key=lambda k: self.baselines[k].fleet.avg_reward)
        self.optimal_metrics = self.baselines[self.reference].fleet
        self._cache: dict[bytes, SimulatedMetrics] = {}

    def measure(self, table: torch.Tensor) -> SimulatedMetrics:
        """``simulate`` of the table's rule (cached)."""
        key = torch.as_tensor(table).to(torch.uint8).numpy().tobytes()
        if key not in self._cache:
            rule = table_rule(table, self.model.single.num_states)
            self._cache[key] = simulate(self.model, rule, sim=self.sim, **self.kw)
        return self._cache[key]

    def metrics(self, table: torch.Tensor) -> Metrics:
        """The fleet's ``Metrics`` of a table policy, by simulation."""
        return self.measure(table).fleet
