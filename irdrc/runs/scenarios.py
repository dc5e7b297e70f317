"""The named scenarios (``irdrc/scenarios/*.yaml``, the config group ``env``, package data: an
installed wheel has them too): listed with their purposes, loaded with their ``defaults``, given as
``Params`` (``irdrc.scenario``) and registered with Hydra.

A scenario file holds the ``env`` keys of MODEL.md, its purpose on its first line. It may start with
``defaults: [other]`` to take another scenario's values first and override some of them
(``ref_impl.yaml`` does). A file of the user's, anywhere, is a scenario too: ``env=PATH.yaml`` on
the command line, ``irdrc.scenario(PATH.yaml)`` in Python (its ``defaults`` name scenarios of
irdrc or files beside it; without them it starts from ``paper``).
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

FILE_SUFFIXES = (".yaml", ".yml")
"""A scenario given by its file (``env=PATH.yaml``) rather than by name ends with one of these."""


def scenario_file(value: str) -> Path | None:
    """The scenario file ``value`` names (it ends with .yaml or .yml), as an absolute path; None for
    a scenario's name.

    Raises:
        ValueError: no such file.
    """
    if not str(value).endswith(FILE_SUFFIXES):
        return None
    path = Path(value).expanduser().resolve()
    if not path.is_file():
        raise ValueError(f"env={value}: no such scenario file ({path})")
    return path


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

    file = scenario_file(name)
    path = file or envs_dir / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(
            f"env={name!r} is not a scenario; available: {', '.join(list_scenarios(envs_dir))}, "
            "or a scenario file of your own (env=PATH.yaml)"
        )
    if file is not None:
        name = str(file)
    if name in _seen:
        raise ValueError(f"scenario defaults form a cycle: {' -> '.join((*_seen, name))}")
    try:
        node = OmegaConf.load(path)
    except Exception as err:  # YAML's own error, one line
        raise ValueError(f"{path}: not a YAML file ({str(err).splitlines()[0]})") from None
    if not isinstance(node, DictConfig):
        raise ValueError(f"{path}: a scenario file holds a mapping of env keys, not a list")
    # a file of the user's without defaults takes the paper's values first, as the command line does
    bases = node.pop("defaults", ["paper"] if file is not None else [])
    if isinstance(bases, str):  # defaults: paper, one name without its list
        bases = [bases]
    merged: Any = OmegaConf.create()
    for base in bases:
        if base != "_self_":
            base = str(base)
            if file is not None and base.endswith(FILE_SUFFIXES):
                base = str(file.parent / base)  # a file beside this one
            merged = OmegaConf.merge(merged, load_scenario(base, envs_dir, (*_seen, name)))
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


def register_scenario_file(path: Path) -> str:
    """Put the scenario file ``path`` into Hydra's ConfigStore (group ``env``) under a name of its
    own, read now; returns that name."""
    import hashlib

    from hydra.core.config_store import ConfigStore

    name = "file_" + hashlib.sha256(str(path).encode()).hexdigest()[:16]
    ConfigStore.instance().store(group="env", name=name, node=load_scenario(str(path)))
    return name


def scenario_file_overrides(args: list[str]) -> tuple[list[str], dict[str, str]]:
    """``args`` with each ``env=PATH.yaml`` (a scenario file of the user's) given as the name it
    is registered under with Hydra, and each such name → the file's absolute path."""
    out, files = [], {}
    for o in args:
        key = o.split("=", 1)[0].lstrip("+~")
        path = scenario_file(o.split("=", 1)[1]) if key == "env" and "=" in o else None
        if path is None:
            out.append(o)
            continue
        name = register_scenario_file(path)
        files[name] = str(path)
        out.append(f"{o.split('=', 1)[0]}={name}")
    return out, files
