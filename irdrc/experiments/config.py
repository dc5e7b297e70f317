"""Scenarios (``envs/*.yaml``) and Hydra wiring shared by the recipes.

A scenario file holds the ``env`` keys of MODEL.md. It may start with ``defaults: [other]`` to take
another scenario's values first and override some of them (``ref_impl.yaml`` does).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from irdrc.experiments.grid import is_scenario_key, override_key

ROOT = Path(__file__).resolve().parents[2]
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
    extra = [o for o in hc.overrides.task if is_scenario_key(o)]
    return f"{name}[{','.join(extra)}]" if extra else name


def scenario_overrides() -> list[str]:
    """The running Hydra app's scenario as overrides: its ``env`` and ``reward`` choices plus any
    ``env.*`` / ``reward.*`` command-line overrides (what a recipe passes on to the runs it plans)."""
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    out = [f"{g}={hc.runtime.choices[g]}" for g in ("env", "reward") if hc.runtime.choices.get(g)]
    out += [o for o in hc.overrides.task if is_scenario_key(o)]
    return out


RENAMED = {
    "solve": {
        "gamma": "optimum_gamma",
        "mc_episodes": "eval.mc_episodes",
        "num_envs": "eval.mc_num_envs",
    },
    "qlearning": {"mc_episodes": "eval.mc_episodes", "num_envs": "eval.mc_num_envs"},
    "figure2": {"dqn_eval_every_frames": "eval.every_frames"},
    "demo": {"num_envs": "eval.mc_num_envs", "episodes": "eval.mc_episodes"},
    "bench_dqn": {"eval_every_frames": "eval.every_frames"},
}
"""Per recipe: config keys renamed when every recipe got one name per idea (old → new). The old
names keep working on the command line and in sweeps, with a note."""

REMOVED = {
    "qlearning": {
        "algo.eval_every_episodes": "use eval.every_frames (env steps: episodes × env.horizon)",
    },
}
"""Per recipe: keys that no longer exist, and what to use instead."""


def replace_mappings(config_name: str, overrides: list[str]) -> list[str]:
    """``key={…}`` for a key whose default is a mapping (``bench_dqn.py profiles={…}``) becomes
    ``~key`` and ``+key={…}``: the new mapping replaces the default instead of being merged into
    it (Hydra refuses keys the default does not have)."""
    mapped = [o for o in overrides if "={" in o and o[0] not in "+~"]
    if not mapped:
        return list(overrides)
    base = _default_config(config_name)
    out = []
    for o in overrides:
        key = override_key(o)
        if o in mapped and isinstance(OmegaConf.select(base, key, default=None), DictConfig):
            out += [f"~{key}", f"+{o}"]
        else:
            out.append(o)
    return out


def _default_config(config_name: str) -> DictConfig:
    """The recipe's config with no overrides (cached)."""
    if config_name not in _DEFAULTS:
        _DEFAULTS[config_name] = compose(config_name, [])
    return _DEFAULTS[config_name]


_DEFAULTS: dict[str, DictConfig] = {}


def rename_overrides(config_name: str, overrides: list[str]) -> tuple[list[str], list[str]]:
    """Command-line overrides with renamed keys (``RENAMED``) replaced by their new names, and
    mappings replaced whole (``replace_mappings``).

    Returns:
        (the overrides, one note per renamed key).

    Raises:
        ValueError: an override sets a removed key (``REMOVED``), naming what to use instead.
    """
    renamed, removed = RENAMED.get(config_name, {}), REMOVED.get(config_name, {})
    out, notes = [], []
    for o in overrides:
        key = override_key(o)
        if key in removed:
            raise ValueError(f"{key} no longer exists: {removed[key]}")
        if key in renamed and "=" in o:
            prefix = o[: len(o) - len(o.lstrip("+~"))]
            o = f"{prefix}{renamed[key]}={o.split('=', 1)[1]}"
            notes.append(f"note: {key} is now {renamed[key]} (the old name still works for now)")
        out.append(o)
    return replace_mappings(config_name, out), notes


def compose(config_name: str, overrides: list[str] | None = None) -> DictConfig:
    """Compose ``recipes/conf/<config_name>.yaml`` with command-line style ``overrides``.

    Renamed keys are accepted (``RENAMED``). Works inside or outside a running Hydra app (the
    global Hydra state is restored afterwards).
    """
    overrides, _ = rename_overrides(config_name, list(overrides or []))
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
