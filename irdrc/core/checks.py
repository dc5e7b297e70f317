"""The shared checks every layer's configs use: numbers, choices, flags, lists, unknown keys, and the
builder that turns a plain mapping into a frozen config dataclass.

Every check raises a ``ValueError`` naming the key as the user types it (``env.p1.speed``,
``algo.lr``), the value and what is allowed, in one line. Pure Python (no torch, no OmegaConf), so a
recipe can check its whole command line before anything heavy is imported.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any


def grouped(x: float, digits: int = 0) -> str:
    """``x`` for a message or a table, its thousands set apart by spaces: ``100 800``, ``1 461.5``."""
    return f"{x:,.{digits}f}".replace(",", " ")


def counted(n: int, noun: str) -> str:
    """``n noun`` for a message, the noun plural unless ``n`` is 1: ``1 seed``, ``3 seeds``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def check_number(
    key: str,
    value: Any,
    lo: float = -math.inf,
    hi: float = math.inf,
    *,
    integer: bool = False,
    open_lo: bool = False,
    open_hi: bool = False,
) -> Any:
    """``value`` as an int or float if it is a finite number within the bounds, else a ``ValueError``
    naming ``key``, the value and the allowed range (``open_lo`` / ``open_hi`` exclude a bound)."""
    kind = "an integer" if integer else "a number"
    left, right = "(" if open_lo else "[", ")" if open_hi else "]"
    if hi == math.inf:
        bounds = f"> {lo}" if open_lo else f">= {lo}"
    elif lo == -math.inf:
        bounds = f"< {hi}" if open_hi else f"<= {hi}"
    else:
        bounds = f"{left}{lo}, {hi}{right}"
    if isinstance(value, bool) or not isinstance(value, int | float):
        where = "in " if lo > -math.inf and hi < math.inf else ""
        raise ValueError(f"{key}={value!r} must be {kind} {where}{bounds}")
    if integer and not (
        isinstance(value, int) or (math.isfinite(value) and float(value).is_integer())
    ):
        raise ValueError(f"{key}={value!r} must be {kind} (a whole number)")
    ok = (lo < value if open_lo else lo <= value) and (value < hi if open_hi else value <= hi)
    if not math.isfinite(value) or not ok:
        raise ValueError(f"{key}={value!r} is outside the allowed range {bounds}")
    return int(value) if integer else float(value)


INT = {"integer": True}
OPEN_HI = {"open_hi": True}
"""Keywords of ``check_number`` for the spec tables of ``check_numbers``."""

NumberSpec = tuple[str, float, float, dict[str, bool]]
"""One row of ``check_numbers``' specs: (field, low, high, ``check_number`` keywords)."""


def check_numbers(obj: Any, prefix: str, specs: Iterable[NumberSpec]) -> None:
    """Check, and set as checked, the numeric fields of a frozen dataclass ``obj`` from its own
    ``__post_init__``: ``specs`` holds (field, low, high, ``check_number`` keywords) each; the key
    in messages is ``prefix`` + field."""
    for key, lo, hi, kw in specs:
        value = check_number(f"{prefix}{key}", getattr(obj, key), lo, hi, **kw)
        object.__setattr__(obj, key, value)


def check_choice(key: str, value: Any, choices: Iterable[Any]) -> Any:
    """``value`` if it is one of ``choices``, else a ``ValueError`` naming the key and the choices."""
    choices = list(choices)
    wrong_type = isinstance(value, bool) and not any(isinstance(c, bool) for c in choices)
    if wrong_type or value not in choices:
        raise ValueError(f"{key}={value!r} must be one of {', '.join(map(str, choices))}")
    return value


def check_bool(key: str, value: Any) -> bool:
    """``value`` if it is true or false, else a ``ValueError`` naming the key."""
    if not isinstance(value, bool):
        raise ValueError(f"{key}={value!r} must be true or false")
    return value


def check_file_name(key: str, value: Any) -> str:
    """``value`` if it is a plain file name (a file the run writes into its own directory), else
    a ``ValueError`` naming the key (a path elsewhere is set by ``hydra.run.dir``)."""
    bad = not isinstance(value, str) or not value.strip() or value in (".", "..")
    if bad or "/" in value or "\\" in value:
        raise ValueError(
            f"{key}={value!r} must be a file name: it is written into the run directory, which "
            "hydra.run.dir=DIR sets"
        )
    return value


def check_file(key: str, path: Path, name: str, what: str = "file") -> Path:
    """``path`` if it is a file, else a ``ValueError`` naming ``key``: a run directory that holds
    ``name`` is answered with that file's path (``resume=DIR`` → ``resume=DIR/checkpoint.pt``)."""
    if path.is_file():
        return path
    if path.is_dir():
        inside = path / name
        if inside.is_file():
            raise ValueError(f"{key}={path} is a directory: its {name} is {key}={inside}")
        raise ValueError(f"{key}={path} is a directory, and it holds no {name}")
    if path.exists():  # a device, a pipe, a socket
        raise ValueError(f"{key}={path} is not a regular file")
    raise ValueError(f"{key}={path}: no such {what}")


