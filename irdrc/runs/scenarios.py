"""The named scenarios (``irdrc/scenarios/*.yaml``, the config group ``env``, package data: an
installed wheel has them too): listed with their purposes, loaded with their ``defaults``, given as
``Params`` (``irdrc.scenario``) and registered with Hydra.

A scenario file holds the ``env`` keys of MODEL.md, its purpose on its first line. It may start with
``defaults: [other]`` to take another scenario's values first and override some of them
(``ref_impl.yaml`` does).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from irdrc.core.params import Params

ENVS_DIR = Path(__file__).resolve().parents[1] / "scenarios"
"""Where the named scenarios are."""


def list_scenarios(envs_dir: Path = ENVS_DIR) -> list[str]:
    """Names of the scenarios in ``irdrc/scenarios/``."""
    return sorted(p.stem for p in envs_dir.glob("*.yaml"))


def scenario_purposes(envs_dir: Path = ENVS_DIR) -> dict[str, str]:
    """Each named scenario with its purpose: the first line of its file, a comment.

    Raises:
        ValueError: a scenario file whose first line is not a comment.
    """
    out = {}
    for name in list_scenarios(envs_dir):
        first = (envs_dir / f"{name}.yaml").read_text().split("\n", 1)[0]
        if not first.startswith("#"):
            raise ValueError(f"{envs_dir / name}.yaml: its first line must say its purpose (# …)")
        out[name] = first.lstrip("#").strip()
    return out


def fleet_scenarios(envs_dir: Path = ENVS_DIR) -> list[str]:
    """Names of the scenarios in ``irdrc/scenarios/`` that are fleets of vehicles (they set
    ``vehicles``, themselves or through their defaults)."""
    return [n for n in list_scenarios(envs_dir) if "vehicles" in load_scenario(n, envs_dir)]


def scenario(name: str, overrides: Mapping[str, Any] | None = None, /, **more: Any) -> Params:
    """The ``Params`` of the named scenario ``name`` (``irdrc/scenarios/<name>.yaml``, one
    vehicle) with ``overrides`` named as on the command line (``{"env.p1.speed": 0.5, "reward.r4":
    50}``, as a mapping or as keywords: ``**{"env.p1.speed": 0.5}``), the paper's reward:
    ``irdrc.scenario("multilevel")``, for the gym id (``params=``) or any model.

    Raises:
        ValueError: an unknown scenario, a fleet (``irdrc.fleet.parallel_env`` and ``FleetSpec``
            take those), or a bad key or value.
    """
    from omegaconf import OmegaConf

    from irdrc.core.overrides import apply_overrides
    from irdrc.core.params import Params

    env = cast(dict[str, Any], OmegaConf.to_container(load_scenario(name), resolve=True))
    if "vehicles" in env:
        raise ValueError(
            f"scenario {name!r} is a fleet of vehicles: irdrc.fleet.parallel_env(**overrides) "
            "and irdrc.fleet.spec.FleetSpec build fleets"
        )
    merged: dict[str, Any] = {"env": env, "reward": {}}
    apply_overrides(merged, {**(overrides or {}), **more})
    return Params.from_config(merged, strict=False)


def load_scenario(name: str, envs_dir: Path = ENVS_DIR, _seen: tuple[str, ...] = ()) -> DictConfig:
    """The ``env`` config of scenario ``name`` (an OmegaConf node), its ``defaults`` resolved.

    Raises:
        ValueError: unknown scenario, a file that is not a mapping, or a cycle in ``defaults``.
    """
    from omegaconf import DictConfig, OmegaConf

    path = envs_dir / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(
            f"env={name!r} is not a scenario; available: {', '.join(list_scenarios(envs_dir))}"
        )
    if name in _seen:
        raise ValueError(f"scenario defaults form a cycle: {' -> '.join((*_seen, name))}")
    node = OmegaConf.load(path)
    if not isinstance(node, DictConfig):
        raise ValueError(f"{path}: a scenario file holds a mapping of env keys, not a list")
    bases = node.pop("defaults", [])
    merged: Any = OmegaConf.create()
    for base in bases:
        if base != "_self_":
            merged = OmegaConf.merge(merged, load_scenario(str(base), envs_dir, (*_seen, name)))
    return cast(DictConfig, OmegaConf.merge(merged, node))


_REGISTERED: set[str] = set()


def register_scenarios(envs_dir: Path = ENVS_DIR) -> None:
    """Put every scenario into Hydra's ConfigStore as the config group ``env`` (once a process)."""
    from hydra.core.config_store import ConfigStore

    if str(envs_dir) in _REGISTERED:
        return
    cs = ConfigStore.instance()
    for name in list_scenarios(envs_dir):
        cs.store(group="env", name=name, node=load_scenario(name, envs_dir))
    _REGISTERED.add(str(envs_dir))
