"""Scenarios (``envs/*.yaml``) and Hydra wiring shared by the recipes.

A scenario file holds the ``env`` keys of MODEL.md. It may start with ``defaults: [other]`` to take
another scenario's values first and override some of them (``ref_impl.yaml`` does).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

ROOT = Path(__file__).resolve().parents[1]
ENVS_DIR = ROOT / "envs"
CONF_DIR = ROOT / "recipes" / "conf"


def list_scenarios(envs_dir: Path = ENVS_DIR) -> list[str]:
    """Names of the scenarios in ``envs/``."""
    return sorted(p.stem for p in envs_dir.glob("*.yaml"))


def load_scenario(name: str, envs_dir: Path = ENVS_DIR, _seen: tuple[str, ...] = ()) -> DictConfig:
    """The ``env`` config of scenario ``name``, its ``defaults`` resolved.

    Raises:
        ValueError: unknown scenario, or a cycle in ``defaults``.
    """
    path = envs_dir / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(
            f"env={name!r} is not a scenario; available: {', '.join(list_scenarios(envs_dir))}"
        )
    if name in _seen:
        raise ValueError(f"scenario defaults form a cycle: {' -> '.join((*_seen, name))}")
    node = OmegaConf.load(path)
    bases = node.pop("defaults", [])
    merged = OmegaConf.create()
    for base in bases:
        if base == "_self_":
            continue
        merged = OmegaConf.merge(merged, load_scenario(str(base), envs_dir, (*_seen, name)))
    return OmegaConf.merge(merged, node)


def register_scenarios(envs_dir: Path = ENVS_DIR) -> None:
    """Put every scenario into Hydra's ConfigStore as the config group ``env``.

    The recipes call this before ``hydra.main`` so that ``env=ref_impl`` picks ``envs/ref_impl.yaml``.
    """
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    for name in list_scenarios(envs_dir):
        cs.store(group="env", name=name, node=load_scenario(name, envs_dir))


def scenario_name(cfg: Any = None) -> str:
    """The scenario a recipe ran: the Hydra choice of ``env``, plus any ``env.*`` / ``reward.*``
    command-line overrides in brackets (``paper[env.p1.speed=0.5,reward.r4=50]``); ``custom``
    outside a Hydra app."""
    try:
        from hydra.core.hydra_config import HydraConfig

        hc = HydraConfig.get()
    except Exception:
        return "custom"
    name = str(hc.runtime.choices.get("env", "custom"))
    extra = [
        o for o in hc.overrides.task if o.split("=")[0].lstrip("+~").startswith(("env.", "reward."))
    ]
    return f"{name}[{','.join(extra)}]" if extra else name


def scenario_overrides() -> list[str]:
    """The running Hydra app's scenario as overrides: its ``env`` and ``reward`` choices plus any
    ``env.*`` / ``reward.*`` command-line overrides (what a recipe passes on to the runs it plans)."""
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    out = [f"{g}={hc.runtime.choices[g]}" for g in ("env", "reward") if hc.runtime.choices.get(g)]
    out += [
        o for o in hc.overrides.task if o.split("=")[0].lstrip("+~").startswith(("env.", "reward."))
    ]
    return out


def compose(config_name: str, overrides: list[str] | None = None) -> DictConfig:
    """Compose ``recipes/conf/<config_name>.yaml`` with command-line style ``overrides``.

    Works inside or outside a running Hydra app (the global Hydra state is restored afterwards).
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    register_scenarios()
    gh = GlobalHydra.instance()
    saved = gh.hydra if gh.is_initialized() else None
    gh.clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
            return hydra_compose(config_name=config_name, overrides=list(overrides or []))
    finally:
        gh.clear()
        if saved is not None:
            gh.initialize(saved)
