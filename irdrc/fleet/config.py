"""The fleet's configuration in the recipes' style: ``env=fleet`` (``envs/fleet.yaml``, the paper's
vehicle plus the fleet keys) with ``env.vehicles``, ``env.channels``, ``env.access``, ``env.share``
and ``env.observe`` beside every single-vehicle ``env.*`` / ``reward.*`` key, validated before any
work."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from irdrc.core.params import Params, check_choice, to_plain
from irdrc.fleet.env import OBSERVE
from irdrc.fleet.exact import FleetSpec

FLEET_KEYS = ("vehicles", "channels", "access", "share", "observe")
"""The ``env.*`` keys of a fleet (MODEL.md § C) beside the single vehicle's."""


def is_fleet(cfg: Any) -> bool:
    """Whether a config's ``env`` is a fleet (it has ``env.vehicles``)."""
    env = to_plain(cfg).get("env", {}) if cfg is not None else {}
    return isinstance(env, Mapping) and "vehicles" in env


def _lists(node: Any, prefix: str) -> list[str]:
    """Dotted keys whose value is a list (per-vehicle values)."""
    if isinstance(node, Mapping):
        return [k for key, v in node.items() for k in _lists(v, f"{prefix}{key}.")]
    return [prefix[:-1]] if isinstance(node, list | tuple) else []


def fleet_from_config(cfg: Any) -> tuple[FleetSpec, str]:
    """The fleet (``FleetSpec``) and what each vehicle observes (``env.observe``) from a config
    holding ``env`` (a fleet scenario) and ``reward``.

    Raises:
        ValueError: not a fleet, a bad fleet value, a bad vehicle value (as the single-vehicle
            recipes say it), or per-vehicle lists.
    """
    plain = to_plain(cfg)
    env = dict(plain.get("env", {}))
    if "vehicles" not in env:
        raise ValueError("not a fleet: choose env=fleet (or set +env.vehicles=N)")
    fleet = {k: env.pop(k) for k in FLEET_KEYS if k in env}
    lists = _lists(env, "env.") + _lists(plain.get("reward", {}), "reward.")
    if lists:
        raise ValueError(
            f"{', '.join(lists)}: per-vehicle values are not supported yet — the fleet's vehicles "
            "are alike (one single-vehicle model for all); give one value"
        )
    vehicle = Params.from_config({"env": env, "reward": plain.get("reward", {})})
    observe = fleet.pop("observe", "own")
    check_choice("env.observe", observe, OBSERVE)
    spec = FleetSpec(vehicle=vehicle, **fleet)
    return spec, observe


def single_vehicle_only(cfg: Any, recipe: str) -> None:
    """Refuse a fleet scenario in a recipe that takes one vehicle, naming the fleet's recipes."""
    if is_fleet(cfg):
        raise ValueError(
            f"env=fleet (env.vehicles=…) is a fleet of vehicles; {recipe} takes one vehicle — "
            "run the fleet with recipes/fleet.py (learners) or recipes/solve.py (its optimum)"
        )
