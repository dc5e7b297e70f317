"""A recipe's config, composed once: Hydra's config groups (``irdrc/conf``, shipped inside the
package; the group ``env`` is the named scenarios of ``irdrc.runs.scenarios``) and its override
grammar, one compose per run, turned into plain containers at once."""

from __future__ import annotations

import copy
import dataclasses
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

from irdrc.core.checks import closest
from irdrc.core.overrides import refuse_share_keys
from irdrc.runs.grid import is_scenario_key, override_key
from irdrc.runs.scenarios import (
    FILE_SUFFIXES,
    list_scenarios,
    register_scenarios,
    scenario_file_overrides,
)

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
"""The recipes' Hydra configs (``dqn.yaml``, ``algo/``, …), package data."""

FIXED = {
    "optimum_gamma": "set optimum_gamma=…, which every run and ratio reads",
    "eval.mc_episodes": "its runs are scored exactly, not by Monte Carlo episodes",
    "checkpoint.every_frames": "its runs keep no checkpoints",
    "eval.every_frames": "set eval.every_frames=…",
}
"""Keys a many-run recipe sets for every run after its ``overrides`` (scoring, checkpoints), with
what to do instead: ``Composed.refuse_overwritten(fixed=…)`` refuses them in an overrides list."""

OPTIONAL_KEYS = (
    "env.factors",
    "env.bursty",
    "env.detection_prob",
    "env.false_alarm_prob",
    "env.actions",
    "env.levels",
    "env.sensing",
    "env.dwell_gain",
    "reward.r5",
)
"""Optional keys of the general model (MODEL.md § B, § D): absent from v1 scenarios, so an override of
one adds it (Hydra's ``++``); ``Params`` validates them."""


def recipe_call(name: str) -> str:
    """What follows ``python`` to run recipe ``name`` from the working directory: its script
    (``recipes/NAME.py``) in a checkout of irdrc, else ``-m irdrc NAME`` (the installed package;
    it works from any directory)."""
    return (
        f"recipes/{name}.py" if (Path("recipes") / f"{name}.py").is_file() else f"-m irdrc {name}"
    )


def config_groups() -> list[str]:
    """Config groups a command line may choose (``env=…``, ``algo=…``, …)."""
    return sorted(["env", *(p.name for p in CONF_DIR.iterdir() if p.is_dir())])


def group_options(group: str) -> list[str]:
    """The options of a config group."""
    if group == "env":
        return list_scenarios()
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