def check_list(
    key: str,
    value: Any,
    item: Callable[[str, Any], Any] | None = None,
    *,
    empty: bool = False,
    length: int | None = None,
    distinct: bool = False,
) -> tuple[Any, ...]:
    """``value`` as a tuple if it is a list (non-empty unless ``empty``; of ``length`` items when
    given; without a repeated item when ``distinct``: a list whose items each make runs), each
    item passed through ``item(f"{key}[{i}]", x)``; else a ``ValueError``."""
    if not isinstance(value, list | tuple):
        hint = f" (one item: {key}=[{value}])" if isinstance(value, str | int | float) else ""
        raise ValueError(f"{key}={value!r} must be a list{hint}")
    if length is not None and len(value) != length:
        raise ValueError(f"{key}={list(value)!r} must be a list of {length} values")
    if not value and not empty:
        raise ValueError(f"{key}={list(value)!r} must be a non-empty list")
    out = tuple(item(f"{key}[{i}]", x) if item else x for i, x in enumerate(value))
    if distinct:
        repeated = [x for i, x in enumerate(out) if x in out[:i]]
        if repeated:
            raise ValueError(f"{key}={list(value)!r} repeats {repeated[0]!r}: the same runs twice")
    return out


def numbers(lo: float = -math.inf, hi: float = math.inf, **kw: Any) -> Callable[[str, Any], Any]:
    """An item check for ``check_list``: each item a number in [lo, hi] (``check_number``'s keywords)."""
    return lambda key, x: check_number(key, x, lo, hi, **kw)


def closest(key: str, allowed: Iterable[str], cutoff: float = 0.6) -> str | None:
    """The allowed name closest to ``key`` (None when nothing is close)."""
    found = difflib.get_close_matches(key, sorted(allowed), n=1, cutoff=cutoff)
    return found[0] if found else None


def reject_unknown_keys(prefix: str, keys: Iterable[Any], allowed: Iterable[str]) -> None:
    """Raise a ``ValueError`` naming every key of ``keys`` not in ``allowed`` (with ``prefix``), the
    closest allowed key for each, and the allowed ones. The one check behind every config section."""
    allowed = sorted(allowed)
    extra = sorted(str(k) for k in set(keys) - set(allowed))
    if not extra:
        return
    hints = []
    for k in extra:
        near = closest(k, allowed)
        hints.append(f"{prefix}{k}" + (f" (did you mean {prefix}{near}?)" if near else ""))
    raise ValueError(
        f"unknown key(s) {', '.join(hints)}; allowed: {', '.join(prefix + n for n in allowed)}"
    )


def reset_option(options: Any, name: str = "state") -> Any:
    """``options[name]`` of a gymnasium or PettingZoo ``reset(options=…)`` (None without it); any
    other key is refused naming the closest, as a misspelt option would otherwise be ignored."""
    if options is None:
        return None
    if not isinstance(options, Mapping):
        raise ValueError(f"options={options!r} must be a dict, e.g. {{{name!r}: 5}}")
    reject_unknown_keys("options.", options, (name,))
    return options.get(name)


def build(cls: type, data: Any, prefix: str = "") -> Any:
    """A frozen config dataclass ``cls`` from a plain mapping: unknown keys refused (naming the
    closest), each field from its key — a field whose type is a config dataclass from the nested
    mapping (by its ``from_dict(data, prefix)`` when it has one), a field with ``metadata["build"]``
    by that function of the whole mapping, any other from the value as it is — and missing keys left
    to the field's default. The dataclass's own ``__post_init__`` checks the values.

    Fields with ``metadata["keys"]`` read those keys of the mapping (e.g. ``env`` and ``reward`` for
    one model field); a field starting with ``_`` is never read from the data.
    """
    if not isinstance(data, Mapping):
        raise ValueError(f"{prefix.rstrip('.') or 'config'} must be a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = [f for f in dataclasses.fields(cls) if f.init and not f.name.startswith("_")]
    allowed: set[str] = set()
    for f in fields:
        allowed |= set(f.metadata.get("keys", (f.name,)))
    reject_unknown_keys(prefix, data, allowed)
    kwargs: dict[str, Any] = {}
    for f in fields:
        keys = f.metadata.get("keys", (f.name,))
        if "build" in f.metadata:
            if any(k in data for k in keys):
                kwargs[f.name] = f.metadata["build"](data, prefix)
            continue
        if f.name not in data:
            continue
        value, kind = data[f.name], hints.get(f.name)
        if isinstance(kind, type) and dataclasses.is_dataclass(kind):
            sub = f"{prefix}{f.name}."
            reader = getattr(kind, "from_dict", None)
            value = reader(value, sub) if reader is not None else build(kind, value, sub)
        kwargs[f.name] = value
    return cls(**kwargs)
