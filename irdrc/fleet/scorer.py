"""The fleet's exact metrics, per vehicle and for the fleet, and its scorer: decentralised policies
against the centralised optimum (value iteration over the joint actions, ``irdrc.core.exact``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch

from irdrc.core.exact import DEFAULT_OPTIMUM_GAMMA, Scorer, as_schedule, stationary_occupancy
from irdrc.core.exact.solve import metrics_from_sums
from irdrc.core.metrics import Metrics, long_run_rates
from irdrc.fleet.model import FleetModel
from irdrc.fleet.policies import joint_policy

if TYPE_CHECKING:
    from irdrc.core.exact.solve import Solution

FLEET_METRICS = (
    "avg_reward",
    "throughput",
    "miss_detection",
    "radar_fraction",
    "drop_rate",
    "denial_rate",
    "link_capacity",
    "mean_queue",
)
"""Metrics per vehicle and for the fleet (ratios of sums across vehicles)."""

PRINTED = (
    "avg_reward",
    "throughput",
    "miss_detection",
    "radar_fraction",
    "denial_rate",
    "drop_rate",
)
"""The columns of a printed fleet table."""


def fleet_metrics(model: FleetModel, policy: Any) -> tuple[Metrics, list[dict[str, float]]]:
    """Exact long-run metrics of a joint policy (stationary, or periodic as a list of per-phase
    policies, averaged over its phases): the fleet's ``Metrics`` (reward, throughput, drops and
    capacity summed over the vehicles; miss detection a ratio of sums; radar fraction and mean
    queue averaged over them) and each vehicle's, then the fleet's, as dicts of ``FLEET_METRICS``."""
    model.check_exact()
    occ = stationary_occupancy(model, as_schedule(policy, model.num_states, model.num_actions))
    per: list[dict[str, Any]] = []
    for i in range(model.N):
        rates = long_run_rates(model.sums(occ, i))
        rates.pop("false_alarm_rate", None)
        per.append({**rates, "vehicle": i + 1})
    sums = model.sums(occ)
    fleet = long_run_rates(sums)
    fleet.pop("false_alarm_rate", None)
    per.append({"vehicle": "fleet", **fleet})
    return metrics_from_sums(model, sums), per


class FleetScorer(Scorer):
    """The scorer of the fleet's decentralised policies against the centralised optimum: a table
    [S] over the single-vehicle states every vehicle applies to its own state, one such table per
    vehicle [N·S] (vehicle-major), or a joint action per joint state [S_fleet]."""

    model: FleetModel

    def __init__(self, model: FleetModel, gamma: float = DEFAULT_OPTIMUM_GAMMA) -> None:
        model.check_exact()
        super().__init__(model, gamma)

    @property
    def fleet_optimum(self) -> Solution:
        """The centralised optimum (value iteration's ``Solution``)."""
        return self.optimal

    def policy(self, table: torch.Tensor) -> torch.Tensor:
        """The joint policy of a decentralised ``table`` (``joint_policy``)."""
        return joint_policy(self.model, table)