@dataclass(frozen=True)
class Composed:
    """One composed config: ``cfg`` (plain containers, resolved), the group ``choices``, the
    command line's ``task`` overrides, the run directory Hydra's ``hydra.run.dir`` names."""

    name: str
    cfg: dict[str, Any]
    choices: dict[str, str]
    task: list[str]
    run_dir: str

    @property
    def scenario(self) -> str:
        """The scenario as runs name it: the ``env`` choice, plus any ``env.*`` / ``reward.*``
        overrides in brackets (``paper[env.p1.speed=0.5,reward.r4=50]``)."""
        name = self.choices.get("env") or "custom"
        if name.endswith(FILE_SUFFIXES):  # a scenario file: its file name
            name = Path(name).name
        extra = [o.removeprefix("++") for o in self.task if is_scenario_key(o)]
        return f"{name}[{','.join(extra)}]" if extra else name

    @property
    def scenario_overrides(self) -> list[str]:
        """The scenario as overrides: the ``env`` and ``reward`` choices and the ``env.*`` /
        ``reward.*`` overrides (what a recipe passes on to the runs it plans)."""
        out = [f"{g}={self.choices[g]}" for g in ("env", "reward") if self.choices.get(g)]
        return out + [o for o in self.task if is_scenario_key(o)]

    @property
    def explicit(self) -> frozenset[str]:
        """The keys the command line set (groups included)."""
        return frozenset(override_key(o) for o in self.task)

    def refuse_unread(self, keys: Iterable[str], why: str) -> None:
        """Refuse a key of the command line this run does not read: one of ``keys``, or a key of
        one of those sections (``algo`` covers ``algo.lr``), named with ``why``. A value nothing
        reads would otherwise be taken without a word; one that asks for nothing (``[]``, ``{}``,
        ``null``) passes."""
        keys = tuple(keys)
        for o in self.task:
            key, value = override_key(o), o.partition("=")[2].strip()
            if value in ("[]", "{}", "null"):
                continue
            if any(key == k or key.startswith(f"{k}.") for k in keys):
                raise ValueError(f"{o.lstrip('+')}: {why}")

    def refuse_overwritten(
        self, axes: dict[str, str], overrides: Any = (), fixed: tuple[str, ...] = ()
    ) -> None:
        """Refuse a key the recipe sets per run itself (``axes``: the key → what to do instead)
        where the command line's scenario (``env.*``, ``reward.*``: passed on to every run) or the
        recipe's ``overrides`` list sets it too: the runs would overwrite it without a word. (A key
        of the recipe's own on its command line, ``eval.every_frames=…``, is not passed on.)
        ``fixed`` names keys of ``FIXED`` the recipe sets for every run after the overrides."""
        axes = {**axes, **{key: FIXED[key] for key in fixed}}
        scenario = [o for o in self.task if is_scenario_key(o)]
        given = {override_key(o): o.lstrip("+") for o in [*scenario, *map(str, overrides)]}
        for key, instead in axes.items():
            if key in given:
                raise ValueError(
                    f"{given[key]} would be overwritten: {self.name} sets {key} per run; {instead}"
                )


def _primary(config_name: str) -> dict[str, Any]:
    """The recipe's own YAML file, unmerged (no compose): which of its keys hold mappings."""
    from omegaconf import OmegaConf

    path = CONF_DIR / f"{config_name}.yaml"
    node = OmegaConf.to_container(OmegaConf.load(path), resolve=False) if path.is_file() else {}
    return cast(dict[str, Any], node) if isinstance(node, dict) else {}


def _select(node: Any, key: str) -> Any:
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def prepare_overrides(config_name: str, overrides: list[str]) -> list[str]:
    """The command line as Hydra takes it: ``key={…}`` for a key whose default is a mapping
    (``profiles={…}``) replaces it (``~key`` then ``+key=…``, not a merge), an optional key of
    the general model is added where the scenario lacks it (``++``), and so is a key of a section
    the recipe leaves open (``algo: {}`` in ``online.yaml``: its keys are the chosen learner's,
    checked by the recipe)."""
    primary, out = _primary(config_name), []
    for o in overrides:
        key = override_key(o)
        section = _select(primary, key.split(".")[0]) if "." in key else None
        if "={" in o and o[0] not in "+~" and isinstance(_select(primary, key), dict):
            out += [f"~{key}", f"+{o}"]
        elif (o[0] not in "+~" and "=" in o and key.startswith(OPTIONAL_KEYS)) or (
            o[0] not in "+~" and "=" in o and section == {}
        ):
            out.append(f"++{o}")
        else:
            out.append(o)
    return out


