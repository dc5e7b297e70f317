"""The fleet's configuration in the recipes' style: ``env=fleet`` (``envs/fleet.yaml``, the paper's
vehicle plus the fleet keys) with ``env.vehicles``, ``env.channels``, ``env.access``, ``env.share``
and ``env.observe`` beside every single-vehicle ``env.*`` / ``reward.*`` key, validated before any
work."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from irdrc.core.checks import check_choice
from irdrc.core.params import Params
from irdrc.fleet.spec import OBSERVE, FleetSpec

FLEET_KEYS = ("vehicles", "channels", "access", "share", "observe")
"""The ``env.*`` keys of a fleet (MODEL.md § C) beside the single vehicle's."""


def is_fleet(cfg: Mapping | None) -> bool:
    """Whether a config's ``env`` is a fleet (it has ``env.vehicles``)."""
    env = cfg.get("env", {}) if cfg is not None else {}
    return isinstance(env, Mapping) and "vehicles" in env


def _lists(node: Any, prefix: str) -> list[str]:
    """Dotted keys whose value is a list (per-vehicle values)."""
    if isinstance(node, Mapping):
        return [k for key, v in node.items() for k in _lists(v, f"{prefix}{key}.")]
    return [prefix[:-1]] if isinstance(node, list | tuple) else []


def _pick(node: Any, i: int) -> Any:
    """``node`` with every list replaced by its ``i``-th element (vehicle i + 1's value)."""
    if isinstance(node, Mapping):
        return {k: _pick(v, i) for k, v in node.items()}
    return node[i] if isinstance(node, list | tuple) else node


def fleet_from_config(cfg: Mapping) -> tuple[FleetSpec, str]:
    """The fleet (``FleetSpec``) and what each vehicle observes (``env.observe``) from a config
    holding ``env`` (a fleet scenario) and ``reward``. Any single-vehicle key may be a list of one
    value per vehicle (``env.p1.speed=[0.1,1.0]``, ``reward.r4=[5,50]``) where they differ.

    Raises:
        ValueError: not a fleet, a bad fleet value, a bad vehicle value (as the single-vehicle
            recipes say it, naming the vehicle), or a list of the wrong length.
    """
    plain = cfg
    env = dict(plain.get("env", {}))
    if "vehicles" not in env:
        raise ValueError("not a fleet: choose env=fleet (or set +env.vehicles=N)")
    fleet = {k: env.pop(k) for k in FLEET_KEYS if k in env}
    reward = plain.get("reward", {})
    observe = fleet.pop("observe", "own")
    check_choice("env.observe", observe, OBSERVE)
    lists = _lists(env, "env.") + _lists(reward, "reward.")
    if not lists:
        return FleetSpec(
            vehicle=Params.from_config({"env": env, "reward": reward}), **fleet
        ), observe
    n = fleet.get("vehicles")
    sizes = {k: len(list_at(env, reward, k)) for k in lists}
    wrong = {k: m for k, m in sizes.items() if m != n}
    if wrong:
        k, m = next(iter(wrong.items()))
        raise ValueError(f"{k} has {m} values for env.vehicles={n}: give one value per vehicle")
    per = []
    for i in range(n):
        try:
            per.append(Params.from_config({"env": _pick(env, i), "reward": _pick(reward, i)}))
        except ValueError as err:
            raise ValueError(f"vehicle {i + 1}: {err}") from err
    return FleetSpec(vehicle=per[0], per_vehicle=tuple(per), **fleet), observe


def list_at(env: Mapping, reward: Mapping, key: str) -> list:
    """The list at dotted ``key`` (``env.…`` or ``reward.…``)."""
    node: Any = {"env": env, "reward": reward}
    for part in key.split("."):
        node = node[part]
    return list(node)
