"""The grid grammar shared by sweeps (``sweep.grid``) and batched scenarios (``batch_grid``).

A grid is a mapping ``{key: [values…]}``; its points are the cartesian product in key order, each a
``{key: value}`` dict that becomes command-line style overrides (``key=value``).
"""

from __future__ import annotations

import hashlib
import itertools
import shlex
from collections.abc import Mapping
from typing import Any

SCENARIO_PREFIXES = ("env.", "reward.")
"""Config keys that describe the scenario (the model), as opposed to the method or the run."""


def override_key(override: str) -> str:
    """The key of a command-line override: ``+env.p1.speed=0.5`` → ``env.p1.speed``."""
    return override.split("=", 1)[0].lstrip("+~")


def is_learner_key(key_or_override: str) -> bool:
    """Whether a key (or an override) sets the learner itself: ``algo…`` or ``network…`` (what a
    profile of a benchmark or the study may set; the rest is theirs)."""
    return override_key(key_or_override).split(".")[0] in ("algo", "network")


def is_scenario_key(key_or_override: str) -> bool:
    """Whether a key (or an override ``key=value``) sets an ``env.`` or ``reward.`` value."""
    return override_key(key_or_override).startswith(SCENARIO_PREFIXES)


def format_value(value: Any) -> str:
    """A value as Hydra's override grammar reads it back (lists as ``[a,b]``, None as ``null``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return "[" + ",".join(format_value(v) for v in value) + "]"
    return str(value)


def parse_grid(grid: Any, name: str = "sweep.grid") -> list[dict[str, Any]]:
    """All points of a grid ``{key: [values…]}`` (the cartesian product, in key order).

    Args:
        grid: the mapping.
        name: the config key holding it, for error messages.

    Raises:
        ValueError: empty or malformed grid (not a mapping, a key without values, a value that is
            not a non-empty list, a duplicate value).
    """
    if grid is None or (isinstance(grid, Mapping) and not grid):
        example = "{env.p1.speed: [0.1,1.0]}" if name == "batch_grid" else "{seed: [0,1,2]}"
        raise ValueError(f"{name} is empty: give it as {name}='{example}'")
    if not isinstance(grid, Mapping):
        raise ValueError(f"{name}={grid!r} must be a mapping of override key → list of values")
    for key, values in grid.items():
        if not isinstance(key, str) or not key or "=" in key:
            raise ValueError(f"{name} key {key!r} must be a config key such as env.p1.speed")
        if not isinstance(values, list) or not values:
            raise ValueError(f"{name}.{key}={values!r} must be a non-empty list of values")
        if len({format_value(v) for v in values}) != len(values):
            raise ValueError(f"{name}.{key}={values!r} repeats a value")
    keys = list(grid)
    return [
        dict(zip(keys, combo, strict=True)) for combo in itertools.product(*(grid[k] for k in keys))
    ]


def point_overrides(point: Mapping[str, Any]) -> list[str]:
    """A grid point as override strings."""
    return [f"{k}={format_value(v)}" for k, v in point.items()]


def point_id(
    point: Mapping[str, Any], method: str = "", base: list[str] | tuple[str, ...] = ()
) -> str:
    """Stable id of a grid point: readable prefix + hash of its overrides (order-independent),
    of the method and of the base overrides (so two sweeps of one grid with different bases, or
    methods, never share a trial directory). The prefix names each key by its last part and a
    path by its file: ``speed=0.5_seed=0__…``, ``learner=watchful.py-Watchful__…``."""
    ov = sorted(point_overrides(point))
    key = "|".join(ov) + (f"||{method}||" + "|".join(base) if method or base else "")
    digest = hashlib.sha1(key.encode()).hexdigest()[:10]
    readable = "_".join(
        f"{k.rsplit('.', 1)[-1]}={v.rsplit('/', 1)[-1]}" for k, v in (o.split("=", 1) for o in ov)
    )
    safe = "".join(c if c.isalnum() or c in "=_.-" else "-" for c in readable)[:60]
    return f"{safe}__{digest}"


def scenario_of(overrides: list[str]) -> str:
    """Scenario name as the recipes write it: the env choice plus env./reward. overrides."""
    env = next((o.split("=", 1)[1] for o in overrides if o.startswith("env=")), "paper")
    extra = [o for o in overrides if is_scenario_key(o)]
    return f"{env}[{','.join(extra)}]" if extra else env


def candidate_overrides(candidates: Any, key: str = "candidates") -> dict[str, list[str]]:
    """The candidates compared: name → overrides (one, the default, when unset: ``None``). An
    empty mapping is refused: it would compare nothing."""
    raw = {"dqn": []} if candidates is None else candidates
    if not isinstance(raw, dict) or not raw:
        example = "{p01: [env.p1.speed=0.1]}" if key == "scenarios" else "{dqn: []}"
        raise ValueError(
            f"{key}={raw} must map names to lists of overrides, e.g. {example} (null: the default)"
        )
    out = {}
    for name, extra in raw.items():
        if not isinstance(extra, list) or not all(isinstance(o, str) and "=" in o for o in extra):
            raise ValueError(f"{key}.{name} must be a list of overrides (key=value)")
        out[str(name)] = list(extra)
    return out


def require_runs(count: int, parts: str) -> None:
    """Refuse a benchmark whose lists leave it nothing to run: ``parts`` names the lists whose
    product makes each of its parts (e.g. ``learners × seeds``)."""
    if count == 0:
        raise ValueError(f"nothing to run: each part is empty ({parts}); give one a value")


def shell_quote(arg: str) -> str:
    """``arg`` quoted for a POSIX shell, readably: single quotes as ``shlex.quote`` gives, or double
    quotes when the argument holds single quotes and nothing a shell expands inside double quotes."""
    quoted = shlex.quote(arg)
    if "'" in arg and not any(c in arg for c in '"$`\\!'):
        return f'"{arg}"'
    return quoted
