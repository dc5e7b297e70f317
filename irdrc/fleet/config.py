"""The fleet's configuration in the recipes' style: ``env=fleet``
(``irdrc/scenarios/fleet.yaml``, the paper's vehicle plus the fleet keys) with ``env.vehicles``,
``env.channels``, ``env.access``, ``env.share`` and ``env.observe`` beside every single-vehicle
``env.*`` / ``reward.*`` key, validated before any work."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from irdrc.core.checks import check_choice
from irdrc.core.params import Params
from irdrc.fleet.spec import OBSERVE, FleetSpec

FLEET_KEYS = ("vehicles", "channels", "access", "share", "observe")
"""The ``env.*`` keys of a fleet (MODEL.md § C) beside the single vehicle's."""


def is_fleet(cfg: Mapping[str, Any] | None) -> bool:
    """Whether a config's ``env`` is a fleet (it has ``env.vehicles``)."""
    env = cfg.get("env", {}) if cfg is not None else {}
    return isinstance(env, Mapping) and "vehicles" in env


LIST_DEPTH = {"rates": 1, "transition": 2, "levels": 1, "event": 1, "packets": 1, "comm_reward": 1}
"""How deeply a single vehicle's list-valued key nests (``env.bursty.*``, ``env.factors.<f>.*``):
such a key is per-vehicle only as a list of those (``env.bursty.rates=[[0.5,2],[0.3,1]]``)."""


def _depth(value: Any) -> int:
    if not isinstance(value, list | tuple):
        return 0
    return 1 + max((_depth(v) for v in value), default=0)


def _per_vehicle(key: str, value: Any) -> bool:
    """Whether ``value`` at dotted ``key`` lists one value per vehicle: a list at a key whose
    single-vehicle value is not one, or a list of the single-vehicle lists at a list-valued key."""
    parts = key.split(".")
    list_valued = (parts[1:2] == ["bursty"] and len(parts) == 3) or (
        parts[1:2] == ["factors"] and len(parts) == 4
    )
    natural = LIST_DEPTH.get(parts[-1], 0) if list_valued else 0
    return isinstance(value, list | tuple) and _depth(value) > natural


def _lists(node: Any, prefix: str) -> list[str]:
    """Dotted keys whose value lists one value per vehicle (``_per_vehicle``)."""
    if isinstance(node, Mapping):
        return [k for key, v in node.items() for k in _lists(v, f"{prefix}{key}.")]
    return [prefix[:-1]] if _per_vehicle(prefix[:-1], node) else []


def _pick(node: Any, i: int, prefix: str) -> Any:
    """``node`` with every per-vehicle list replaced by its ``i``-th element (vehicle i + 1's)."""
    if isinstance(node, Mapping):
        return {k: _pick(v, i, f"{prefix}{k}.") for k, v in node.items()}
    return node[i] if _per_vehicle(prefix[:-1], node) else node


def fleet_from_config(cfg: Mapping[str, Any]) -> tuple[FleetSpec, str]:
    """The fleet (``FleetSpec``) and what each vehicle observes (``env.observe``) from a config
    holding ``env`` (a fleet scenario) and ``reward``. Any single-vehicle key may be a list of one
    value per vehicle (``env.p1.speed=[0.1,1.0]``, ``reward.r4=[5,50]``) where they differ; a
    list-valued key (``env.bursty.rates``, ``env.factors.speed.event`` …) is shared as it is and
    per vehicle as a list of such lists.

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
    n = fleet["vehicles"]
    sizes = {k: len(list_at(env, reward, k)) for k in lists}
    wrong = {k: m for k, m in sizes.items() if m != n}
    if wrong:
        k, m = next(iter(wrong.items()))
        raise ValueError(f"{k} has {m} values for env.vehicles={n}: give one value per vehicle")
    per = []
    for i in range(n):
        try:
            per.append(
                Params.from_config(
                    {"env": _pick(env, i, "env."), "reward": _pick(reward, i, "reward.")}
                )
            )
        except ValueError as err:
            raise ValueError(f"vehicle {i + 1}: {err}") from err
    return FleetSpec(vehicle=per[0], per_vehicle=tuple(per), **fleet), observe


def list_at(env: Mapping[str, Any], reward: Mapping[str, Any], key: str) -> list[Any]:
    """The list at dotted ``key`` (``env.…`` or ``reward.…``)."""
    node: Any = {"env": env, "reward": reward}
    for part in key.split("."):
        node = node[part]
    return list(node)
