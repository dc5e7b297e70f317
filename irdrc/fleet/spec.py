"""A fleet of vehicles sharing one road and one base station (MODEL.md § C): its parameters and the
uplink's access rule. Pure Python (no torch), so a fleet scenario is checked before any work."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

from irdrc.core.checks import check_choice, check_number
from irdrc.core.params import Params

OBSERVE = ("own", "full")
"""What a vehicle observes (``env.observe``): its own components and the shared road and weather,
or every vehicle's."""

ACCESS = ("scheduled", "collision")
"""Uplink access rules: ``scheduled`` (K of the requests granted at random when more ask) or
``collision`` (no request granted when more than K ask)."""

FLEET_STATE_LIMIT = 2_000_000
"""The largest joint state space the exact fleet model is built for (value tensors of float64 per
joint action; N = 2 on the paper's sizes has 30 976 states, N = 3 2 725 888 — beyond it)."""


@dataclass(frozen=True)
class FleetSpec:
    """A fleet of identical vehicles (MODEL.md § C).

    Attributes:
        vehicle: each vehicle's single-vehicle model (vehicle 1's with ``per_vehicle``).
        vehicles: N.
        channels: K, uplink channels at the base station.
        access: ``scheduled`` or ``collision`` (``ACCESS``).
        share: the probability that another vehicle in radar mode detects a vehicle's event.
        per_vehicle: None (every vehicle is ``vehicle``), or N single-vehicle models where the
            vehicles differ — in their probabilities, rates and rewards; their state spaces, the
            shared road and weather chains and the horizon must be the same (``FleetModel``
            checks).
    """

    vehicle: Params = field(default_factory=Params)
    vehicles: int = 2
    channels: int = 1
    access: str = "scheduled"
    share: float = 0.5
    per_vehicle: tuple[Params, ...] | None = None

    def __post_init__(self) -> None:
        check_number("env.vehicles", self.vehicles, 1, 16, integer=True)
        check_number("env.channels", self.channels, 1, 16, integer=True)
        check_choice("env.access", self.access, ACCESS)
        check_number("env.share", self.share, 0.0, 1.0)
        for i, p in enumerate((self.vehicle, *(self.per_vehicle or ()))):
            if not isinstance(p, Params):
                which = "vehicle" if i == 0 else f"per_vehicle[{i - 1}]"
                raise ValueError(
                    f"FleetSpec({which}=…) takes a vehicle's Params, got {type(p).__name__}: "
                    "Params.from_overrides({'env.p1.speed': 0.5}) or irdrc.scenario(NAME)"
                )
        if self.vehicle.env.actions != "binary":
            raise ValueError(
                f"env.actions={self.vehicle.env.actions}: a fleet's vehicles choose comm or radar "
                "each step (MODEL.md § C); time-sharing (§ D) is for one vehicle: env.actions=binary"
            )
        if self.per_vehicle is not None:
            per = tuple(self.per_vehicle)
            if len(per) != self.vehicles:
                raise ValueError(
                    f"{len(per)} per-vehicle models for env.vehicles={self.vehicles}: give one "
                    "value per vehicle"
                )
            object.__setattr__(self, "per_vehicle", per)
            object.__setattr__(self, "vehicle", per[0])

    @property
    def vehicle_params(self) -> tuple[Params, ...]:
        """Each vehicle's single-vehicle model."""
        return self.per_vehicle or (self.vehicle,) * self.vehicles

    @property
    def alike(self) -> bool:
        """Whether every vehicle has the same model."""
        return len(set(self.vehicle_params)) == 1


def grants(comm: tuple[int, ...], channels: int, access: str) -> list[tuple[float, frozenset[int]]]:
    """The uplink's outcomes when the vehicles ``comm`` ask for it: (probability, granted set).
    At most ``channels`` requests are all granted; beyond, ``scheduled`` grants ``channels`` of
    them uniformly at random and ``collision`` none."""
    if len(comm) <= channels:
        return [(1.0, frozenset(comm))]
    if access == "collision":
        return [(1.0, frozenset())]
    sets = list(itertools.combinations(comm, channels))
    return [(1.0 / len(sets), frozenset(s)) for s in sets]