def _initialised() -> Any:
    """Hydra initialised on ``irdrc/conf`` for one compose (global state restored after)."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    class _Scope:
        def __enter__(self) -> None:
            gh = GlobalHydra.instance()
            self.saved = gh.hydra if gh.is_initialized() else None
            gh.clear()
            self.ctx = initialize_config_dir(config_dir=str(CONF_DIR), version_base=None)
            self.ctx.__enter__()

        def __exit__(self, *exc: Any) -> None:
            self.ctx.__exit__(*exc)
            gh = GlobalHydra.instance()
            gh.clear()
            if self.saved is not None:
                gh.initialize(self.saved)

    return _Scope()


def compose(
    config_name: str, overrides: list[str] | tuple[str, ...] = (), algo_keys: Any = ()
) -> Composed:
    """Compose ``irdrc/conf/<config_name>.yaml`` with command-line ``overrides`` — once — into
    plain containers. ``hydra.*`` overrides set the run's own settings (``hydra.run.dir``).
    ``algo_keys`` (a recipe's ``ALGO_KEYS``) are the ``algo.`` keys an unknown key's hint may name
    beside those the composed files hold (a profile lists only the keys that act in its run).

    Raises:
        ValueError: an unknown key (naming the closest valid one), an unknown group option, or an
            override Hydra cannot parse — one line each.
    """
    from hydra import compose as hydra_compose
    from omegaconf import OmegaConf, open_dict

    register_scenarios()
    args = prepare_overrides(config_name, [str(o) for o in overrides])
    args, files = scenario_file_overrides(args)
    _check_choices(config_name, args, files)
    try:
        with _initialised():
            cfg = hydra_compose(config_name=config_name, overrides=args, return_hydra_config=True)
    except Exception as err:  # Hydra's own errors: one line each
        raise ValueError(_explain(config_name, args, err, algo_keys)) from None
    hydra = cfg.hydra
    choices = {k: str(v) for k, v in hydra.runtime.choices.items() if not k.startswith("hydra")}
    task = [str(o) for o in hydra.overrides.task if not override_key(str(o)).startswith("hydra")]
    if choices.get("env") in files:  # a scenario file: named by its path, wherever it is read
        choices["env"] = files[choices["env"]]
        task = [f"env={choices['env']}" if override_key(o) == "env" else o for o in task]
    run_dir = str(hydra.run.dir)
    with open_dict(cfg):
        del cfg["hydra"]
    plain = cast(dict[str, Any], OmegaConf.to_container(cfg, resolve=True))
    if isinstance(env := plain.get("env"), dict):  # a radar-share key for whole-step modes
        refuse_share_keys(
            env.get("actions", "binary"), {override_key(o): o.lstrip("+") for o in task}
        )
    return Composed(config_name, plain, choices, task, run_dir)


def _groups_of(config_name: str) -> set[str]:
    """The config groups a recipe's defaults list chooses from."""
    out = set()
    for entry in _primary(config_name).get("defaults", []):
        if isinstance(entry, dict):
            out |= {str(k).split("/")[-1].split("@")[0] for k in entry}
    return out


def _check_choices(config_name: str, args: list[str], files: Any = ()) -> None:
    """An unknown option of a config group, named with the options; a group the recipe has no
    choice of, naming the recipes that do. ``files``: the names scenario files are registered
    under (``scenario_file_overrides``)."""
    groups = config_groups()
    mine = _groups_of(config_name)
    for o in args:
        key = override_key(o)
        if "=" in o and o[0] not in "+~" and key in groups:
            value = o.split("=", 1)[1]
            if key not in mine:
                users = sorted(p.stem for p in CONF_DIR.glob("*.yaml") if key in _groups_of(p.stem))
                raise ValueError(
                    f"{config_name} has no {key}: {key}= is for "
                    + ", ".join(f"python {recipe_call(u)}" for u in users)
                )
            if value not in group_options(key) and value not in files:
                options = ", ".join(group_options(key))
                own = ", or a scenario file of your own (env=PATH.yaml)" if key == "env" else ""
                raise ValueError(f"{key}={value!r} is not a choice of {key}: {options}{own}")


def _explain(config_name: str, args: list[str], err: Exception, algo_keys: Any = ()) -> str:
    """Hydra's error as one line; an unknown key with the closest valid key (``algo_keys``: as
    ``compose``'s)."""
    import re

    found = re.search(r"Could not override '([^']+)'", str(err))
    if found:
        bad = next((a for a in args if override_key(a) == found.group(1)), "")
        known = _known_keys(config_name, args, bad) | {f"algo.{k}" for k in algo_keys}
        return unknown_key(config_name, found.group(1), known)
    text = str(err).strip().splitlines()[0] if str(err).strip() else ""
    ambiguous = re.search(r"Ambiguous value for argument '([^']+)'", str(err))
    if ambiguous:
        key, _, value = ambiguous.group(1).partition("=")
        return (
            f"{key}={value}: one run takes one value (where the key takes a list: {key}='[{value}]'); "
            f"several runs over values: python recipes/sweep.py method=… "
            f"sweep.grid='{{{key}: [{value}]}}'"
        )
    merging = re.search(r"Error merging override ([^=\s]+)=(.)", str(err))
    if merging and "Cannot merge" in str(err.__cause__ or ""):  # a list for a mapping, or back
        key, given = merging.groups()
        if given == "[":
            return (
                f"{key} is a mapping, not a list: set one of its keys ({key}.KEY=…), or all of "
                f"it as {key}='{{KEY: …}}'"
            )
        return f"{key} is a list, not a mapping: {key}='[…]'"
    if type(err).__name__ == "OverrideParseException":
        for arg in args:
            key, _, value = arg.partition("=")
            if value[:1] in "[{" and value[-1:] in "]}" and "=" in value:
                quoted = re.sub(r"\[([^\[\]]*)\]", lambda m: f"[{_quote_items(m.group(1))}]", value)
                return (
                    f"{arg}: a list element that holds '=' is quoted, the whole argument too: "
                    f'"{key}={quoted}" ({text})'
                )
    return f"{type(err).__name__}: {text}"


def _quote_items(items: str) -> str:
    """A list's comma-separated ``items`` with each one that holds '=' in quotes."""
    out = [v.strip() for v in items.split(",") if v.strip()]
    return ",".join(v if v[0] in "'\"" or "=" not in v else f"'{v}'" for v in out)


def unknown_key(config_name: str, key: str, known: set[str]) -> str:
    """The one line that refuses an unknown ``key``, with the closest of the ``known`` keys: the
    one known key whose name is the same or ends it (``total_frames`` → ``algo.total_frames``,
    ``gamma`` → ``optimum_gamma``, ``algo.eval_every_episodes`` → ``algo.episodes``), else the
    closest spelling: within the key's own section when that section exists, if any is close."""
    parent, _, leaf = key.rpartition(".")
    same = [
        k
        for k in known
        if (name := k.rpartition(".")[2]) == leaf
        or name.endswith("_" + leaf)
        or leaf.endswith("_" + name)
    ]
    siblings = {k.rpartition(".")[2]: k for k in known if k.rpartition(".")[0] == parent}
    near: str | None = None
    if len(same) == 1:
        near = same[0]
    elif parent and siblings:  # a known section: only its own keys, by their names
        near = siblings.get(closest(leaf, siblings) or "")
    else:
        near = closest(key, known)
    hint = f"; did you mean {near}?" if near and near != key else ""
    return f"unknown key {key!r} in {config_name}{hint} ({config_name}.yaml has no such key)"


def _known_keys(config_name: str, args: list[str], bad: str = "") -> set[str]:
    """Every dotted key of the recipe's config composed without the bad override (an error's
    hint only: this second compose runs only on the way to a refusal)."""
    from hydra import compose as hydra_compose
    from omegaconf import OmegaConf

    rest = [a for a in args if a != bad and not override_key(a).startswith("hydra")]
    try:
        with _initialised():
            cfg = hydra_compose(config_name=config_name, overrides=rest)
    except Exception:
        return set()
    return _flat_keys(OmegaConf.to_container(cfg, resolve=False)) | set(config_groups())


def _flat_keys(node: Any, prefix: str = "") -> set[str]:
    out = set()
    if isinstance(node, dict):
        for k, v in node.items():
            out.add(f"{prefix}{k}")
            out |= _flat_keys(v, f"{prefix}{k}.")
    return out


def stored_overrides(args: list[str]) -> tuple[list[str], list[str]]:
    """With ``resume=true hydra.run.dir=DIR``, the command line completed by the overrides the run
    in DIR was started with (its ``.hydra/overrides.yaml``; what the command line sets wins), so a
    sweep, a figure or a benchmark goes on with its own grid; and the overrides taken from there."""
    from omegaconf import OmegaConf

    values = {override_key(a): a.split("=", 1)[1] for a in args if "=" in a}
    run_dir = values.get("hydra.run.dir")
    if str(values.get("resume", "")).lower() != "true" or not run_dir:
        return args, []
    record = Path(run_dir.strip("'\"")).expanduser() / ".hydra" / "overrides.yaml"
    if not record.is_file():
        return args, []
    taken = [
        str(o)
        for o in OmegaConf.load(record)
        if override_key(str(o)) not in values and not override_key(str(o)).startswith("hydra")
    ]
    return [*taken, *args], taken


def with_profile_keys(args: list[str], keys: Any) -> list[str]:
    """``args`` with every ``algo.K=…`` whose K is one of ``keys`` (a recipe's ``ALGO_KEYS``: every
    key its learner reads) added where the chosen profile's file leaves it out (``++``): a profile
    lists the keys that act in its run, and the others keep their defaults until a command line
    sets them."""
    keys = set(keys or ())
    out = []
    for a in args:
        key = override_key(a)
        if a[0] not in "+~" and "=" in a and key.startswith("algo.") and key[5:] in keys:
            a = f"++{a}"
        out.append(a)
    return out


def compose_recipe(module: Any, args: list[str]) -> Composed:
    """``module``'s config (a recipe module: its ``NAME``, ``ALGO_KEYS`` and, where the command line
    decides more, ``algo_keys(args)``) composed with ``args``, a profile's omitted keys taking the
    command line's values (``with_profile_keys``)."""
    keys = {*getattr(module, "ALGO_KEYS", ())}
    if (more := getattr(module, "algo_keys", None)) is not None:
        keys |= more(args)
    return compose(module.NAME, with_profile_keys(args, keys), keys)


def recorded(module: Any, config: Any, composed: Composed) -> Composed:
    """``composed`` as the run of ``module``'s typed ``config`` records it (``config.yaml``, the
    checkpoint): with what the recipe resolves in Python written in, where the module has
    ``recorded(config, cfg)`` (a learner's whole profile)."""
    record = getattr(module, "recorded", None)
    if record is None:
        return composed
    return dataclasses.replace(composed, cfg=record(config, composed.cfg))


class SeededCompose:
    """``compose_recipe`` for many runs of one recipe (a sweep's points): runs whose overrides differ
    only in an integer ``seed=`` share one Hydra composition, and each gets a copy with its own
    seed — the same ``Composed`` a fresh composition gives (Hydra reads ``seed=7`` as the integer
    7; no config value refers to the seed). Composing takes about a quarter of a second, and a
    benchmark plans hundreds of runs."""

    def __init__(self, module: Any):
        self.module = module
        self._shared: dict[tuple[str, ...], Composed] = {}

    def __call__(self, args: list[str]) -> Composed:
        at = [i for i, a in enumerate(args) if override_key(a) == "seed"]
        if len(at) != 1 or not re.fullmatch(r"seed=-?\d+", args[at[0]]):
            return compose_recipe(self.module, args)
        i = at[0]
        key = (*args[:i], "seed=*", *args[i + 1 :])
        if key not in self._shared:
            self._shared[key] = compose_recipe(self.module, args)
        shared, seed = self._shared[key], int(args[i].split("=", 1)[1])
        cfg = copy.deepcopy(shared.cfg)
        cfg["seed"] = seed
        task = [f"seed={seed}" if override_key(t) == "seed" else t for t in shared.task]
        return dataclasses.replace(shared, cfg=cfg, choices=dict(shared.choices), task=task)
